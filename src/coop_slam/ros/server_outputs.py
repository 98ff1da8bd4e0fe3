"""What the server's worker decides, published on ROS: merge events, TF ``world -> robot_k/map``
and each robot's correction, the team map (cloud, paths, markers; the dense cloud and occupancy
grid), acknowledgements, keyframe requests and stats. Translation only: the decisions are
:class:`coop_slam.team.worker.ServerWorker`'s.
"""

from __future__ import annotations

import dataclasses
import json
import threading

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String

from ..team.dense_map import DenseMap
from ..team.fusion import robot_colours
from ..team.results import TYPE_LOOP, TYPE_OVERLAP
from ..team.view import marker_scale
from ..team.worker import RobotCorrection, ServerOutputs, TeamEvent, TeamMapView
from .convert import cloud_to_msg, grid_to_msg, pose_to_msg, transform_stamped, transform_to_msg
from .validation import RejectCounter
from .wire_bridge import to_ros

EDGE_COLOURS = {
    "place_recognition": (1.0, 0.9, 0.1, 1.0),
    "rendezvous": (1.0, 0.2, 1.0, 1.0),
    TYPE_OVERLAP: (1.0, 0.6, 0.1, 1.0),
    TYPE_LOOP: (0.2, 1.0, 1.0, 1.0),
}


class RosServerOutputs(ServerOutputs):
    """Publishers of the server node; per-robot ones are made when the worker names its robots."""

    wants_team_map = True

    def __init__(self, low_bandwidth: bool, on_robots=None):
        """``on_robots(robot_ids)``: called after the robots' publishers exist (the node
        subscribes to their keyframes then)."""
        import tf2_ros
        from nav_msgs.msg import OccupancyGrid, Path
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        from coop_slam.msg import KeyframeAck, KeyframeRequest, MapCorrection, MergeEvent

        self._msgs = dict(
            Path=Path,
            MapCorrection=MapCorrection,
            MergeEvent=MergeEvent,
            Ack=KeyframeAck,
            OccupancyGrid=OccupancyGrid,
        )
        self._KeyframeRequest = KeyframeRequest
        self.low_bandwidth, self.on_robots = low_bandwidth, on_robots
        self.rejects = RejectCounter("server")
        self.tf = tf2_ros.StaticTransformBroadcaster()
        self.pub_merge = rospy.Publisher("/merge_events", MergeEvent, queue_size=20, latch=True)
        self.pub_stats = rospy.Publisher("/server/stats", String, queue_size=5, latch=True)
        self.pub_cloud = rospy.Publisher("/team_map/cloud", PointCloud2, queue_size=1, latch=True)
        self.pub_dense = rospy.Publisher("/team_map/dense", PointCloud2, queue_size=1, latch=True)
        self.pub_grid = rospy.Publisher("/team_map/grid", OccupancyGrid, queue_size=1, latch=True)
        self.pub_markers = rospy.Publisher(
            "/team_map/markers", MarkerArray, queue_size=1, latch=True
        )
        self.pub_path, self.pub_corr, self.pub_ack, self.pub_request = {}, {}, {}, {}
        self.pub_robot_grid = {}
        self._lock = threading.Lock()  # acknowledgements come from the callback threads too

    def robots(self, robot_ids: list[int]) -> None:
        with self._lock:
            for r in robot_ids:
                if r in self.pub_path:
                    continue
                self.pub_path[r] = rospy.Publisher(
                    f"/team_map/robot_{r}/path", self._msgs["Path"], queue_size=1, latch=True
                )
                self.pub_robot_grid[r] = rospy.Publisher(
                    f"/robot_{r}/team_grid", self._msgs["OccupancyGrid"], queue_size=1, latch=True
                )
                self.pub_corr[r] = rospy.Publisher(
                    f"/robot_{r}/correction", self._msgs["MapCorrection"], queue_size=5, latch=True
                )
                self.pub_ack[r] = rospy.Publisher(
                    f"/robot_{r}/keyframe_ack", self._msgs["Ack"], queue_size=5, latch=True
                )
                # Any robot may send place signatures (low-bandwidth mode, or what its radio
                # budget held back), and the server then asks for whole keyframes.
                self.pub_request[r] = rospy.Publisher(
                    f"/robot_{r}/keyframe_request",
                    self._KeyframeRequest,
                    queue_size=10,
                    latch=True,
                )
        if self.on_robots is not None:
            self.on_robots(robot_ids)

    def reject(self, where: str, why: str) -> None:
        self.rejects.reject(where, why)

    def ack(self, ack) -> None:
        with self._lock:
            pub = self.pub_ack.get(ack.robot_id)
            if pub is not None:
                pub.publish(to_ros(ack))

    def request(self, request) -> None:
        pub = self.pub_request.get(request.robot_id)
        if pub is not None:
            pub.publish(to_ros(request))

    def event(self, e: TeamEvent) -> None:
        """A merge, link or loop as a MergeEvent (field for field; the core logged it)."""
        fields = {f.name: getattr(e, f.name) for f in dataclasses.fields(e) if f.name != "stamp_s"}
        for name in ("T_mapA_mapB", "T_camA_camB"):
            fields[name] = transform_to_msg(fields[name])
        msg = self._msgs["MergeEvent"](**fields)
        msg.header.stamp, msg.header.frame_id = rospy.Time.from_sec(e.stamp_s), "world"
        self.pub_merge.publish(msg)

    def corrections(self, corrections: list[RobotCorrection], stamp_s: float) -> None:
        stamp = rospy.Time.from_sec(stamp_s) if stamp_s else rospy.Time.now()
        transforms = []
        for c in corrections:
            if c.merged:
                transforms.append(
                    transform_stamped(c.T_group_map, "world", f"robot_{c.robot_id}/map", stamp)
                )
            corr = self._msgs["MapCorrection"](
                robot_id=c.robot_id,
                merged=c.merged,
                T_world_map=transform_to_msg(c.T_group_map),
                keyframe_ids=list(c.keyframe_poses),
                keyframe_poses=[pose_to_msg(P) for P in c.keyframe_poses.values()],
                map_scale=c.map_scale,
                metric=c.metric,
            )
            corr.header.stamp, corr.header.frame_id = stamp, "world"
            pub = self.pub_corr.get(c.robot_id)
            if pub is not None:
                pub.publish(corr)
        if transforms:
            self.tf.sendTransform(transforms)

    def cloud(self, cloud: tuple, stamp_s: float) -> None:
        """In the map builder's thread: a built cloud goes out."""
        if rospy.is_shutdown():  # built while the node stopped: nowhere to go
            return
        points, rgb, _ = cloud
        self.pub_cloud.publish(cloud_to_msg(points, "world", rospy.Time.from_sec(stamp_s), rgb))

    def dense_map(self, dense: DenseMap, stamp_s: float) -> None:
        """In the map builder's thread: the dense cloud and the world group's grid go out."""
        if rospy.is_shutdown():
            return
        stamp = rospy.Time.from_sec(stamp_s)
        rgb = robot_colours(dense.robot_ids)
        self.pub_dense.publish(cloud_to_msg(dense.points, "world", stamp, rgb))
        if dense.grid is not None:
            self.pub_grid.publish(grid_to_msg(dense.grid, "world", stamp, dense.floor_z_m))
        for r, grid in dense.robot_grids.items():
            pub = self.pub_robot_grid.get(r)
            if pub is not None:
                pub.publish(grid_to_msg(grid, f"robot_{r}/map", stamp))

    def team_map(self, view: TeamMapView, stamp_s: float) -> None:
        stamp = rospy.Time.from_sec(stamp_s) if stamp_s else rospy.Time.now()
        for r, (frame, poses) in view.robot_paths.items():
            path = self._msgs["Path"]()
            path.header.stamp, path.header.frame_id = stamp, frame
            for kf, (kf_stamp_s, T) in poses.items():
                ps = PoseStamped(pose=pose_to_msg(T))
                ps.header.stamp = rospy.Time.from_sec(kf_stamp_s)
                ps.header.frame_id = frame
                ps.header.seq = kf  # the keyframe id
                path.poses.append(ps)
            pub = self.pub_path.get(r)
            if pub is not None:
                pub.publish(path)
        self.pub_markers.publish(team_markers(view, stamp))

    def stats(self, stats: dict) -> None:
        self.pub_stats.publish(String(data=json.dumps(stats)))


def team_markers(view: TeamMapView, stamp):
    """Paths (a line per map), labels and the edges of merges, links and loops, in ``world``."""
    from geometry_msgs.msg import Point
    from std_msgs.msg import ColorRGBA
    from visualization_msgs.msg import Marker, MarkerArray

    size = marker_scale({m.map_id: m.path_xyz for m in view.maps})
    markers = MarkerArray()
    clear = Marker(action=Marker.DELETEALL)
    clear.header.frame_id = "world"
    markers.markers.append(clear)

    def marker(ns, mid, kind, rgba, scale):
        m = Marker(ns=ns, id=mid, type=kind, action=Marker.ADD)
        m.header.frame_id, m.header.stamp = "world", stamp
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = scale
        m.color = ColorRGBA(*rgba)
        return m

    for m in view.maps:  # per map (a robot's map segments apart)
        c = robot_colours([m.robot_id])[0] / 255.0
        line = marker("paths", m.map_id, Marker.LINE_STRIP, (*c, 1.0), 0.04 * size)
        line.points = [Point(*p) for p in np.asarray(m.path_xyz, float)]
        markers.markers.append(line)
        label = marker("labels", m.map_id, Marker.TEXT_VIEW_FACING, (1, 1, 1, 1), 0.4 * size)
        label.text = f"robot_{m.robot_id}" + ("" if m.merged else " (unmerged)")
        if m.segment is not None:
            label.text += f" segment {m.segment}"
        if not m.metric:
            label.text += " (own scale)"  # a monocular map not merged with a metric one
        last = np.asarray(m.path_xyz[-1], float)
        label.pose.position = Point(last[0], last[1], last[2] + 0.6 * size)
        markers.markers.append(label)
    for k, (kind, pa, pb) in enumerate(view.edges):
        edge = marker(
            "merges", k, Marker.LINE_LIST, EDGE_COLOURS.get(kind, (1, 1, 1, 1)), 0.06 * size
        )
        edge.points = [Point(*pa), Point(*pb)]
        markers.markers.append(edge)
    return markers
