"""Dataset player node: publishes robots' camera streams, ground truth and /clock.

Per robot k (``robot_k``), an RGB-D camera: ``camera/color/image_raw`` (bgr8, or mono8),
``camera/color/camera_info``, ``camera/depth/image_raw`` (32FC1 metres or 16UC1 millimetres,
registered to colour); a stereo camera (ROS stereo conventions, rectified):
``camera/left/image_rect``, ``camera/right/image_rect``, ``camera/left/camera_info``,
``camera/right/camera_info`` (baseline in its projection matrix); and ``ground_truth/pose``
(camera optical frame in ``gt_world``).

Timing never uses rospy's clock (this node *drives* /clock). In lock-step mode the next frames are
published only after every consuming client acknowledged the previous ones on
``robot_k/frame_stats``, so results do not depend on machine speed; robots without a consumer play
at ``rate`` × real time.
"""

from __future__ import annotations

import time

import numpy as np
import rospy
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Bool

from ..config import load_config
from ..datasets import DatasetError
from ..errors import CoopSlamError
from ..playback import (
    RobotStream,
    build_schedule,
    camera_topic_names,
    ground_truth_by_frame,
    group_simultaneous,
    image_topic,
    load_streams,
    parse_clock_offsets,
    parse_robot_ids,
    parse_sensors,
)
from ..prefetch import Prefetcher, PrefetchError
from .bag_player import BagPlayer
from .camera_messages import frame_messages, messages_bytes
from .conductor import conduct, play_camera
from .lockstep import FrameAcks, wait_for_consumers
from .player_config import PlayerConfig

# Lock-step playback decodes this far ahead at most [MiB] (~20 frame groups of two RGB-D robots):
# enough to stay ahead of clients that each take a frame at a time.
LOCKSTEP_AHEAD_MB = 64.0


class _RobotTopics:
    def __init__(self, stream: RobotStream, depth_encoding: str, clock_offset_s: float = 0.0):
        self.stream = stream
        self.depth_encoding = depth_encoding
        # A robot whose clock runs ahead stamps its images so (and acknowledges them so).
        self.clock_offset_s = clock_offset_s
        self.T_world_cam = ground_truth_by_frame(stream)
        self.pubs = {}
        first = stream.sequence.frames[0]
        for topic, msg in frame_messages(stream, first, 0.0, depth_encoding, np.eye(4)):
            self.pubs[topic] = rospy.Publisher(topic, type(msg), queue_size=20)
        self.color = self.pubs[image_topic(stream.robot_id, stream.sequence.camera.sensor)]
        self.acks = FrameAcks(stream.name)

    @property
    def has_consumer(self) -> bool:
        return self.acks.has_consumer

    def messages(self, play_s: float, frame) -> list:
        T_world_cam = self.T_world_cam[frame.index]
        stamp_s = play_s + self.clock_offset_s
        return frame_messages(self.stream, frame, stamp_s, self.depth_encoding, T_world_cam)

    def publish(self, play_s: float, frame, messages: list | None = None) -> None:
        for topic, msg in messages if messages is not None else self.messages(play_s, frame):
            self.pubs[topic].publish(msg)

    def wait_ack(self, play_s: float, timeout_s: float, frame=None) -> bool:
        """Wait for the client's acknowledgement of the frame at play_s. A client that went away
        and came back meanwhile (restarted) never got the frame: it is sent again."""
        deadline = time.monotonic() + timeout_s
        gone = False
        while True:
            remaining = deadline - time.monotonic()
            if self.acks.wait(play_s + self.clock_offset_s, min(1.0, max(remaining, 0.0))):
                return True
            if remaining <= 1.0 or rospy.is_shutdown():
                return False
            if self.color.get_num_connections() == 0:
                gone = True
            elif gone and frame is not None:
                gone = False
                rospy.logwarn(
                    "player: robot_%d's client is back (restarted?): sending the frame at "
                    "%.3f s again",
                    self.stream.robot_id,
                    play_s,
                )
                time.sleep(1.0)  # its other subscriptions (depth, camera_info) connect too
                self.publish(play_s, frame)


class PlayerNode:
    def __init__(self, cfg: PlayerConfig):
        self.cfg = cfg
        offsets = list(cfg.start_offsets_s) or None
        self.source = load_streams(
            scenario=cfg.scenario or None,
            dataset=cfg.dataset or None,
            split=cfg.split or None,
            robots=cfg.robots or None,
            seed=cfg.seed,
            camera_file=cfg.camera_file or None,
            start_offsets_s=offsets,
            world_params={"duration_s": cfg.duration_s} if cfg.duration_s > 0 else None,
            sensors=parse_sensors(cfg.sensors),
            only_robots=parse_robot_ids(cfg.only_robots),
            progress=lambda done, total: rospy.loginfo_throttle(
                5.0, "player: generating world %d/%d frames", done, total
            ),
        )
        self.schedule = build_schedule(self.source.streams, keep_timing=cfg.keep_timing)
        # A conductor only steps through the frames: the cameras stand on the robots' hosts.
        clocks = parse_clock_offsets(cfg.clock_offsets)
        self.topics = {
            s.robot_id: _RobotTopics(s, cfg.depth_encoding, clocks.get(s.robot_id, 0.0))
            for s in self.source.streams
            if cfg.role != "conductor"
        }
        if cfg.role != "camera":  # a camera follows the conductor's clock
            self.clock = rospy.Publisher("/clock", Clock, queue_size=10)
            self.done = rospy.Publisher("~done", Bool, queue_size=1, latch=True)
            self.done.publish(Bool(False))

    def run(self) -> None:
        cfg = self.cfg
        if not self.schedule:
            rospy.logwarn("player: nothing to play")
            return
        if cfg.role == "conductor":
            return conduct(self)
        if cfg.role == "camera":
            return play_camera(self)
        self.clock.publish(
            Clock(clock=rospy.Time.from_sec(max(0.0, self.schedule[0].play_s - 0.1)))
        )
        wait_for_consumers(
            {
                rid: [p for topic, p in t.pubs.items() if topic in camera_topic_names(rid)]
                for rid, t in self.topics.items()
            },
            self.cfg,
        )
        groups = group_simultaneous(self.schedule)
        total = len(self.schedule)
        rospy.loginfo(
            "player: %d robots, %d frames, %s",
            len(self.topics),
            total,
            "lock-step" if cfg.lockstep else f"{cfg.rate:g} x real time",
        )
        prefetch = self._prefetch(groups)
        try:
            self._play(groups, prefetch)
        finally:
            if prefetch is not None:
                prefetch.close()

    def _prefetch(self, groups) -> Prefetcher | None:
        """Live playback decodes frames ahead (up to ~preload_mb), so decoding neither takes the
        clients' cores when a frame is due nor delays its publishing. Lock-step decodes the next
        few frames while the clients work on this one (a third of the player's time per frame
        was spent decoding while the clients waited for it), starting at once."""
        if self.cfg.preload_mb <= 0:
            return None
        budget_mb = self.cfg.preload_mb
        if self.cfg.lockstep:
            budget_mb = min(budget_mb, LOCKSTEP_AHEAD_MB)
        prefetch = Prefetcher(groups, self._group_messages, messages_bytes, int(budget_mb * 2**20))
        rospy.on_shutdown(prefetch.close)  # Ctrl-C while decoding ahead stops at once
        if self.cfg.lockstep:
            return prefetch
        t0 = time.monotonic()
        prefetch.wait_filled(
            lambda done, total: rospy.loginfo(
                "player: decoding frames ahead, %d/%d groups", done, total
            )
        )
        done, total = prefetch.filled()
        rospy.loginfo(
            "player: %d of %d frame groups decoded ahead in %.1f s (~preload_mb %g)",
            done,
            total,
            time.monotonic() - t0,
            self.cfg.preload_mb,
        )
        return prefetch

    def _group_messages(self, group) -> dict:
        """Each robot's messages of a frame group, or the DatasetError of its frame."""
        out = {}
        for g in group:
            try:
                out[g.robot_id] = self.topics[g.robot_id].messages(g.play_s, g.frame)
            except DatasetError as exc:
                out[g.robot_id] = exc
        return out

    def publish_frame(self, topics: _RobotTopics, item, messages=None) -> None:
        """Publish a scheduled frame (``messages``: decoded ahead, or the error decoding met); a
        frame that cannot be read is skipped, saying so."""
        try:
            if isinstance(messages, DatasetError):
                raise messages
            topics.publish(item.play_s, item.frame, messages)
        except DatasetError as exc:
            rospy.logerr(
                "player: skipping robot_%d frame %d: %s", item.robot_id, item.frame.index, exc
            )

    def _play(self, groups, prefetch: Prefetcher | None) -> None:
        cfg = self.cfg
        total = len(self.schedule)
        warned_free = set()
        wall0, sim0 = None, groups[0][0].play_s
        published = 0
        last_progress = time.monotonic()
        for index, group in enumerate(groups):
            if rospy.is_shutdown():
                return
            play_s = group[0].play_s
            lockstep_ids = [
                g.robot_id for g in group if cfg.lockstep and self.topics[g.robot_id].has_consumer
            ]
            try:  # taken before the wait for its time, so waiting for the loader overlaps it
                ready = prefetch.get(index) if prefetch is not None else {}
            except PrefetchError:
                return  # closed: shutting down
            if wall0 is None:
                # Paced from the first frame's going out: from before its loading, the frames
                # after it came early and bunched (14 ms apart instead of 33, live RedKitchen),
                # just while a client makes its first frame.
                wall0 = time.monotonic()
            if not lockstep_ids and cfg.rate > 0:
                delay = wall0 + (play_s - sim0) / cfg.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if cfg.lockstep:
                for g in group:
                    if g.robot_id not in lockstep_ids and g.robot_id not in warned_free:
                        warned_free.add(g.robot_id)
                        rospy.logwarn(
                            "player: no consumer acknowledges robot_%d's frames; it plays "
                            "at %g x real time",
                            g.robot_id,
                            cfg.rate,
                        )
            self.clock.publish(Clock(clock=rospy.Time.from_sec(play_s)))
            for g in group:
                self.publish_frame(self.topics[g.robot_id], g, ready.get(g.robot_id))
            frames = {g.robot_id: g.frame for g in group}
            for rid in lockstep_ids:
                if not self.topics[rid].wait_ack(play_s, cfg.ack_timeout_s, frames[rid]):
                    rospy.logwarn(
                        "player: robot_%d did not acknowledge the frame at %.3f s within "
                        "%.0f s; going on",
                        rid,
                        play_s,
                        cfg.ack_timeout_s,
                    )
            published += len(group)
            if time.monotonic() - last_progress > cfg.progress_period_s or published == total:
                last_progress = time.monotonic()
                rospy.loginfo(
                    "player: %d/%d frames (%.0f %%), sim time %.2f s",
                    published,
                    total,
                    100.0 * published / total,
                    play_s,
                )
        # A last clock tick lets consumers finish time-based work on the final frame.
        self.clock.publish(Clock(clock=rospy.Time.from_sec(self.schedule[-1].play_s + 0.5)))
        self.done.publish(Bool(True))
        rospy.loginfo("player: done, %d frames played", published)


def main() -> None:
    rospy.init_node("dataset_player")
    params = {k: v for k, v in rospy.get_param("~", {}).items()}
    try:
        cfg = load_config(PlayerConfig, params)
        node = BagPlayer(cfg) if cfg.bag else PlayerNode(cfg)
    except CoopSlamError as exc:
        rospy.logfatal("player: %s", exc)
        raise SystemExit(1) from exc
    node.run()
    if cfg.exit_when_done:
        return
    rospy.spin()
