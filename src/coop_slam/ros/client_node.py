"""Client node: visual odometry on one robot's RGB-D, stereo or monocular camera, publishing
keyframes, pose, TF, path and cloud.

Composed of small parts: :mod:`.camera_input` (camera infos, image pairs, the newest frame to the
tracking thread), the odometry (:class:`coop_slam.vo.pipeline.VisualOdometry`, tracked here in
one thread), :mod:`.uplink_bridge` (keyframe messages to the server and its answers),
:mod:`.pose_output` (pose, TF, path, cloud, the team map's corrections), :mod:`.team_cues`
(marker sightings, asking the server when lost) and :mod:`.frame_outputs` (a tracked frame's
outputs and stats, in frame order from a thread of their own).

Robot k's topics live under ``/robot_k`` and its frames are ``robot_k/...``, whatever namespace the
node is started in: the server finds a robot by its id alone. A monocular map has no metric scale:
its keyframes say so by their camera's sensor type, and only the server can give them metres.
"""

from __future__ import annotations

import gc
import queue
import threading
import time

import rospy
from sensor_msgs.msg import Image

from ..camera_presets import layered, load_preset
from ..config import load_yaml_config
from ..errors import CoopSlamError
from ..geometry import T_base_cam_of
from ..markers import MarkerConfig, MarkerDetector
from ..optim.bundle import prestart_worker
from ..playback import PLAYABLE_SENSORS
from ..robot_description import describe
from ..uplink.config import UplinkConfig
from ..vo.config import VoConfig
from ..vo.kernels import warm_up
from ..vo.pipeline import VisualOdometry
from ..vo.shared_work import shared_worker
from ..vo.types import STATE_INITIALIZING
from .camera_input import CameraInput
from .convert import description_to_msg
from .frame_outputs import FrameOutputs, TrackedFrame
from .log_bridge import forward_core_logs
from .params import client_params
from .pose_output import PoseOutput
from .team_cues import TeamCues
from .uplink_bridge import UplinkBridge, server_vocabulary
from .validation import RejectCounter

FRAMES_COMING_S = 0.2  # a frame within this long [s, wall]: the camera is running


class ClientNode:
    def __init__(self):
        from coop_slam.msg import FrameStats, MapCorrection

        p = client_params(rospy.get_param("~", {}))
        self.robot_id = p.robot_id
        self.name = name = f"robot_{self.robot_id}"
        sensor = p.sensor
        if sensor not in PLAYABLE_SENSORS:
            raise CoopSlamError(
                f"~sensor must be one of {', '.join(PLAYABLE_SENSORS)}, got '{sensor}'"
            )
        self.sensor = sensor
        self.T_base_cam = T_base_cam_of(p.T_base_cam)
        preset = load_preset(p.camera)  # a known camera's values, under the node's own
        self.vo_cfg = load_yaml_config(VoConfig, p.config, "vo", layered(preset, "vo", p.vo))
        if self.vo_cfg.planar.enabled:  # the floor normal (base z) as the camera sees it
            self.vo_cfg.planar.up_cam = (self.T_base_cam[:3, :3].T @ [0.0, 0.0, 1.0]).tolist()
        # Lock-step playback: a frame is finished when local mapping has caught up too, so that
        # results do not depend on how fast the machine maps. Live, the mapper runs beside
        # tracking and a backlog is reported (FrameStats.mapping_backlog and a warning).
        self.wait_for_mapping = p.wait_for_mapping
        self.mapping_backlog_warn = p.mapping_backlog_warn
        self.vo: VisualOdometry | None = None
        self.frames = 0
        self._counters_said = (0, 0, 0)  # keyframes sent, held back, unacked: last published
        self.lock = threading.Lock()  # the odometry and what is made of it: one thread at a time
        self.rejects = RejectCounter(f"client {name}")
        self._FrameStats = FrameStats
        self.pub_stats = rospy.Publisher(f"/{name}/frame_stats", FrameStats, queue_size=50)
        self.pose = PoseOutput(
            self.robot_id,
            self.T_base_cam,
            p.cloud_period_s,
            p.path_period_s,
            self.rejects,
            p.frame_config,
        )
        # The uplink's work on a frame's odometry events (records, budget, encoding, spool,
        # publishing: up to ~90 ms on a keyframe frame) runs in its own thread, beside tracking;
        # what it notes for the path is taken by the tracker's lock holders (the next frame, a
        # correction, the idle flush). Made before the bridge, whose resend thread may flush.
        self._uplink_jobs: queue.Queue = queue.Queue()
        self._uplink_notes: list = []
        self._notes_lock = threading.Lock()
        self.uplink = UplinkBridge(
            name,
            load_yaml_config(UplinkConfig, p.config, "uplink", layered(preset, "uplink", p.uplink)),
            p.delivery,
            p.server_wait_s,
            self.rejects,
            self._with_odometry,
            self.wait_for_mapping,
            dict(robot_id=self.robot_id, T_base_cam=self.T_base_cam),
            p.spool_config,
            p.clock_offset_s,
        )
        self.uplink.flush_now = self._flush_uplink
        # Keyframes a budget sent as signatures only get no pose back: they follow their neighbours
        self.pose.shared.server_holds = self.uplink.engine.planner.holds
        self.cues = self._team_cues(p, preset)
        # Ready before subscribing to the camera: the player waits for that, so no frame comes
        # while the kernels and the BA process load.
        self._ready_before_frames()
        self.camera = CameraInput(
            name,
            self.robot_id,
            sensor,
            p.depth_scale or float((preset.get("camera") or {}).get("depth_scale", 1000.0)),
            self.rejects,
            self.lock,
            self._camera_changed,
            self._frame_not_tracked,
        )
        self.outputs = FrameOutputs(
            name,
            self.lock,
            self.pose,
            self.cues,
            self.pub_stats.publish,
            self._counters,
            lambda text: self.rejects.reject(self.camera.topics["image"], text),
            beside=not self.wait_for_mapping,
        )
        threading.Thread(target=self._uplink_loop, daemon=True).start()
        threading.Thread(target=self._track_frames, daemon=True).start()
        self.sub_corr = rospy.Subscriber(
            f"/{name}/correction", MapCorrection, self._on_correction, queue_size=5
        )
        rospy.loginfo("client %s (%s): waiting for %s", name, sensor, self.camera.describe())

    def _team_cues(self, p, preset) -> TeamCues:
        """Our description (latched: the server places sightings of our marker with our own
        mounts) and the marker sightings and questions to the server."""
        from coop_slam.msg import RobotDescription as RobotDescriptionMsg

        markers = load_yaml_config(
            MarkerConfig, p.config, "markers", layered(preset, "markers", p.markers)
        )
        self.pub_description = rospy.Publisher(
            f"/{self.name}/description", RobotDescriptionMsg, queue_size=1, latch=True
        )
        self.pub_description.publish(
            description_to_msg(
                describe(self.robot_id, self.sensor, self.T_base_cam, markers, p.camera)
            )
        )
        return TeamCues(
            self.robot_id,
            self.T_base_cam,
            MarkerDetector(markers),
            p.marker_every_frames,
            self._vocabulary,
            lambda: self.uplink.engine.segment_base,
            self.pose.cam_frame,
            detect_beside=not self.wait_for_mapping,  # lock-step: the same sightings every run
        )

    def _ready_before_frames(self) -> None:
        """What the first frames would otherwise wait for or be stopped by."""
        warm_up()  # the odometry's compiled kernels
        shared_worker().submit(lambda: None).result()  # the thread tracking shares
        if self.vo_cfg.threaded and self.vo_cfg.ba.enabled:
            prestart_worker()  # and the local BA's process, its kernels loaded
        # Python's full collection scans every object it tracks; here ~140,000, nearly all the
        # libraries' (rospy, numpy, numba, GTSAM): ~40 ms with every thread stopped, about once in
        # a 20 s RedKitchen run, long enough to drop a frame. Collected once now (no frame waits)
        # and frozen, a full collection scans what came after.
        gc.collect()
        gc.freeze()

    def _with_odometry(self, fn):
        with self.lock:
            return None if self.vo is None else fn(self.vo)

    def _vocabulary(self):
        engine = self.uplink.engine
        if engine.vocabulary is None:
            engine.vocabulary = server_vocabulary(self.name, 3.0)
        return engine.vocabulary

    def _camera_changed(self, old, new) -> None:
        """A new camera model (the tracker's lock held): a new map."""
        rospy.logwarn(
            "client %s: camera model changed (%dx%d fx=%.1f -> %dx%d fx=%.1f); starting a new map",
            self.name,
            old.width,
            old.height,
            old.fx,
            new.width,
            new.height,
            new.fx,
        )
        if self.vo is not None:
            self.vo.reset()
            self._hand_to_uplink(None)  # after what its frames made; everything it holds goes
            self.uplink.engine.odometry_replaced(self.vo.keyframes_made, self.vo.map_segment)
            self.vo.close()
            self.vo = None

    def _frame_not_tracked(self, stamp, dropped: bool) -> None:
        stats = self._FrameStats(robot_id=self.robot_id, tracking_ok=False, dropped=dropped)
        stats.header.stamp = stamp
        self.pub_stats.publish(stats)

    # --- tracking ---------------------------------------------------------------------------------
    def _track_frames(self) -> None:
        while not rospy.is_shutdown():
            item = self.camera.slot.take(timeout_s=0.5)
            if item is not None:
                self._track(*item)

    def _track(self, image_msg: Image, second_msg: Image | None) -> None:
        stamp = image_msg.header.stamp
        stats = self._FrameStats(robot_id=self.robot_id, tracking_ok=False)
        stats.header.stamp = stamp
        self.camera.wait_for_camera()
        frame = None
        try:
            with self.lock:
                image, second = self.camera.decode(image_msg, second_msg)
                if self.vo is None:
                    self.vo = VisualOdometry(self.vo_cfg, self.camera.camera)
                    self.uplink.engine.camera = self.camera.camera
                res = self.vo.track(stamp.to_sec(), image, second)
                self.frames += 1
                self._after_mapping(stats)
                if res.state == STATE_INITIALIZING:  # e.g. a monocular camera not moved yet
                    rospy.loginfo_throttle(5.0, "client %s: %s", self.name, res.message)
                elif res.message.startswith(("map initialized", "relocalized in the team map")):
                    rospy.loginfo("client %s: %s", self.name, res.message)
                stats.track_ms, stats.tracking_ok = res.track_ms, bool(res.ok)
                self.cues.maybe_ask(self.vo)
                self._hand_to_uplink(stamp.to_sec())
                frame = TrackedFrame(
                    stamp,
                    res,
                    self.vo,
                    self.uplink.engine.kf_id_base,
                    self.frames,
                    image,
                    self.camera.camera.K,
                )
        except CoopSlamError as exc:
            self.rejects.reject(self.camera.topics["image"], str(exc))
        finally:
            self.outputs.put(frame, stats)  # pose, TF, path, cloud, sightings, stats

    def _after_mapping(self, stats) -> None:
        stats.mapping_backlog = min(self.vo.mapping_backlog, 65535)
        if self.wait_for_mapping:
            self.vo.flush()
        elif stats.mapping_backlog >= self.mapping_backlog_warn:
            rospy.logwarn_throttle(
                10.0,
                "client %s: local mapping is %d keyframes behind the camera (the map is refined "
                "later than tracking needs it)",
                self.name,
                stats.mapping_backlog,
            )

    def _hand_to_uplink(self, now_s: float | None) -> None:
        """The odometry's events at data time ``now_s`` to the uplink's thread (None: the
        odometry is closing, everything it holds goes). Done before returning in lock-step
        playback, so the messages are the same however loaded the machine is, and at closing."""
        self._take_notes()
        if now_s is not None:
            self.uplink.last_frame_wall = time.monotonic()
        self._uplink_jobs.put((self.vo.drain_events(), now_s))
        if self.wait_for_mapping or now_s is None:
            self._uplink_jobs.join()
            self._take_notes()

    def _uplink_loop(self) -> None:
        # Never takes self.lock: its holders wait for this thread (join) with it held.
        while True:
            events, now_s = self._uplink_jobs.get()
            try:
                messages, notes = self._uplink_step(events, now_s)
                # Noted before they go: a correction that answers them finds their keyframes.
                with self._notes_lock:
                    self._uplink_notes.extend(notes)
                self.uplink.send(messages)
            except Exception as exc:  # this thread is what sends: it must not end
                rospy.logerr("client %s: uplink: %s: %s", self.name, type(exc).__name__, exc)
            finally:
                self._uplink_jobs.task_done()

    def _take_notes(self) -> None:
        """What the uplink's thread noted (keyframes, segments) to the path (the tracker's lock
        held)."""
        with self._notes_lock:
            notes, self._uplink_notes = self._uplink_notes, []
        if notes:
            self.pose.note(notes)

    def _uplink_step(self, events, now_s: float | None) -> tuple[list, list]:
        """``events`` at data time ``now_s`` through the uplink (None: the odometry is closing,
        everything it holds goes); says what they say on the console and returns the messages
        to send and the notes."""
        step = self.uplink.engine.events(events, now_s)
        for note in step.notes:
            if note.kind == "warning":
                rospy.logwarn("client %s: %s", self.name, note.text)
            elif note.kind == "segment":
                rospy.logwarn(
                    "client %s: tracking lost for good; new map segment %d (%s)",
                    self.name,
                    note.segment,
                    note.text,
                )
        return step.messages, step.notes

    def _counters(self, stats) -> None:
        stats.keyframes = len(self.pose.kf_poses)
        stats.keyframes_sent = self.uplink.engine.keyframes_sent
        stats.keyframes_held_back = self.uplink.engine.keyframes_held_back
        stats.unacked = self.uplink.engine.unacked
        self._counters_said = (stats.keyframes_sent, stats.keyframes_held_back, stats.unacked)

    def _flush_uplink(self, blocking: bool = True) -> None:
        """Send whatever the uplink holds, and say the delivery counters when they changed since
        the last frame's (no frame will: the demo waits for the unacknowledged to be stored). Not
        ``blocking``: nothing when a frame is being tracked (the resend thread must not wait for
        one)."""
        if not self.lock.acquire(blocking=blocking):
            return
        try:
            self._uplink_jobs.join()  # the frames' events first (no new ones: the lock is held)
            self._take_notes()
            self.pose.publish_correction(self.vo, self.uplink.engine.kf_id_base)
            self.cues.finish(self.vo)
            if self.uplink.engine.held:
                self.uplink.send(self.uplink.engine.flush())
            said = self._counters_said
            stats = self._FrameStats(robot_id=self.robot_id, tracking_ok=True)  # stamp 0
            self._counters(stats)
            if self._counters_said != said:
                self.pub_stats.publish(stats)
        finally:
            self.lock.release()

    def _on_correction(self, msg) -> None:
        # While frames come, the corrected path and cloud go after the next frame's pose (here,
        # with the tracker's lock held, they held up the next frame by 20-50 ms).
        frames_coming = time.monotonic() - self.uplink.last_frame_wall < FRAMES_COMING_S
        with self.lock:
            self._take_notes()  # the keyframes it places
            self.pose.correction(
                msg, self.vo, self.uplink.engine.kf_id_base, publish_now=not frames_coming
            )

    def shutdown(self) -> None:
        self.camera.slot.close()
        self.outputs.drain(2.0)  # the last frames' outputs, if they go in time
        with self.lock:
            if self.vo is not None:
                self._uplink_jobs.join()
                self.uplink.send(self.uplink.engine.flush())  # best effort: going down
                self.vo.close()
            self.uplink.close()
        rospy.loginfo(
            "client %s: %d frames, %d dropped (busy), %d keyframes, %d corrections applied, %d "
            "rejected messages",
            self.name,
            self.frames,
            self.camera.slot.dropped,
            len(self.pose.kf_poses),
            self.pose.corrections_applied,
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
