"""Rejecting bad input in nodes: one clear log line per rejected message, and a count per reason."""

from __future__ import annotations

import collections
import time

import rospy


class RejectCounter:
    """Counts rejected messages per topic; logs each rejection once per ``log_period_s`` per topic
    (so a flood of bad messages cannot flood the log) with the reason and the running count."""

    def __init__(self, node_name: str, log_period_s: float = 5.0):
        self.node_name = node_name
        self.log_period_s = log_period_s
        self.counts: collections.Counter[str] = collections.Counter()
        self._last_log: dict[str, float] = {}

    def reject(self, topic: str, reason: str) -> None:
        self.counts[topic] += 1
        now = time.monotonic()  # wall time: sim time may stand still in lock-step playback
        last = self._last_log.get(topic)
        if last is None or abs(now - last) >= self.log_period_s:
            self._last_log[topic] = now
            rospy.logwarn(
                "%s: rejected message on %s (%d rejected so far): %s",
                self.node_name,
                topic,
                self.counts[topic],
                reason,
            )

    @property
    def total(self) -> int:
        return sum(self.counts.values())
