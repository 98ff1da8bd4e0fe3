"""What a client shows of itself: its camera pose (``/robot_k/pose``), TF ``robot_k/map ->
robot_k/odom -> robot_k/base_link -> robot_k/camera_optical`` (REP-105; names and who publishes
which edge: :mod:`coop_slam.frames`, a base with its own odometry), its keyframe path and
local cloud, each with the team map's correction laid over it (pose-graph sharing,
:mod:`coop_slam.vo.shared_poses`): the odometry goes on in its own frame.

The odometry's own map frame is its first camera frame; ``robot_k/map`` is the robot body at
start (z up), so maps are upright in RViz. ``map -> odom`` is identity until the server sends a
correction. A monocular map has no metric scale: poses, paths and clouds are in its unit (the
median depth of its first two keyframes' points) until the server gives it metres.
"""

from __future__ import annotations

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path

from ..frames import FrameConfig, T_map_odom_over
from ..geometry import invert, transform_points
from ..vo.shared_poses import NEWEST, SharedPoses
from ..wire.record import ACTION_NEW, ACTION_REMOVE
from .convert import (
    MessageError,
    cloud_to_msg,
    pose_from_msg,
    pose_to_msg,
    transform_from_msg,
    transform_stamped,
)
from .validation import RejectCounter


class PoseOutput:
    def __init__(
        self,
        robot_id: int,
        T_base_cam: np.ndarray,
        cloud_period_s: float,
        path_period_s: float,
        rejects: RejectCounter,
        frames: FrameConfig | None = None,
    ):
        import tf2_ros
        from sensor_msgs.msg import PointCloud2

        self.robot_id, self.T_base_cam, self.rejects = robot_id, T_base_cam, rejects
        name = f"robot_{robot_id}"
        self.frames = frames or FrameConfig()
        names = self.frames.names(robot_id)
        self.map_frame, self.odom_frame = names.map, names.odom
        self.base_frame, self.cam_frame = names.base, names.camera
        self.cloud_period_s = cloud_period_s
        # The path holds every keyframe: rebuilt at each keyframe change it cost milliseconds on
        # the frames that insert keyframes and grew with the map (docs/tuning.md).
        self.path_period_s = path_period_s
        self.tf = tf2_ros.TransformBroadcaster()
        self.static_tf = tf2_ros.StaticTransformBroadcaster()
        if self.frames.publish_camera_tf:
            self.static_tf.sendTransform(
                transform_stamped(T_base_cam, self.base_frame, self.cam_frame, rospy.Time(0))
            )
        self.tf_buffer = None
        if self.frames.external_odom:  # the base's own odom -> base_link, to publish over it
            self.tf_buffer = tf2_ros.Buffer(cache_time=rospy.Duration(30.0))
            self.tf_listener = tf2_ros.TransformListener(self.tf_buffer)
            self._tf_errors = (
                tf2_ros.LookupException,
                tf2_ros.ConnectivityException,
                tf2_ros.ExtrapolationException,
            )
        self.pub_pose = rospy.Publisher(f"/{name}/pose", PoseStamped, queue_size=10)
        self.pub_path = rospy.Publisher(f"/{name}/path", Path, queue_size=1, latch=True)
        self.pub_cloud = rospy.Publisher(
            f"/{name}/local_map", PointCloud2, queue_size=1, latch=True
        )
        self.shared = SharedPoses()
        self.kf_poses: dict[int, tuple[float, np.ndarray]] = {}  # id -> (stamp, T_map_cam)
        self.segment_starts = False  # a new map segment begins with the next new keyframe
        self.path_due = False  # keyframes changed since the path last went out
        self.corrected_due = False  # a correction's path and cloud have not gone yet
        self._corrected_stamp = None
        self.last_cloud_s = self.last_path_s = -1e9
        self.corrections_applied = 0
        self.T_world_map = None

    # --- the odometry's keyframes -----------------------------------------------------------------
    def note(self, notes) -> None:
        """What the uplink made of the odometry's events (see coop_slam.uplink.engine.Note)."""
        for n in notes:
            if n.kind == "segment":
                self.segment_starts = True  # with the next new keyframe
            elif n.kind == "keyframe":
                rec = n.record
                if self.segment_starts and rec.action == ACTION_NEW:
                    self.shared.start_segment(rec.keyframe_id)
                    self.segment_starts = False
                if rec.action == ACTION_REMOVE:
                    self.kf_poses.pop(rec.keyframe_id, None)
                    self.shared.forget(rec.keyframe_id)
                else:
                    self.kf_poses[rec.keyframe_id] = (rec.stamp_s, rec.T_map_cam)
                self.path_due = True

    def frame(self, stamp, res, vo, kf_id_base: int) -> None:
        """After a tracked frame: the pose and TF, the path and the cloud when due."""
        t_s = stamp.to_sec()
        if res.ok:  # first: the pose is what the robot's other nodes wait for
            self.publish_pose(stamp, self.T_base_cam @ res.T_map_cam)
        if self.corrected_due:
            self.publish_correction(vo, kf_id_base)
            self.last_path_s = self.last_cloud_s = t_s
        if self.path_due and t_s - self.last_path_s >= self.path_period_s:
            self.last_path_s = t_s
            self.publish_path(vo, kf_id_base)
        if t_s - self.last_cloud_s >= self.cloud_period_s:
            self.last_cloud_s = t_s
            self.publish_cloud(stamp, vo, kf_id_base)

    # --- the team map's correction ----------------------------------------------------------------
    def correction(self, msg, vo, kf_id_base: int, publish_now: bool = True) -> None:
        """The server's correction of this robot (with the tracker's lock held). Its path and
        cloud go now, or (``publish_now`` False: frames are coming) with the next frame, so that
        the tracker does not wait for them."""
        if msg.robot_id != self.robot_id:
            self.rejects.reject(
                "correction", f"correction for robot {msg.robot_id} on robot_{self.robot_id}'s"
            )
            return
        try:
            T_world_map = transform_from_msg(msg.T_world_map, "T_world_map")
            poses = [pose_from_msg(p, "keyframe pose") for p in msg.keyframe_poses]
        except MessageError as exc:
            self.rejects.reject("correction", str(exc))
            return
        if len(poses) != len(msg.keyframe_ids):
            self.rejects.reject("correction", "keyframe_ids and keyframe_poses differ in length")
            return
        self.T_world_map = T_world_map if msg.merged else None
        odom = self._odom_poses(vo, kf_id_base)
        if self.shared.receive(dict(zip(msg.keyframe_ids, poses)), odom):
            self.corrections_applied += 1
            self.corrected_due, self._corrected_stamp = True, msg.header.stamp
            if publish_now:
                self.publish_correction(vo, kf_id_base)

    def publish_correction(self, vo, kf_id_base: int) -> None:
        """The path and cloud as the newest correction placed them, if they have not gone yet
        (the tracker's lock held)."""
        if not self.corrected_due:
            return
        self.corrected_due = False
        self.publish_path(vo, kf_id_base)
        if vo is not None:
            self.publish_cloud(self._corrected_stamp, vo, kf_id_base)

    # --- publishing -------------------------------------------------------------------------------
    def publish_pose(self, stamp, T_odom_cam: np.ndarray) -> None:
        T_map_odom = self.shared.T_map_odom
        msg = PoseStamped(pose=pose_to_msg(T_map_odom @ T_odom_cam))
        msg.header.stamp, msg.header.frame_id = stamp, self.map_frame
        self.pub_pose.publish(msg)
        T_odom_base = T_odom_cam @ invert(self.T_base_cam)
        if self.tf_buffer is not None:
            self._publish_over_external_odom(stamp, T_map_odom @ T_odom_base)
            return
        self.tf.sendTransform(
            [
                transform_stamped(T_map_odom, self.map_frame, self.odom_frame, stamp),
                transform_stamped(T_odom_base, self.odom_frame, self.base_frame, stamp),
            ]
        )

    def _publish_over_external_odom(self, stamp, T_map_base: np.ndarray) -> None:
        """map -> odom over the base's own odom -> base_link at the image's stamp."""
        try:
            tf = self.tf_buffer.lookup_transform(
                self.odom_frame, self.base_frame, stamp, rospy.Duration(0.05)
            )
        except self._tf_errors as exc:
            rospy.logwarn_throttle(
                10.0,
                f"client robot_{self.robot_id}: external_odom: no {self.odom_frame} -> "
                f"{self.base_frame} at the image's stamp ({exc}); is the base's odometry "
                "running, and are the clocks of camera and base the same?",
            )
            return
        T_odom_base = transform_from_msg(tf.transform, "odom -> base_link")
        self.tf.sendTransform(
            transform_stamped(
                T_map_odom_over(T_map_base, T_odom_base), self.map_frame, self.odom_frame, stamp
            )
        )

    def _odom_poses(self, vo, kf_id_base: int) -> dict[int, np.ndarray]:
        """Our keyframes' poses in robot_k/odom (message ids): those of the current map segment
        as the odometry has them now, older ones as sent."""
        poses = {kid: T for kid, (_, T) in self.kf_poses.items()}
        if vo is not None:
            for k, T in vo.keyframe_poses().items():
                if k + kf_id_base in poses:
                    poses[k + kf_id_base] = self.T_base_cam @ T
        return poses

    def publish_path(self, vo, kf_id_base: int) -> None:
        """Our keyframes in robot_k/map, each with the team map's correction."""
        self.path_due = False
        path = Path()
        path.header.frame_id = self.map_frame
        T_cam_base = invert(self.T_base_cam)
        poses = self.shared.keyframe_poses(self._odom_poses(vo, kf_id_base))
        for kid in sorted(poses):
            ps = PoseStamped(pose=pose_to_msg(poses[kid] @ T_cam_base))
            stamp_s = self.kf_poses[kid][0]
            ps.header.stamp, ps.header.frame_id = rospy.Time.from_sec(stamp_s), self.map_frame
            ps.header.seq = kid  # the keyframe's id, as in the team map's paths
            path.poses.append(ps)
        if path.poses:
            path.header.stamp = path.poses[-1].header.stamp
        self.pub_path.publish(path)

    def publish_cloud(self, stamp, vo, kf_id_base: int) -> None:
        if self.shared.corrected:
            xyz, ref = vo.map_points_with_reference()
            # A point no keyframe observes any more goes with where the robot is now.
            ids = np.where(ref > 0, ref + kf_id_base, NEWEST)
            pts = self.shared.points(transform_points(self.T_base_cam, xyz), ids)
        else:  # nothing to lay over (finding each point's reference keyframe takes a while)
            pts = transform_points(self.T_base_cam, vo.map_point_arrays()[1])
        self.pub_cloud.publish(cloud_to_msg(pts, self.map_frame, stamp))
