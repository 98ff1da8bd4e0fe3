"""Client node: visual odometry on one robot's RGB-D, stereo or monocular camera, publishing
keyframes, pose, TF, path and cloud.

Inputs (``~sensor``): ``rgbd`` -- ``camera/color/image_raw``, ``camera/depth/image_raw`` (registered
to colour) and ``camera/color/camera_info``; ``stereo`` -- the ROS stereo conventions of a
rectified pair, ``camera/left/image_rect``, ``camera/right/image_rect``,
``camera/left/camera_info``, ``camera/right/camera_info`` (the baseline from the right camera's
projection matrix); ``mono`` -- one image, ``camera/color/image_raw`` and
``camera/color/camera_info``. Colour or grey images.

A monocular map has no metric scale (its unit is the median depth of the first two keyframes'
points): poses, paths, clouds and keyframes are in that unit, and the keyframes say so by their
camera's sensor type (``CameraModel.SENSOR_MONO``); only the server can give them metres.

Robot k's topics live under ``/robot_k`` and its frames are ``robot_k/...``, whatever namespace the
node is started in: the server finds a robot by its id alone. Frames (REP-105):
``robot_k/map`` -> ``robot_k/odom`` -> ``robot_k/base_link`` -> ``robot_k/camera_optical``. The
odometry's own map frame is the first camera frame; this node re-expresses everything in
``robot_k/map``, defined as the robot body at start (z up), so maps are upright in RViz.
``map -> odom`` is identity until the server sends a correction.

Keyframe messages are numbered (client session and sequence, :mod:`coop_slam.delivery`): the
client keeps those the server has not acknowledged on ``/robot_k/keyframe_ack`` (at most
``~max_unacked``) and sends each again ``~resend_after_s`` after it was sent, then after twice
as long, up to ``~max_resend_after_s`` (at most ``~resend_window`` at once), so a server that
restarts or a radio that drops messages loses nothing and a lagging server is not flooded; not
those the server says it has received (the same topic), while that server run stores them. A
restarted client continues above the keyframe ids and map segments the server has stored for its
robot, in a new map segment.
"""

from __future__ import annotations

import collections
import threading
import time

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Bool

from ..config import load_yaml_config
from ..errors import CoopSlamError
from ..geometry import T_base_cam_of, invert, transform_points
from ..playback import PLAYABLE_SENSORS, camera_topics
from ..vo.shared_poses import NEWEST, SharedPoses
from .convert import (
    MessageError,
    camera_from_info,
    cloud_to_msg,
    depth_from_msg,
    image_from_msg,
    keyframe_to_msg,
    pose_from_msg,
    pose_to_msg,
    stereo_camera_from_infos,
    transform_from_msg,
    transform_stamped,
)
from .log_bridge import forward_core_logs
from .validation import RejectCounter

# How long a frame that came before any camera info waits for one [s]: a camera publishes its
# info with every frame, so it is at most a frame or a loaded machine's scheduling delay behind.
CAMERA_INFO_WAIT_S = 2.0


class ClientNode:
    def __init__(self):
        from coop_slam.msg import FrameStats, KeyFrame, MapCorrection  # noqa: F401

        from ..vo.pipeline import VisualOdometry

        self.robot_id = int(rospy.get_param("~robot_id"))
        if self.robot_id < 1:
            raise CoopSlamError(f"~robot_id must be >= 1, got {self.robot_id}")
        self.name = f"robot_{self.robot_id}"
        ns = f"/{self.name}"
        self.sensor = rospy.get_param("~sensor", "rgbd")
        if self.sensor not in PLAYABLE_SENSORS:
            raise CoopSlamError(
                f"~sensor must be one of {', '.join(PLAYABLE_SENSORS)}, got '{self.sensor}'"
            )
        self.map_frame = f"{self.name}/map"
        self.odom_frame = f"{self.name}/odom"
        self.base_frame = f"{self.name}/base_link"
        self.cam_frame = f"{self.name}/camera_optical"
        self.depth_scale = float(rospy.get_param("~depth_scale", 1000.0))  # 16UC1 units per metre
        self.cloud_period_s = float(rospy.get_param("~cloud_period_s", 2.0))
        # The path holds every keyframe: rebuilt at each keyframe change it cost 2-3.5 ms with
        # 60-100 keyframes, on the frames that insert keyframes, and grew with the map.
        self.path_period_s = float(rospy.get_param("~path_period_s", 1.0))
        base_cam = rospy.get_param("~T_base_cam", [])  # [x y z qx qy qz qw]
        self.T_base_cam = T_base_cam_of(base_cam)
        from ..markers import MarkerConfig, MarkerDetector
        from ..vo.config import VoConfig

        config_file = rospy.get_param("~config", "")
        self.vo_cfg = load_yaml_config(VoConfig, config_file, "vo", rospy.get_param("~vo", {}))
        if self.vo_cfg.planar_motion:  # the floor normal (base z) as the camera sees it
            self.vo_cfg.planar_up_cam = (self.T_base_cam[:3, :3].T @ [0.0, 0.0, 1.0]).tolist()
        self._VisualOdometry = VisualOdometry
        self.vo = None
        self.camera = None
        self._camera_ready = threading.Event()  # set once a camera model is known
        self._camera_wait_s = CAMERA_INFO_WAIT_S
        self.lock = threading.Lock()
        self.rejects = RejectCounter(f"client {self.name}")
        # Pose-graph sharing: the team map's poses of our keyframes over what we publish (path,
        # cloud, map -> odom); the odometry goes on in its own frame (coop_slam.vo.shared_poses).
        self.shared = SharedPoses()
        self.segment_starts = False  # a new map segment begins with the next new keyframe
        self.corrections_applied = 0
        self.T_world_map = None
        self.segment = 0
        self.kf_poses: dict[int, tuple[float, np.ndarray]] = {}  # id -> (stamp, T_map_cam)
        self.last_cloud_s = self.last_path_s = -1e9
        self.path_due = False  # keyframes changed since the path last went out
        self.frames = 0
        # Marker sightings of other robots (rendezvous cue; their bodies are masked for the
        # odometry); 0 disables detection.
        self.marker_every = int(rospy.get_param("~marker_every_frames", 5))
        # Lock-step playback: a frame is finished when local mapping has caught up too, so that
        # results do not depend on how fast the machine maps. Live, the mapper runs beside
        # tracking and a backlog is reported (FrameStats.mapping_backlog and a warning).
        self.wait_for_mapping = bool(rospy.get_param("~wait_for_mapping", False))
        self.mapping_backlog_warn = int(rospy.get_param("~mapping_backlog_warn", 3))
        self.markers = MarkerDetector(
            load_yaml_config(MarkerConfig, config_file, "markers", rospy.get_param("~markers", {}))
        )

        import message_filters
        import tf2_ros

        self.tf = tf2_ros.TransformBroadcaster()
        self.static_tf = tf2_ros.StaticTransformBroadcaster()
        self.static_tf.sendTransform(
            transform_stamped(self.T_base_cam, self.base_frame, self.cam_frame, rospy.Time(0))
        )
        self.pub_kf = rospy.Publisher(f"{ns}/keyframes", KeyFrame, queue_size=200)
        self._start_delivery(ns)
        self.pub_pose = rospy.Publisher(f"{ns}/pose", PoseStamped, queue_size=10)
        self.pub_path = rospy.Publisher(f"{ns}/path", Path, queue_size=1, latch=True)
        from sensor_msgs.msg import PointCloud2

        self.pub_cloud = rospy.Publisher(f"{ns}/local_map", PointCloud2, queue_size=1, latch=True)
        self.pub_stats = rospy.Publisher(f"{ns}/frame_stats", FrameStats, queue_size=50)
        from ..frame_slot import LatestFrame

        self.slot = LatestFrame()
        self._tracker = threading.Thread(target=self._track_frames, daemon=True)
        self._tracker.start()
        from coop_slam.msg import RobotSighting

        self.pub_sighting = rospy.Publisher("/robot_sightings", RobotSighting, queue_size=10)
        self.topics = camera_topics(self.robot_id, self.sensor)
        self.infos: dict[str, CameraInfo] = {}
        self._info_keys: dict[str, tuple] = {}  # per camera info topic: the last one accepted
        self._info_lock = threading.Lock()
        self.subs_info = [
            rospy.Subscriber(topic, CameraInfo, self._on_info, which, queue_size=5)
            for which, topic in self.topics["infos"].items()
        ]
        # A stream whose partner never comes (no depth / right images) would stall lock-step
        # playback and leave the user guessing: watch both streams alone as well (rospy
        # deserializes a topic once for all of a node's subscribers).
        self._watch_lock = threading.Lock()
        self._unpaired: list = []  # (wall time, stamp) of main images not yet in a pair
        # Stamps of the latest pairs: the lone image's callback may run after its pair's.
        self._paired: collections.deque = collections.deque(maxlen=64)
        self._last_second_wall = -1e9  # wall time of the last second image [s]
        if self.sensor == "mono":  # one image: nothing to pair
            self.sub_image = rospy.Subscriber(
                self.topics["image"], Image, self._on_frame, queue_size=5, buff_size=2**24
            )
        else:
            image = message_filters.Subscriber(
                self.topics["image"], Image, queue_size=5, buff_size=2**24
            )
            second = message_filters.Subscriber(
                self.topics["second"], Image, queue_size=5, buff_size=2**24
            )
            self.sync = message_filters.TimeSynchronizer([image, second], 10)
            self.sync.registerCallback(self._on_frame)
            self.sub_image_watch = rospy.Subscriber(
                self.topics["image"], Image, self._on_image_alone, queue_size=5, buff_size=2**24
            )
            self.sub_second_watch = rospy.Subscriber(
                self.topics["second"], Image, self._on_second_alone, queue_size=5, buff_size=2**24
            )
            self._watch = threading.Thread(target=self._watch_pairs, daemon=True)
            self._watch.start()
        self.sub_corr = rospy.Subscriber(
            f"{ns}/correction", MapCorrection, self._on_correction, queue_size=5
        )
        rospy.loginfo(
            "client %s (%s): waiting for %s",
            self.name,
            self.sensor,
            " and ".join(
                rospy.resolve_name(self.topics[k]) for k in ("image", "second") if k in self.topics
            ),
        )

    def _start_delivery(self, ns: str) -> None:
        """Numbered keyframe messages, acknowledgements, sending again; ids after a restart."""
        from coop_slam.msg import KeyframeAck

        from ..delivery import Outbox

        self.outbox = Outbox(
            int(rospy.get_param("~max_unacked", 1000)),
            float(rospy.get_param("~resend_after_s", 2.0)),
            int(rospy.get_param("~resend_window", 100)),
            float(rospy.get_param("~max_resend_after_s", 30.0)),
        )
        self._outbox_lock = threading.Lock()
        self.keyframes_sent = 0
        self.last_frame_wall = time.monotonic()  # when the newest frame came (idle flush)
        from ..vo.outbox import Uplink, UplinkConfig

        # Updates carry what changed since the server got the keyframe (~uplink).
        self.uplink = Uplink(
            load_yaml_config(
                UplinkConfig,
                rospy.get_param("~config", ""),
                "uplink",
                rospy.get_param("~uplink", {}),
            )
        )
        self.vocabulary = None  # the server's, for place signatures (low-bandwidth, lost)
        self._assist_busy, self._assist_last_s = False, 0.0
        self._request_seen = 0
        if self.uplink.pull:
            from coop_slam.msg import KeyframeRequest

            self.vocabulary = self._server_vocabulary(float(rospy.get_param("~server_wait_s", 3.0)))
            self.sub_request = rospy.Subscriber(
                f"{ns}/keyframe_request", KeyframeRequest, self._on_request, queue_size=10
            )
        self._bound_warned = False
        # A restarted client must not reuse the keyframe ids the server stored before: the
        # server's latched acknowledgement says how far they went.
        self.kf_id_base, self.segment_base = 0, 0
        wait_s = float(rospy.get_param("~server_wait_s", 3.0))
        try:
            ack = rospy.wait_for_message(f"{ns}/keyframe_ack", KeyframeAck, timeout=wait_s)
            if ack.last_keyframe_id > 0:
                self.kf_id_base = int(ack.last_keyframe_id)
                self.segment_base = int(ack.last_map_segment) + 1
                rospy.logwarn(
                    "client %s: the server holds %d keyframes of this robot from before: "
                    "continuing from keyframe %d in new map segment %d",
                    self.name,
                    ack.last_keyframe_id,
                    self.kf_id_base + 1,
                    self.segment_base,
                )
        except rospy.ROSException:
            rospy.loginfo(
                "client %s: no server acknowledgement within %.0f s: starting at keyframe 1",
                self.name,
                wait_s,
            )
        self.sub_ack = rospy.Subscriber(f"{ns}/keyframe_ack", KeyframeAck, self._on_ack)
        # Played data (scripts/demo, player.launch): the player says when it has played all.
        self.sub_done = rospy.Subscriber("/player/done", Bool, self._flush_uplink, queue_size=1)
        self._resender = threading.Thread(target=self._resend_loop, daemon=True)
        self._resender.start()

    def _server_vocabulary(self, wait_s: float):
        """The vocabulary the server publishes (its words are what place signatures name), else
        the default one this machine has."""
        import tempfile

        from coop_slam.msg import Vocabulary as VocabularyMsg

        from ..bow import Vocabulary
        from ..bow.training import default_vocabulary_path

        try:
            msg = rospy.wait_for_message("/server/vocabulary", VocabularyMsg, timeout=wait_s)
            suffix = ".npz" if msg.format == "coop_slam-npz" else ".txt"
            with tempfile.NamedTemporaryFile(suffix=suffix) as fh:
                fh.write(msg.data)
                fh.flush()
                vocabulary = Vocabulary.load(fh.name)
            rospy.loginfo("client %s: place signatures in the server's vocabulary", self.name)
            return vocabulary
        except rospy.ROSException:
            path = default_vocabulary_path()
            rospy.logwarn(
                "client %s: no /server/vocabulary within %.0f s: place signatures in %s (the "
                "server must use the same vocabulary)",
                self.name,
                wait_s,
                path,
            )
            return Vocabulary.load(path)

    def _on_request(self, msg) -> None:
        """The server asks for whole keyframes (low-bandwidth mode): each goes as new, in full;
        keyframes this client no longer has are not sent (the server gives up on them)."""
        from ..keyframe_record import ACTION_NEW
        from ..vo.outbox import keyframe_record

        if msg.robot_id != self.robot_id:
            self.rejects.reject("keyframe_request", f"request for robot {msg.robot_id}")
            return
        # The uplink's state (what the server holds) is the tracking thread's too.
        with self.lock:
            if (msg.request and msg.request <= self._request_seen) or self.vo is None:
                return  # latched: answered already (or no map yet)
            self._request_seen = msg.request
            for kid in msg.keyframe_ids:
                kf = self.vo.keyframe(int(kid) - self.kf_id_base)
                if kf is None:
                    rospy.loginfo(
                        "client %s: the server asks for keyframe %d, gone", self.name, kid
                    )
                    continue
                rec = keyframe_record(kf, self.robot_id, self.camera, self.T_base_cam)
                rec = self._as_sent(rec)
                rec.action = ACTION_NEW
                self.uplink.answer(rec)
                self._send_keyframe(keyframe_to_msg(rec, self.map_frame))

    def _as_sent(self, rec):
        """A record with this client run's keyframe ids and map segments (after a restart they
        go on above the server's)."""
        rec.keyframe_id += self.kf_id_base
        rec.covisible_ids = rec.covisible_ids + np.uint32(self.kf_id_base)
        rec.map_segment += self.segment_base
        return rec

    def _on_ack(self, msg) -> None:
        if msg.robot_id != self.robot_id:
            self.rejects.reject("keyframe_ack", f"acknowledgement for robot {msg.robot_id}")
            return
        with self._outbox_lock:
            self.outbox.server_is(msg.server_session)
            self.outbox.ack(msg.session, msg.sequence)
            # (received_session 0, an ack naming no receipt, is no client's session)
            self.outbox.received(msg.received_session, msg.received_sequence)
        # Keyframes the server refused: later messages must not count on it holding them.
        self.uplink.forget(getattr(msg, "refused_keyframe_ids", ()))

    def _resend_loop(self) -> None:
        while not rospy.is_shutdown():
            time.sleep(0.5)
            # No frame for a while: the camera stopped, what the uplink holds goes now. Played
            # data in lock-step waits for every client, so a pause says nothing there: what is
            # held goes when the player is done (the messages stay the same however loaded the
            # machine is).
            if (
                len(self.uplink.holdback)
                and time.monotonic() - self.last_frame_wall > self.uplink.idle_flush_s
                and not (self.wait_for_mapping and self.sub_done.get_num_connections())
            ):
                self._flush_uplink(blocking=False)
            with self._outbox_lock:
                due = self.outbox.due()
            if due and self.pub_kf.get_num_connections() > 0:
                rospy.loginfo_throttle(
                    10.0,
                    "client %s: sending %d unacknowledged keyframe messages again",
                    self.name,
                    len(due),
                )
                for msg in due:
                    self.pub_kf.publish(msg)

    def _flush_uplink(self, msg=None, blocking: bool = True) -> None:
        """Send whatever the uplink holds (``msg``: the player's ``done``, when it is done), and
        say how many new keyframes went in all (no frame will: see :meth:`_publish_counters`).
        Not ``blocking``: nothing when a frame is being tracked (the resend thread must not wait
        for one)."""
        if (msg is not None and not msg.data) or not self.lock.acquire(blocking=blocking):
            return
        try:
            if len(self.uplink.holdback):
                self._send_records(self.uplink.flush())
                self._publish_counters()
        finally:
            self.lock.release()

    def _publish_counters(self) -> None:
        """The delivery counters of FrameStats without a frame (stamp 0): keyframes sent after
        the last frame (what the uplink held) count too."""
        from coop_slam.msg import FrameStats

        stats = FrameStats(robot_id=self.robot_id, tracking_ok=True)
        stats.keyframes = len(self.kf_poses)
        stats.keyframes_sent, stats.unacked = self.keyframes_sent, self.outbox.unacked
        self.pub_stats.publish(stats)

    def _send_keyframe(self, msg) -> None:
        with self._outbox_lock:
            msg.session, msg.sequence, overflow = self.outbox.add(msg)
        if overflow and not self._bound_warned:
            self._bound_warned = True
            rospy.logwarn(
                "client %s: %d keyframe messages not acknowledged by the server (is it "
                "running? see /robot_%d/keyframe_ack): the oldest are given up from now on "
                "(~max_unacked)",
                self.name,
                self.outbox.max_unacked,
                self.robot_id,
            )
        self.pub_kf.publish(msg)

    # --- callbacks --------------------------------------------------------------------------------
    def _on_info(self, msg: CameraInfo, which: str) -> None:
        topic = self.topics["infos"][which]
        # Every frame brings its camera info; only a change needs a new camera model.
        key = (
            msg.width,
            msg.height,
            msg.distortion_model,
            tuple(msg.D),
            tuple(msg.K),
            tuple(msg.P),
        )
        # One info at a time: stereo's left and right callbacks run in threads of their own, and
        # a camera built from one new and one old info must not be kept as the last accepted.
        with self._info_lock:
            if self.camera is not None and self._info_keys.get(which) == key:
                return
            self.infos[which] = msg
            try:
                if self.sensor == "stereo":
                    if "left" not in self.infos or "right" not in self.infos:
                        return
                    cam = stereo_camera_from_infos(self.infos["left"], self.infos["right"])
                else:  # rgbd or mono: the colour camera
                    cam = camera_from_info(msg, sensor=self.sensor, depth_scale=self.depth_scale)
            except MessageError as exc:
                self._info_keys.pop(which, None)  # the next info is checked again, in full
                self.rejects.reject(topic, str(exc))
                return
            self._info_keys[which] = key
            with self.lock:
                if self.camera is not None and cam != self.camera:
                    rospy.logwarn(
                        "client %s: camera model changed (%dx%d fx=%.1f -> %dx%d fx=%.1f); "
                        "starting a new map",
                        self.name,
                        self.camera.width,
                        self.camera.height,
                        self.camera.fx,
                        cam.width,
                        cam.height,
                        cam.fx,
                    )
                    self._close_vo()
                self.camera = cam
                self._camera_ready.set()

    def _close_vo(self) -> None:
        if self.vo is not None:
            self.vo.reset()
            self._publish_events()
            # The next odometry numbers its keyframes from 1 and its segments from 0 again: the
            # messages go on after this one's (its reset announced the segment they start in).
            self.kf_id_base += self.vo.keyframes_made
            self.segment_base += self.vo.map_segment
            self.vo.close()
            self.vo = None

    def _on_image_alone(self, msg: Image) -> None:
        with self._watch_lock:
            if msg.header.stamp not in self._paired:
                self._unpaired.append((time.monotonic(), msg.header.stamp))

    def _on_second_alone(self, msg: Image) -> None:
        self._last_second_wall = time.monotonic()

    def _watch_pairs(self) -> None:
        """Main images older than 3 s while the second stream (depth / right) has been silent for
        3 s: say which topic is silent, and acknowledge those frames (not tracked) so lock-step
        playback goes on. (Images left over while the second stream flows were dropped by a busy
        client, or are still queued: not a fault of the input.)"""
        from coop_slam.msg import FrameStats

        while not rospy.is_shutdown():
            time.sleep(1.0)
            now = time.monotonic()
            with self._watch_lock:
                old = [s for t, s in self._unpaired if now - t > 3.0]
                if now - self._last_second_wall < 3.0:
                    continue
                self._unpaired = [(t, s) for t, s in self._unpaired if now - t <= 3.0]
            if not old:
                continue
            what = "depth" if self.sensor == "rgbd" else "right"
            self.rejects.reject(
                self.topics["image"],
                f"{len(old)} image(s) without a {what} image of the same stamp on "
                f"{rospy.resolve_name(self.topics['second'])} within 3 s: is it published?",
            )
            for stamp in old:
                stats = FrameStats(robot_id=self.robot_id, tracking_ok=False)
                stats.header.stamp = stamp
                self.pub_stats.publish(stats)

    def _on_frame(self, image_msg: Image, second_msg: Image | None = None) -> None:
        """A camera frame (pair): handed to the tracking thread; one the tracker had not taken
        yet is dropped (the newest frame wins, see coop_slam.frame_slot) and said so."""
        from coop_slam.msg import FrameStats

        stamp = image_msg.header.stamp
        with self._watch_lock:
            self._unpaired = [(t, s) for t, s in self._unpaired if s != stamp]
            self._paired.append(stamp)
        dropped = self.slot.put((image_msg, second_msg))
        if dropped is not None:
            stats = FrameStats(robot_id=self.robot_id, tracking_ok=False, dropped=True)
            stats.header.stamp = dropped[0].header.stamp
            self.pub_stats.publish(stats)
            rospy.logwarn_throttle(
                10.0,
                "client %s: busy, %d frame(s) dropped so far (the newest frame is tracked)",
                self.name,
                self.slot.dropped,
            )

    def _track_frames(self) -> None:
        while not rospy.is_shutdown():
            item = self.slot.take(timeout_s=0.5)
            if item is not None:
                self._track(*item)

    def _track(self, image_msg: Image, second_msg: Image | None) -> None:
        from coop_slam.msg import FrameStats

        from ..vo.types import STATE_INITIALIZING

        stamp = image_msg.header.stamp
        stats = FrameStats(robot_id=self.robot_id, tracking_ok=False)
        stats.header.stamp = stamp
        # Images and their camera info come on topics of their own, in no order between them:
        # the very first image may come before any info (a loaded machine makes that likely), and
        # rejecting it would start a monocular map from a later view. It waits for the info.
        if not self._camera_ready.wait(self._camera_wait_s):
            self._camera_wait_s = 0.0  # none came: no info is published, later frames go at once
        try:
            with self.lock:
                if self.camera is None:
                    missing = [t for w, t in self.topics["infos"].items() if w not in self.infos]
                    raise MessageError(f"no camera_info received yet on {', '.join(missing)}")
                image = image_from_msg(image_msg)
                if self.sensor == "mono":
                    second = None
                    if image.shape[:2] != (self.camera.height, self.camera.width):
                        raise MessageError(
                            f"image {image.shape[1]}x{image.shape[0]} does not match "
                            f"camera_info {self.camera.width}x{self.camera.height}"
                        )
                else:
                    if self.sensor == "stereo":
                        second, what = image_from_msg(second_msg), "right image"
                    else:
                        second, what = depth_from_msg(second_msg, self.depth_scale), "depth"
                    if (
                        image.shape[:2] != (self.camera.height, self.camera.width)
                        or second.shape[:2] != image.shape[:2]
                    ):
                        raise MessageError(
                            f"image {image.shape[1]}x{image.shape[0]} / {what} "
                            f"{second.shape[1]}x{second.shape[0]} do not match camera_info "
                            f"{self.camera.width}x{self.camera.height}"
                        )
                if self.vo is None:
                    self.vo = self._VisualOdometry(self.vo_cfg, self.camera)
                res = self.vo.track(stamp.to_sec(), image, second)
                self.frames += 1
                stats.mapping_backlog = min(self.vo.mapping_backlog, 65535)
                if self.wait_for_mapping:
                    self.vo.flush()
                elif stats.mapping_backlog >= self.mapping_backlog_warn:
                    rospy.logwarn_throttle(
                        10.0,
                        "client %s: local mapping is %d keyframes behind the camera (the map "
                        "is refined later than tracking needs it)",
                        self.name,
                        stats.mapping_backlog,
                    )
                if res.state == STATE_INITIALIZING:  # e.g. a monocular camera not moved yet
                    rospy.loginfo_throttle(5.0, "client %s: %s", self.name, res.message)
                elif res.message.startswith("map initialized"):
                    rospy.loginfo("client %s: %s", self.name, res.message)
                stats.track_ms, stats.tracking_ok = res.track_ms, bool(res.ok)
                if res.message.startswith("relocalized in the team map"):
                    rospy.loginfo("client %s: %s", self.name, res.message)
                self._maybe_ask_server()
                self._publish_events(stamp.to_sec())
                if self.path_due and stamp.to_sec() - self.last_path_s >= self.path_period_s:
                    self.last_path_s = stamp.to_sec()
                    self._publish_path()
                stats.keyframes = len(self.kf_poses)
                stats.keyframes_sent, stats.unacked = self.keyframes_sent, self.outbox.unacked
                if res.ok:
                    self._publish_pose(stamp, self.T_base_cam @ res.T_map_cam)
                if self.marker_every and self.frames % self.marker_every == 0:
                    self._detect_markers(stamp, image, res)
                if stamp.to_sec() - self.last_cloud_s >= self.cloud_period_s:
                    self.last_cloud_s = stamp.to_sec()
                    self._publish_cloud(stamp)
        except CoopSlamError as exc:
            self.rejects.reject(self.topics["image"], str(exc))
        finally:
            self.pub_stats.publish(stats)

    def _maybe_ask_server(self) -> None:
        """Lost, and the own map does not place the camera: ask the server for the team's local
        map where it is (at most one question a second, one at a time)."""
        view = self.vo.lost_view()
        if view is None or self._assist_busy or time.monotonic() - self._assist_last_s < 1.0:
            return
        self._assist_busy, self._assist_last_s = True, time.monotonic()
        self.vo.expect_local_map()
        segment = self.vo.map_segment
        threading.Thread(target=self._ask_server, args=(view, segment), daemon=True).start()

    def _ask_server(self, descriptors: np.ndarray, segment: int) -> None:
        from coop_slam.srv import Relocalize

        from ..bow.signature import encode_signature

        points, desc, pending = None, None, False
        try:
            if self.vocabulary is None:
                self.vocabulary = self._server_vocabulary(3.0)
            bow, _ = self.vocabulary.transform(descriptors)
            gaps, weights, weight_max = encode_signature(bow)
            ask = rospy.ServiceProxy("/server/relocalize", Relocalize)
            ask.wait_for_service(timeout=2.0)
            rep = ask(
                robot_id=self.robot_id,
                map_segment=segment + self.segment_base,
                bow_word_gaps=gaps,
                bow_weights=weights,
                bow_weight_max=weight_max,
            )
            pending = bool(getattr(rep, "pending", False))
            rospy.loginfo(
                "client %s: lost; the server %s: %s",
                self.name,
                (
                    "sends the team's local map"
                    if rep.found
                    else ("fetches it" if pending else "cannot place it")
                ),
                rep.message,
            )
            if rep.found and self.vo is not None and self.vo.map_segment == segment:
                pts = np.asarray(rep.points, float).reshape(-1, 3)
                # Sent in robot_k/map; the odometry's map frame is its first camera frame.
                points = transform_points(invert(self.T_base_cam), pts)
                desc = np.frombuffer(rep.descriptors, np.uint8).reshape(-1, 32)
        except (rospy.ROSException, rospy.ServiceException, CoopSlamError, ValueError) as exc:
            rospy.logwarn("client %s: lost; asking the server failed: %s", self.name, exc)
        finally:
            if pending:  # keep waiting, and ask again soon
                self._assist_last_s = time.monotonic() - 0.7
            elif self.vo is not None:
                self.vo.offer_local_map(points, desc)
            self._assist_busy = False

    def _detect_markers(self, stamp, image, res) -> None:
        from coop_slam.msg import RobotSighting

        from ..markers import body_box_cam

        cfg = self.markers.config
        for s in self.markers.detect(image, self.camera.K):
            if s.marker_id == self.robot_id or s.marker_id < 1:
                continue  # our own body, or not a robot id
            if res.ok and cfg.mask_s > 0:  # a robot is a moving object, not a landmark
                corners_map = transform_points(res.T_map_cam, body_box_cam(cfg, s.T_cam_body))
                self.vo.ignore_region(corners_map, stamp.to_sec() + cfg.mask_s)
            msg = RobotSighting(
                observer_id=self.robot_id,
                observed_id=s.marker_id,
                marker_id=s.marker_id,
                T_cam_body=pose_to_msg(s.T_cam_body),
                reprojection_error_px=s.reprojection_error_px,
            )
            msg.header.stamp, msg.header.frame_id = stamp, self.cam_frame
            self.pub_sighting.publish(msg)

    def _on_correction(self, msg) -> None:
        if msg.robot_id != self.robot_id:
            self.rejects.reject(
                "correction", f"correction for robot {msg.robot_id} on " f"{self.name}'s topic"
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
        with self.lock:
            self.T_world_map = T_world_map if msg.merged else None
            if self.shared.receive(dict(zip(msg.keyframe_ids, poses)), self._odom_poses()):
                self.corrections_applied += 1
                self._publish_path()
                if self.vo is not None:
                    self._publish_cloud(msg.header.stamp)

    # --- publishing -------------------------------------------------------------------------------
    def _publish_events(self, now_s: float | None = None) -> None:
        """Hand the odometry's events at data time ``now_s`` to the uplink and send what it lets
        go (None: everything it holds, the odometry is closing)."""
        from ..keyframe_record import ACTION_NEW, ACTION_REMOVE
        from ..vo.outbox import event_record
        from ..vo.types import EVENT_NEW_SEGMENT, EVENT_WARNING, KEYFRAME_ACTIONS

        made_s = 0.0 if now_s is None else now_s  # None: all goes below, made whenever
        for ev in self.vo.drain_events():
            if ev.kind == EVENT_WARNING:
                rospy.logwarn("client %s: %s", self.name, ev.message)
            elif ev.kind == EVENT_NEW_SEGMENT:
                rospy.logwarn(
                    "client %s: tracking lost for good; new map segment %d (%s)",
                    self.name,
                    ev.map_segment,
                    ev.message,
                )
                self.segment = ev.map_segment + self.segment_base
                self.segment_starts = True  # with the next new keyframe
                self._send_records(self.uplink.flush())  # the old map's keyframes go first
            elif ev.kind in KEYFRAME_ACTIONS:
                rec = self._as_sent(event_record(ev, self.robot_id, self.camera, self.T_base_cam))
                if self.segment_starts and rec.action == ACTION_NEW:
                    self.shared.start_segment(rec.keyframe_id)
                    self.segment_starts = False
                if rec.action == ACTION_REMOVE:
                    self.kf_poses.pop(rec.keyframe_id, None)
                    self.shared.forget(rec.keyframe_id)
                else:
                    self.kf_poses[rec.keyframe_id] = (rec.stamp_s, rec.T_map_cam)
                self.path_due = True
                # An update goes with what changed since the server got the keyframe.
                self._send_records(self.uplink.offer(rec, made_s))
        if now_s is None:
            self._send_records(self.uplink.flush())
        else:
            self.last_frame_wall = time.monotonic()
            self._send_records(self.uplink.due(now_s))

    def _send_records(self, outgoing) -> None:
        """Send keyframe records as the uplink prepared them (self.lock held)."""
        from ..keyframe_record import ACTION_NEW
        from ..vo.outbox import signature_of

        for rec, out in outgoing:
            if out.skip:
                continue
            try:
                if out.signature:
                    msg = keyframe_to_msg(signature_of(rec, self.vocabulary), self.map_frame)
                else:
                    msg = keyframe_to_msg(
                        rec, self.map_frame, out.delta, out.patched, out.refs, moves=out.moves
                    )
            except CoopSlamError as exc:  # one record the encoder refuses must not stop the rest
                rospy.logerr(
                    "client robot_%d: keyframe %d not sent: %s", self.robot_id, rec.keyframe_id, exc
                )
                continue
            self.keyframes_sent += rec.action == ACTION_NEW
            self._send_keyframe(msg)

    def _publish_pose(self, stamp, T_odom_cam: np.ndarray) -> None:
        T_map_odom = self.shared.T_map_odom
        T_map_cam = T_map_odom @ T_odom_cam
        msg = PoseStamped(pose=pose_to_msg(T_map_cam))
        msg.header.stamp, msg.header.frame_id = stamp, self.map_frame
        self.pub_pose.publish(msg)
        T_odom_base = T_odom_cam @ invert(self.T_base_cam)
        self.tf.sendTransform(
            [
                transform_stamped(T_map_odom, self.map_frame, self.odom_frame, stamp),
                transform_stamped(T_odom_base, self.odom_frame, self.base_frame, stamp),
            ]
        )

    def _odom_poses(self) -> dict[int, np.ndarray]:
        """Our keyframes' poses in robot_k/odom (message ids): those of the current map segment
        as the odometry has them now, older ones as sent."""
        poses = {kid: T for kid, (_, T) in self.kf_poses.items()}
        if self.vo is not None:
            for k, T in self.vo.keyframe_poses().items():
                if k + self.kf_id_base in poses:
                    poses[k + self.kf_id_base] = self.T_base_cam @ T
        return poses

    def _publish_path(self) -> None:
        """Our keyframes in robot_k/map, each with the team map's correction (see
        coop_slam.vo.shared_poses)."""
        self.path_due = False
        path = Path()
        path.header.frame_id = self.map_frame
        T_cam_base = invert(self.T_base_cam)
        poses = self.shared.keyframe_poses(self._odom_poses())
        for kid in sorted(poses):
            ps = PoseStamped(pose=pose_to_msg(poses[kid] @ T_cam_base))
            stamp_s = self.kf_poses[kid][0]
            ps.header.stamp, ps.header.frame_id = rospy.Time.from_sec(stamp_s), self.map_frame
            ps.header.seq = kid  # the keyframe's id, as in the team map's paths
            path.poses.append(ps)
        if path.poses:
            path.header.stamp = path.poses[-1].header.stamp
        self.pub_path.publish(path)

    def _publish_cloud(self, stamp) -> None:
        if self.shared.corrected:
            xyz, ref = self.vo.map_points_with_reference()
            # A point no keyframe observes any more goes with where the robot is now.
            ids = np.where(ref > 0, ref + self.kf_id_base, NEWEST)
            pts = self.shared.points(transform_points(self.T_base_cam, xyz), ids)
        else:  # nothing to lay over (finding each point's reference keyframe takes a while)
            pts = transform_points(self.T_base_cam, self.vo.map_point_arrays()[1])
        self.pub_cloud.publish(cloud_to_msg(pts, self.map_frame, stamp))

    def shutdown(self) -> None:
        self.slot.close()
        with self.lock:
            if self.vo is not None:
                self._send_records(self.uplink.flush())  # best effort: the node is going down
                self.vo.close()
        rospy.loginfo(
            "client %s: %d frames, %d dropped (busy), %d keyframes, %d corrections applied, %d "
            "rejected messages",
            self.name,
            self.frames,
            self.slot.dropped,
            len(self.kf_poses),
            self.corrections_applied,
            self.rejects.total,
        )


def main() -> None:
    rospy.init_node("client")
    forward_core_logs(f"client {rospy.get_param('~robot_id', '?')}")
    try:
        node = ClientNode()
    except CoopSlamError as exc:
        rospy.logfatal("client: %s", exc)
        raise SystemExit(1) from exc
    rospy.on_shutdown(node.shutdown)
    rospy.spin()
