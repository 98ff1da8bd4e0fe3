"""Lock-step playback: a robot's frame acknowledgements (``robot_k/frame_stats``) and the wait for
every camera topic's subscribers before the first frame, shared by both players."""

from __future__ import annotations

import threading
import time

import rospy

from .player_config import PlayerConfig


class FrameAcks:
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
