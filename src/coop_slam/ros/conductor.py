"""Playback split over hosts (``scripts/demo --hosts``): a *conductor* on the station drives /clock
and steps through all robots' frames; a *camera* player on each robot's host plays that robot's
frames when told, so a robot's images never leave its host.

Both run on the harness network (the player's, which a field team does not have): the conductor
publishes each step on ``/player/step`` (``std_msgs/Header``: ``seq`` the step's index, ``stamp``
its play time, ``frame_id`` the frames stepped so far) and, in lock-step, waits until every camera
with a frame in the step reported it done on ``/player/played`` (``frame_id`` the robot,
``seq`` index + 1; ``seq`` 0 says "ready" before the first step).
"""

from __future__ import annotations

import bisect
import queue
import threading
import time

import rospy
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Bool, Header

from ..playback import camera_topic_names, group_simultaneous
from .lockstep import wait_for_consumers

STEP_TOPIC = "/player/step"
PLAYED_TOPIC = "/player/played"
READY_EVERY_S = 1.0  # a camera says "ready" this often until the first step comes


def _robot_of(frame_id: str) -> int | None:
    try:
        return int(frame_id.rsplit("_", 1)[1])
    except (IndexError, ValueError):
        return None


class _Played:
    """The conductor's view of the cameras: who is ready, and the last step each finished."""

    def __init__(self, robot_ids: list[int]):
        self.done = {r: -1 for r in robot_ids}
        self.ready: set[int] = set()
        self.cond = threading.Condition()
        self.sub = rospy.Subscriber(PLAYED_TOPIC, Header, self._on_played, queue_size=100)

    def _on_played(self, msg: Header) -> None:
        robot = _robot_of(msg.frame_id)
        if robot not in self.done:
            return
        with self.cond:
            self.ready.add(robot)
            self.done[robot] = max(self.done[robot], int(msg.seq) - 1)
            self.cond.notify_all()

    def wait(self, ready, timeout_s: float) -> list[int]:
        """Wait until ``ready()`` (under the lock) or the timeout; the robots not done then."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while not ready():
                remaining = deadline - time.monotonic()
                if remaining <= 0 or rospy.is_shutdown():
                    break
                self.cond.wait(min(remaining, 0.2))
            return [r for r in self.done if r not in self.ready]

    def wait_step(self, index: int, robot_ids: set[int], timeout_s: float) -> list[int]:
        """Wait until ``robot_ids`` finished step ``index``; those that did not in time."""
        self.wait(lambda: all(self.done[r] >= index for r in robot_ids), timeout_s)
        return sorted(r for r in robot_ids if self.done[r] < index)


def conduct(node) -> None:
    """The station's part of a player node (``~role conductor``): /clock, the steps, ``~done``."""
    cfg = node.cfg
    groups = group_simultaneous(node.schedule)
    robot_ids = sorted({s.robot_id for s in node.schedule})
    step_pub = rospy.Publisher(STEP_TOPIC, Header, queue_size=1000)
    played = _Played(robot_ids)
    node.clock.publish(Clock(clock=rospy.Time.from_sec(max(0.0, groups[0][0].play_s - 0.1))))
    missing = played.wait(
        lambda: played.ready >= set(robot_ids) and step_pub.get_num_connections() >= len(robot_ids),
        cfg.wait_for_subscribers_s * 2,
    )
    if missing:
        rospy.logwarn("player: no camera player is ready for robots %s; playing anyway", missing)
    time.sleep(0.5)  # the last connections settle
    rospy.loginfo(
        "player (conductor): %d robots, %d frames, %s",
        len(robot_ids),
        len(node.schedule),
        "lock-step" if cfg.lockstep else f"{cfg.rate:g} x real time",
    )
    wall0, sim0 = time.monotonic(), groups[0][0].play_s
    frames, last_progress = 0, time.monotonic()
    for index, group in enumerate(groups):
        if rospy.is_shutdown():
            return
        play_s = group[0].play_s
        if not cfg.lockstep:
            delay = wall0 + (play_s - sim0) / cfg.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        frames += len(group)
        node.clock.publish(Clock(clock=rospy.Time.from_sec(play_s)))
        step_pub.publish(Header(seq=index, stamp=rospy.Time.from_sec(play_s), frame_id=str(frames)))
        if cfg.lockstep:
            late = played.wait_step(index, {g.robot_id for g in group}, cfg.ack_timeout_s)
            if late:
                rospy.logwarn(
                    "player: robots %s did not finish the frame at %.3f s within %.0f s; going on",
                    late,
                    play_s,
                    cfg.ack_timeout_s,
                )
        if time.monotonic() - last_progress > cfg.progress_period_s or index == len(groups) - 1:
            last_progress = time.monotonic()
            rospy.loginfo(
                "player: %d/%d frames (%.0f %%), sim time %.2f s",
                frames,
                len(node.schedule),
                100.0 * frames / len(node.schedule),
                play_s,
            )
    node.clock.publish(Clock(clock=rospy.Time.from_sec(node.schedule[-1].play_s + 0.5)))
    node.done.publish(Bool(True))
    rospy.loginfo("player: done, %d frames stepped", frames)


def play_camera(node) -> None:
    """A robot host's part of a player node (``~role camera``): its robots' frames, each when the
    conductor steps to its time; no /clock."""
    cfg = node.cfg
    steps: queue.Queue = queue.Queue()
    rospy.Subscriber(STEP_TOPIC, Header, steps.put, queue_size=1000)
    played_pub = rospy.Publisher(PLAYED_TOPIC, Header, queue_size=100)
    wait_for_consumers(
        {
            rid: [p for topic, p in t.pubs.items() if topic in camera_topic_names(rid)]
            for rid, t in node.topics.items()
        },
        cfg,
    )
    times = [s.play_s for s in node.schedule]
    started = False
    last_ready = 0.0
    while not rospy.is_shutdown():
        if not started and time.monotonic() - last_ready > READY_EVERY_S:
            last_ready = time.monotonic()
            for rid in node.topics:
                played_pub.publish(Header(seq=0, frame_id=f"robot_{rid}"))
        try:
            step = steps.get(timeout=0.2)
        except queue.Empty:
            continue
        started = True
        play_s = step.stamp.to_sec()
        lo, hi = bisect.bisect_left(times, play_s - 1e-6), bisect.bisect_right(times, play_s + 1e-6)
        for item in node.schedule[lo:hi]:
            topics = node.topics[item.robot_id]
            node.publish_frame(topics, item)
            if cfg.lockstep and topics.has_consumer:
                if not topics.wait_ack(item.play_s, cfg.ack_timeout_s, item.frame):
                    rospy.logwarn(
                        "player: robot_%d did not acknowledge the frame at %.3f s within %.0f s",
                        item.robot_id,
                        item.play_s,
                        cfg.ack_timeout_s,
                    )
            played_pub.publish(
                Header(seq=int(step.seq) + 1, stamp=step.stamp, frame_id=f"robot_{item.robot_id}")
            )
