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

import re
import threading
import time

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Bool

from ..config import load_config
from ..datasets import DatasetError
from ..errors import CoopSlamError
from ..playback import (
    COLOR_TOPIC,
    PlaybackError,
    RobotStream,
    build_schedule,
    camera_topic_names,
    camera_topics,
    ground_truth_by_frame,
    group_simultaneous,
    image_topic,
    load_streams,
    parse_robot_ids,
    parse_sensors,
)
from ..prefetch import Prefetcher, PrefetchError
from .convert import camera_info_to_msg, image_to_msg, pose_to_msg
from .player_config import PlayerConfig


def frame_messages(
    stream: RobotStream,
    frame,
    play_s: float,
    depth_encoding: str = "32FC1",
    T_world_cam: np.ndarray | None = None,
):
    """The messages of one robot's frame at ``play_s``, in publishing order: [(topic, msg)].

    Camera info, depth (or the right image), then colour (left): clients keep the camera info and
    synchronise the images; ground truth ``T_world_cam`` (camera optical frame in ``gt_world``),
    when given and finite, last.
    """
    seq = stream.sequence
    ns = f"/{stream.name}"
    optical_frame = f"{stream.name}/camera_optical"
    stamp = rospy.Time.from_sec(play_s)
    color = seq.load_color(frame)
    enc = "bgr8" if color.ndim == 3 else "mono8"
    topics = camera_topics(stream.robot_id, seq.camera.sensor)
    if seq.camera.sensor == "stereo":
        right = seq.load_right(frame)
        right_frame = f"{stream.name}/camera_right_optical"
        out = [
            (topics["infos"]["left"], camera_info_to_msg(seq.camera, stamp, optical_frame)),
            (
                topics["infos"]["right"],
                camera_info_to_msg(seq.camera, stamp, right_frame, right=True),
            ),
            (topics["second"], image_to_msg(right, enc, stamp, right_frame)),
            (topics["image"], image_to_msg(color, enc, stamp, optical_frame)),
        ]
        return out + _ground_truth(ns, stamp, T_world_cam)
    out = [(topics["infos"]["color"], camera_info_to_msg(seq.camera, stamp, optical_frame))]
    if seq.camera.sensor == "rgbd":
        depth_m = seq.load_depth_m(frame)
        if depth_encoding == "16UC1":
            depth_img = np.clip(np.rint(depth_m * 1000.0), 0, 65535).astype(np.uint16)
        else:
            depth_img = depth_m
        out.append(
            (topics["second"], image_to_msg(depth_img, depth_encoding, stamp, optical_frame))
        )
    out.append((topics["image"], image_to_msg(color, enc, stamp, optical_frame)))
    return out + _ground_truth(ns, stamp, T_world_cam)


def _messages_bytes(group_messages: dict) -> int:
    """Bytes of image data in a frame group's messages (what the prefetch budget counts)."""
    return sum(
        len(getattr(msg, "data", b""))
        for messages in group_messages.values()
        if isinstance(messages, list)
        for _, msg in messages
    )


def _ground_truth(ns: str, stamp, T_world_cam) -> list:
    if T_world_cam is None or not np.all(np.isfinite(T_world_cam)):
        return []
    msg = PoseStamped(pose=pose_to_msg(T_world_cam))
    msg.header.stamp, msg.header.frame_id = stamp, "gt_world"
    return [(f"{ns}/ground_truth/pose", msg)]


class _Acks:
    """A robot's lock-step acknowledgements: the latest frame stamp its client reported done."""

    def __init__(self, robot_name: str):
        from coop_slam.msg import FrameStats

        self.acked_s = -1.0
        self.cond = threading.Condition()
        self.sub = rospy.Subscriber(
            f"/{robot_name}/frame_stats", FrameStats, self._on_ack, queue_size=50
        )

    def _on_ack(self, msg) -> None:
        with self.cond:
            self.acked_s = max(self.acked_s, msg.header.stamp.to_sec())
            self.cond.notify_all()

    @property
    def has_consumer(self) -> bool:
        return self.sub.get_num_connections() > 0

    def wait(self, play_s: float, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while self.acked_s < play_s - 1e-6:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or rospy.is_shutdown():
                    return False
                self.cond.wait(min(remaining, 0.1))
        return True


class _RobotTopics:
    def __init__(self, stream: RobotStream, depth_encoding: str):
        self.stream = stream
        self.depth_encoding = depth_encoding
        self.T_world_cam = ground_truth_by_frame(stream)
        self.pubs = {}
        first = stream.sequence.frames[0]
        for topic, msg in frame_messages(stream, first, 0.0, depth_encoding, np.eye(4)):
            self.pubs[topic] = rospy.Publisher(topic, type(msg), queue_size=20)
        self.color = self.pubs[image_topic(stream.robot_id, stream.sequence.camera.sensor)]
        self.acks = _Acks(stream.name)

    @property
    def has_consumer(self) -> bool:
        return self.acks.has_consumer

    def messages(self, play_s: float, frame) -> list:
        T_world_cam = self.T_world_cam[frame.index]
        return frame_messages(self.stream, frame, play_s, self.depth_encoding, T_world_cam)

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
            if self.acks.wait(play_s, min(1.0, max(remaining, 0.0))):
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


def wait_for_consumers(camera_pubs: dict, cfg: PlayerConfig) -> None:
    """Before playing: wait (each step at most ``cfg.wait_for_subscribers_s``) until each of every
    robot's camera topics (robot id -> their publishers: images and camera infos) has a
    subscriber, then until ``cfg.wait_for_node`` (a bag recorder started alongside) subscribes to
    every robot's keyframes, so neither misses the first frames. (A client that subscribed to its
    images but not yet to its camera info rejected the first frame: a monocular map then started
    from another pair of views, and the run differed from the one before.)"""
    import rosgraph

    deadline = time.monotonic() + cfg.wait_for_subscribers_s
    while time.monotonic() < deadline and not rospy.is_shutdown():
        if all(p.get_num_connections() > 0 for pubs in camera_pubs.values() for p in pubs):
            break
        time.sleep(0.1)
    if cfg.wait_for_node:
        topics = {f"/robot_{r}/keyframes" for r in camera_pubs}
        master = rosgraph.Master(rospy.get_name())
        deadline = time.monotonic() + cfg.wait_for_subscribers_s
        while time.monotonic() < deadline and not rospy.is_shutdown():
            subscribers = dict(master.getSystemState()[1])  # topic -> subscribing nodes
            if all(cfg.wait_for_node in subscribers.get(topic, ()) for topic in topics):
                break
            time.sleep(0.2)
        else:
            rospy.logwarn(
                "player: %s did not subscribe to %s in time; playing anyway",
                cfg.wait_for_node,
                sorted(topics),
            )
    time.sleep(0.5)  # let the connections settle so the first frames are not lost
    for pubs in camera_pubs.values():
        alone = sorted(p.resolved_name for p in pubs if p.get_num_connections() == 0)
        if alone:
            rospy.logwarn("player: nobody subscribes to %s; playing anyway", ", ".join(alone))


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
        self.topics = {s.robot_id: _RobotTopics(s, cfg.depth_encoding) for s in self.source.streams}
        self.clock = rospy.Publisher("/clock", Clock, queue_size=10)
        self.done = rospy.Publisher("~done", Bool, queue_size=1, latch=True)
        self.done.publish(Bool(False))

    def run(self) -> None:
        cfg = self.cfg
        if not self.schedule:
            rospy.logwarn("player: nothing to play")
            return
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
        clients' cores when a frame is due nor delays its publishing; lock-step decodes each
        frame when due (the clients wait for it anyway)."""
        if self.cfg.lockstep or self.cfg.preload_mb <= 0:
            return None
        prefetch = Prefetcher(
            groups, self._group_messages, _messages_bytes, int(self.cfg.preload_mb * 2**20)
        )
        rospy.on_shutdown(prefetch.close)  # Ctrl-C while decoding ahead stops at once
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

    def _play(self, groups, prefetch: Prefetcher | None) -> None:
        cfg = self.cfg
        total = len(self.schedule)
        warned_free = set()
        wall0, sim0 = time.monotonic(), groups[0][0].play_s
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
                try:
                    messages = ready.get(g.robot_id)
                    if isinstance(messages, DatasetError):
                        raise messages
                    self.topics[g.robot_id].publish(play_s, g.frame, messages)
                except DatasetError as exc:
                    rospy.logerr(
                        "player: skipping robot_%d frame %d: %s", g.robot_id, g.frame.index, exc
                    )
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


# What the system itself publishes: a bag recorded on a running team may hold these, and replaying
# them would fight the live clients and server.
SYSTEM_OUTPUT_TOPICS = re.compile(
    r"^/(robot_\d+/(keyframes|keyframe_ack|frame_stats|correction|pose|path|local_map)"
    r"|team_map/.*|merge_events|server/.*|robot_sightings|player/.*|clock|rosout(_agg)?|tf)$"
)


class BagPlayer:
    """Replays a rosbag (the user's own recording, or one written by ``scripts/export_bag``) and
    drives /clock with the bag's time.

    Topics keep their names; the system's own outputs in the bag are not replayed. In lock-step
    mode, robot k's next colour image waits until its client acknowledged the previous one on
    ``robot_k/frame_stats`` (other robots' messages keep flowing meanwhile); robots without a
    consumer, and everything when not in lock-step, play at ``rate`` x real time.
    """

    def __init__(self, cfg: PlayerConfig):
        import rosbag

        self.cfg = cfg
        try:
            self.bag = rosbag.Bag(cfg.bag)
        except (OSError, rosbag.ROSBagException) as exc:
            raise PlaybackError(f"cannot open bag {cfg.bag}: {exc}") from None
        self.clock = rospy.Publisher("/clock", Clock, queue_size=10)
        self.done = rospy.Publisher("~done", Bool, queue_size=1, latch=True)
        self.done.publish(Bool(False))
        self.pubs = {}
        for topic, info in self.bag.get_type_and_topic_info().topics.items():
            if SYSTEM_OUTPUT_TOPICS.match(topic):
                continue
            self.pubs[topic] = info.msg_type
        self.robot_ids = sorted(
            int(m.group(1)) for m in map(COLOR_TOPIC.match, self.pubs) if m is not None
        )
        if not self.robot_ids:
            raise PlaybackError(
                f"bag {cfg.bag} has no robot camera topics (/robot_<k>/camera/color/image_raw "
                "or /robot_<k>/camera/left/image_rect); "
                f"it has: {', '.join(sorted(self.pubs)) or 'nothing'}"
            )
        self.acks = {rid: _Acks(f"robot_{rid}") for rid in self.robot_ids}

    def run(self) -> None:
        import roslib.message

        cfg = self.cfg
        publishers = {}
        for topic, type_name in self.pubs.items():
            cls = roslib.message.get_message_class(type_name)
            if cls is None:
                rospy.logwarn(
                    "player: message type %s of %s unknown here; skipped", type_name, topic
                )
                continue
            publishers[topic] = rospy.Publisher(topic, cls, queue_size=20)
        start = self.bag.get_start_time()
        self.clock.publish(Clock(clock=rospy.Time.from_sec(max(0.0, start - 0.1))))
        cameras = {}  # robot id -> its camera topics' publishers (images, camera infos)
        for topic in publishers:
            if m := COLOR_TOPIC.match(topic):
                rid = int(m.group(1))
                wanted = camera_topic_names(rid)
                cameras[rid] = [p for t, p in publishers.items() if t in wanted]
        wait_for_consumers(cameras, cfg)
        lockstep = {rid for rid, a in self.acks.items() if cfg.lockstep and a.has_consumer}
        for rid in sorted(set(self.acks) - lockstep):
            rospy.logwarn(
                "player: robot_%d's frames play at %g x real time (%s)",
                rid,
                cfg.rate,
                "no consumer acknowledges them" if cfg.lockstep else "lock-step off",
            )
        total = self.bag.get_message_count(topic_filters=list(publishers))
        rospy.loginfo("player: bag %s, robots %s, %d messages", cfg.bag, self.robot_ids, total)
        pending = {}  # robot id -> stamp of its last colour image not yet acknowledged
        wall0 = time.monotonic()
        last_progress = wall0
        for k, (topic, msg, t) in enumerate(self.bag.read_messages(topics=list(publishers))):
            if rospy.is_shutdown():
                return
            m = COLOR_TOPIC.match(topic)
            rid = int(m.group(1)) if m else None
            if rid in lockstep:
                if rid in pending and not self.acks[rid].wait(pending[rid], cfg.ack_timeout_s):
                    rospy.logwarn(
                        "player: robot_%d did not acknowledge the frame at %.3f s within "
                        "%.0f s; going on",
                        rid,
                        pending[rid],
                        cfg.ack_timeout_s,
                    )
                pending[rid] = msg.header.stamp.to_sec()
            elif not lockstep:
                delay = wall0 + (t.to_sec() - start) / cfg.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            self.clock.publish(Clock(clock=t))
            publishers[topic].publish(msg)
            if time.monotonic() - last_progress > cfg.progress_period_s:
                last_progress = time.monotonic()
                rospy.loginfo(
                    "player: %d/%d bag messages (%.0f %%), sim time %.2f s",
                    k + 1,
                    total,
                    100.0 * (k + 1) / max(total, 1),
                    t.to_sec() - start,
                )
        for rid, stamp_s in pending.items():
            self.acks[rid].wait(stamp_s, cfg.ack_timeout_s)
        self.clock.publish(Clock(clock=rospy.Time.from_sec(self.bag.get_end_time() + 0.5)))
        self.done.publish(Bool(True))
        rospy.loginfo("player: bag done")


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
