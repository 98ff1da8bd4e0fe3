"""Recording a run: what the system publishes (keyframes, frame stats, merges, corrections,
optimized team paths, the team cloud, message sizes) into :class:`RunData`, live (the demo's
monitor) or from the bag the demo records; and the ground truth of a sensor bag.

The same :meth:`RunRecorder.feed` serves live and bag input, so a report re-derived from the bag
(``scripts/evaluate``) equals the live one.
"""

from __future__ import annotations

import json
import os
import threading

import numpy as np

from ..evaluation import EvaluationError
from ..evaluation.run_data import RobotRun, RunData, RunInput
from ..playback import GROUND_TRUTH_TOPIC
from ..team.results import TYPE_LINK, TYPE_LOOP
from .convert import (
    MessageError,
    cloud_colours_from_msg,
    cloud_from_msg,
    description_from_msg,
    grid_from_msg,
    pose_from_msg,
    transform_from_msg,
)
from .recorded import keyframe_seen

ROBOT_TOPICS = {  # relative to /robot_k; the message type of each
    "keyframes": "coop_slam/KeyframeMessage",
    "frame_stats": "coop_slam/FrameStats",
    "correction": "coop_slam/MapCorrection",
    "pose": "geometry_msgs/PoseStamped",
    "path": "nav_msgs/Path",
    "local_map": "sensor_msgs/PointCloud2",
    "keyframe_ack": "coop_slam/KeyframeAck",
    "description": "coop_slam/RobotDescription",
}
# What the server publishes per robot: recorded on the station with --hosts (the rest of a robot's
# topics on its own host, so that recording never pulls them across the radio).
STATION_ROBOT_TOPICS = ("correction", "keyframe_ack")
TEAM_TOPICS = {
    "/merge_events": "coop_slam/MergeEvent",
    "/server/stats": "std_msgs/String",
    "/team_map/cloud": "sensor_msgs/PointCloud2",
    "/team_map/dense": "sensor_msgs/PointCloud2",
    "/team_map/grid": "nav_msgs/OccupancyGrid",
    "/team_map/markers": "visualization_msgs/MarkerArray",
    "/robot_sightings": "coop_slam/RobotSighting",
    "/player/done": "std_msgs/Bool",
}


def message_class(type_name: str):
    """The generated class of a message type name (``pkg/Name``)."""
    import importlib

    pkg, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class RunRecorder:
    """Builds :class:`RunData` from what the system publishes: :meth:`feed` takes one message with
    the sim time it was seen at and its serialized size; the same code serves live and bag input."""

    def __init__(self, robot_ids: list[int], clock_offsets: dict | None = None):
        # clock_offsets: robot id -> how far its clock ran ahead of the master's (rehearsed) [s]:
        # its own stamps (keyframes, path) are read back on the master's clock, as the data's.
        offsets = {int(r): float(s) for r, s in (clock_offsets or {}).items()}
        self.run = RunData(
            robots={int(r): RobotRun(clock_offset_s=offsets.get(int(r), 0.0)) for r in robot_ids}
        )
        self.lock = threading.Lock()
        self.done = False  # the player said it has played everything
        self.newest_frame_s = 0.0  # data time: the newest frame any client has finished

    def topics(self, where: str = "all") -> dict[str, str]:
        """Topic -> message type of everything recorded (the demo's rosbag takes the same list):
        ``all``, or what is published on the ``station`` or on the ``robot`` hosts."""
        out = {
            f"/robot_{r}/{t}": ty
            for r in self.run.robots
            for t, ty in ROBOT_TOPICS.items()
            if where == "all" or (t in STATION_ROBOT_TOPICS) == (where == "station")
        }
        if where != "robot":
            out.update({f"/team_map/robot_{r}/path": "nav_msgs/Path" for r in self.run.robots})
            out.update(TEAM_TOPICS)
        return out

    def feed(self, topic: str, msg, t_s: float, nbytes: int) -> None:
        with self.lock:
            self.run.topic_bytes.setdefault(topic, []).append((float(t_s), int(nbytes)))
            parts = topic.strip("/").split("/")
            if topic == "/team_map/cloud":
                self._on_cloud(msg)
            elif topic == "/team_map/dense":
                self._on_dense(msg)
            elif topic == "/team_map/grid":
                self._on_grid(msg)
            elif topic == "/merge_events":
                self._on_merge(msg)
            elif topic == "/server/stats":
                self.run.server_stats = json.loads(msg.data)
            elif topic == "/player/done":
                self.done = self.done or bool(msg.data)
            elif len(parts) == 3 and parts[0] == "team_map" and parts[2] == "path":
                self._on_team_path(msg, int(parts[1].split("_")[1]))
            elif len(parts) == 2 and parts[0].startswith("robot_"):
                robot_id = int(parts[0].split("_")[1])
                handler = getattr(self, f"_on_{parts[1]}", None)
                if robot_id in self.run.robots and handler is not None:
                    handler(msg, self.run.robots[robot_id], t_s, nbytes)

    def _on_frame_stats(self, msg, r: RobotRun, t_s, nbytes) -> None:
        if getattr(msg, "dropped", False):  # busy client: a newer frame was tracked instead
            r.frames_dropped += 1
            return
        frame = not msg.header.stamp.is_zero()  # stamp 0: the delivery counters alone
        r.frames += frame
        frame_s = msg.header.stamp.to_sec() - r.clock_offset_s  # (on the master's clock)
        self.newest_frame_s = max(self.newest_frame_s, frame_s)
        sent = int(getattr(msg, "keyframes_sent", 0))
        held_back = int(getattr(msg, "keyframes_held_back", 0))  # not in older bags
        if not r.keyframes_sent_sessions or sent < r.keyframes_sent_sessions[-1]:
            r.keyframes_sent_sessions.append(sent)  # the first, or a restarted client
            r.held_back_sessions.append(held_back)
        else:
            r.keyframes_sent_sessions[-1] = sent
            r.held_back_sessions[-1] = held_back
        r.unacked = int(getattr(msg, "unacked", 0))
        backlog = int(getattr(msg, "mapping_backlog", 0))
        r.mapping_backlog_max = max(r.mapping_backlog_max, backlog)
        r.frames_mapping_behind += backlog > 1
        if msg.track_ms > 0:
            r.track_ms.append(float(msg.track_ms))
        if not msg.tracking_ok and r.first_keyframe is not None:
            r.lost_frames += 1

    def _on_description(self, msg, r: RobotRun, t_s, nbytes) -> None:
        try:
            r.T_base_cam = description_from_msg(msg).T_base_cam
        except MessageError:
            pass  # the report then places its path with the run's one mount

    def _on_cloud(self, msg) -> None:
        try:
            self.run.team_cloud = (cloud_from_msg(msg), cloud_colours_from_msg(msg))
        except MessageError:
            pass  # a malformed cloud is no cloud: the last good one stays

    def _on_dense(self, msg) -> None:
        try:
            self.run.dense_cloud = (cloud_from_msg(msg), cloud_colours_from_msg(msg))
        except MessageError:
            pass  # as a malformed cloud

    def _on_grid(self, msg) -> None:
        try:
            self.run.grid = grid_from_msg(msg)
            self.run.grid_z_m = float(msg.info.origin.position.z)
        except MessageError:
            pass

    def _on_keyframes(self, msg, r: RobotRun, t_s, nbytes) -> None:
        r.kf_bytes.append((float(t_s), int(nbytes)))
        kf = keyframe_seen(msg)
        count, total = r.kf_kinds.get(kf.kind, (0, 0))
        r.kf_kinds[kf.kind] = (count + 1, total + int(nbytes))
        if kf.removal:
            r.keyframes.pop(kf.keyframe_id, None)
            r.keyframe_points.pop(kf.keyframe_id, None)
            return
        if kf.T_map_cam is None:
            return
        kf = kf._replace(stamp_s=kf.stamp_s - r.clock_offset_s)
        r.sensor = kf.sensor or r.sensor
        r.keyframes[kf.keyframe_id] = (kf.stamp_s, kf.T_map_cam)
        if kf.points_cam is not None:  # (a delta update saw the same, in the camera frame)
            r.keyframe_points[kf.keyframe_id] = kf.points_cam
        r.keyframe_stamps[kf.keyframe_id] = kf.stamp_s
        r.keyframe_segments[kf.keyframe_id] = int(kf.map_segment)
        if r.first_keyframe is None:
            r.first_keyframe = (kf.stamp_s, kf.T_map_cam)

    def _on_path(self, msg, r: RobotRun, t_s, nbytes) -> None:
        path = []
        for ps in msg.poses:
            try:
                stamp_s = ps.header.stamp.to_sec() - r.clock_offset_s
                path.append((ps.header.seq, stamp_s, pose_from_msg(ps.pose)))
            except MessageError:
                continue
        r.path = path

    def _on_correction(self, msg, r: RobotRun, t_s, nbytes) -> None:
        r.T_world_map = transform_from_msg(msg.T_world_map) if msg.merged else None
        r.map_scale = float(msg.map_scale) if msg.map_scale > 0 else 1.0

    def _on_team_path(self, msg, robot_id: int) -> None:
        r = self.run.robots.get(robot_id)
        if r is None:
            return
        if msg.header.frame_id != "world":
            r.team_keyframes = {}
            return
        poses = {}
        for ps in msg.poses:
            try:
                poses[ps.header.seq] = (ps.header.stamp.to_sec(), pose_from_msg(ps.pose))
            except MessageError:
                continue
        r.team_keyframes = poses

    def _on_merge(self, msg) -> None:
        # Stamps of the matched keyframes, culled ones included (the client may cull a keyframe
        # while the merge that rests on it is on its way).
        stamps = []
        for robot, kf in ((msg.robot_a, msg.keyframe_a), (msg.robot_b, msg.keyframe_b)):
            known = self.run.robots[robot].keyframe_stamps if robot in self.run.robots else {}
            stamps.append(known.get(kf))
        if msg.type in (TYPE_LINK, TYPE_LOOP):
            self.run.links.append(
                {
                    "type": msg.type,
                    "robots": [msg.robot_a, msg.robot_b],
                    "keyframe_stamps": stamps,
                    "stamp_s": msg.header.stamp.to_sec(),
                    "T_camA_camB": transform_from_msg(msg.T_camA_camB),
                }
            )
            return
        # Keyed by side: a robot's new map segment merges with its own older one (a == b).
        stamps = {s: t for s, t in zip("ab", stamps) if t is not None}
        self.run.merges.append(
            {
                "type": msg.type,
                "robot_a": msg.robot_a,
                "robot_b": msg.robot_b,
                "keyframe_a": msg.keyframe_a,
                "keyframe_b": msg.keyframe_b,
                "keyframe_stamps": stamps,
                "stamp_s": msg.header.stamp.to_sec(),
                "T_mapA_mapB": transform_from_msg(msg.T_mapA_mapB),
                "T_camA_camB": transform_from_msg(msg.T_camA_camB),
                "scale": getattr(msg, "scale", None),  # not in bags recorded before it
                "published_s": self.newest_frame_s or None,  # data time it was published at
            }
        )


def run_data_from_bag(
    bag_paths: str | list[str], robot_ids: list[int], clock_offsets: dict | None = None
) -> RunData:
    """Replay a recorded run through :class:`RunRecorder` (bag time is the sim time); several
    bags (one per host) are read as one, in time order. ``clock_offsets``: see RunRecorder."""
    import heapq

    import rosbag

    paths = [bag_paths] if isinstance(bag_paths, str) else list(bag_paths)
    rec = RunRecorder(robot_ids, clock_offsets)
    topics = list(rec.topics())
    bags = []
    try:
        for path in paths:
            if not os.path.isfile(path):
                raise EvaluationError(f"bag not found: {path}")
            try:
                bags.append(rosbag.Bag(path))
            except (rosbag.ROSBagException, OSError) as exc:
                raise EvaluationError(f"cannot read bag {path}: {exc}") from exc
        streams = [bag.read_messages(topics=topics, raw=True) for bag in bags]
        for topic, raw, t in heapq.merge(*streams, key=lambda m: m[2]):
            msg = raw[4]()  # the bag's own definition: runs recorded by older code read too
            msg.deserialize(raw[1])
            rec.feed(topic, msg, t.to_sec(), len(raw[1]))
    finally:
        for bag in bags:
            bag.close()
    return rec.run


def run_bags(results: str) -> list[str]:
    """The bags of a demo results folder: ``run.bag``, and with ``--hosts`` each robot host's
    ``run_robot_<k>.bag``."""
    import glob

    return [os.path.join(results, "run.bag")] + sorted(
        glob.glob(os.path.join(results, "run_robot_*.bag"))
    )


def read_bag_input(bag_path: str) -> RunInput:
    """The run input of a sensor bag (``scripts/demo --bag``): robots from its camera topics
    (:mod:`coop_slam.bag_topics`), ground truth from ``/robot_<k>/ground_truth/pose`` (as the
    player publishes it) or, for the one camera of a TUM RGB-D benchmark bag, from its ``/tf``
    ``world -> kinect`` (the motion capture's)."""
    import rosbag

    from ..bag_topics import bag_cameras, describe_drivers

    if not os.path.isfile(bag_path):
        raise EvaluationError(f"bag not found: {bag_path}")
    try:
        bag = rosbag.Bag(bag_path)
    except (rosbag.ROSBagException, OSError) as exc:
        raise EvaluationError(f"cannot read bag {bag_path}: {exc}") from exc
    with bag:
        topics = bag.get_type_and_topic_info().topics
        cameras = bag_cameras(topics)
        if not cameras:
            raise EvaluationError(
                f"bag {bag_path} has no camera topics the player knows ({describe_drivers()}); "
                f"it has: {', '.join(sorted(topics)) or 'nothing'}"
            )
        robot_ids = [c.robot_id for c in cameras]
        gt_topics = {t: int(m.group(1)) for t in topics if (m := GROUND_TRUTH_TOPIC.match(t))}
        samples = {rid: ([], []) for rid in robot_ids}
        if len(cameras) == 1 and cameras[0].driver.name == "tum" and "/tf" in topics:
            samples[robot_ids[0]] = _tum_ground_truth(bag)
        if gt_topics:
            for topic, msg, _ in bag.read_messages(topics=list(gt_topics)):
                rid = gt_topics[topic]
                if rid not in samples:
                    continue
                try:
                    T = pose_from_msg(msg.pose, f"{topic} pose")
                except MessageError:
                    continue  # a NaN ground-truth sample is no sample
                samples[rid][0].append(msg.header.stamp.to_sec())
                samples[rid][1].append(T)
        gts = {}
        for rid, (stamps, poses) in samples.items():
            order = np.argsort(stamps)
            gts[rid] = (
                np.asarray(stamps, float)[order],
                np.asarray(poses, float).reshape(-1, 4, 4)[order],
            )
        return RunInput(
            robot_ids,
            sum(topics[c.image_topic].message_count for c in cameras),
            bag.get_start_time(),
            bag.get_end_time(),
            gts,
            sensors=[c.sensor for c in cameras],
        )


def _tum_ground_truth(bag) -> tuple[list, list]:
    """(stamps, T_world_kinect) of a TUM RGB-D benchmark bag's ``/tf`` (its ground truth: the
    colour camera's optical centre, as its groundtruth.txt)."""
    stamps, poses = [], []
    for _, msg, _ in bag.read_messages(topics=["/tf"]):
        for tf in msg.transforms:
            if (
                tf.header.frame_id.strip("/") == "world"
                and tf.child_frame_id.strip("/") == "kinect"
            ):
                try:
                    poses.append(transform_from_msg(tf.transform, "/tf world -> kinect"))
                except MessageError:
                    continue
                stamps.append(tf.header.stamp.to_sec())
    return stamps, poses
