"""Rejecting bad input in nodes: every kind of rejection is logged, and a count per reason.

A flood of bad messages must not flood the log, but one line per topic and period would hide every
reason but the first (a fuzzer's 2,300 messages showed a handful). So each distinct reason is
logged the first time it occurs; repeats are counted and reported, one line per reason and period.
Reasons differing only in numbers (ids, sizes, values) are one reason.

The logic is plain Python (testable without ROS); nodes log through ``rospy.logwarn``.
"""

from __future__ import annotations

import collections
import re
import time
from collections.abc import Callable

# Numbers (integers, decimals, exponents, with a sign) in a reason, replaced to group reasons.
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
# Distinct reasons tracked per counter: beyond this, new reasons are counted together (a hostile
# sender varying its messages must not grow the node's memory or the log without bound).
MAX_REASONS = 200
OTHER_REASONS = f"(further reasons, beyond the first {MAX_REASONS})"


def reason_kind(reason: str) -> str:
    """A rejection reason with its numbers replaced by '#', so that 'keyframe 12 of robot 2: 3
    keypoints' and 'keyframe 40 of robot 1: 7 keypoints' count as one reason."""
    return _NUMBER.sub("#", reason)


def _rospy_logwarn(msg: str, *args) -> None:
    import rospy

    rospy.logwarn(msg, *args)


class RejectCounter:
    """Counts rejected messages per topic and per (topic, kind of reason). The first rejection of
    each kind is logged at once with its full reason; repeats are summarised at most once per
    ``log_period_s`` per kind, with the count since the last line and the latest reason.

    ``log`` takes a %-format and its arguments (default ``rospy.logwarn``); ``clock`` gives seconds
    (default wall time: sim time may stand still in lock-step playback)."""

    def __init__(
        self,
        node_name: str,
        log_period_s: float = 5.0,
        log: Callable[..., None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.node_name = node_name
        self.log_period_s = log_period_s
        self._log = log or _rospy_logwarn
        self._clock = clock
        self.counts: collections.Counter[str] = collections.Counter()  # per topic
        self.reason_counts: collections.Counter[tuple[str, str]] = collections.Counter()
        self._pending: dict[tuple[str, str], tuple[int, str]] = {}  # unreported: count, latest
        self._last_log: dict[tuple[str, str], float] = {}

    def reject(self, topic: str, reason: str) -> None:
        self.counts[topic] += 1
        kind = reason_kind(reason)
        key = (topic, kind)
        if key not in self.reason_counts and len(self.reason_counts) >= MAX_REASONS:
            key = (topic, OTHER_REASONS)
        self.reason_counts[key] += 1
        now = self._clock()
        if key not in self._last_log:
            self._last_log[key] = now
            self._log(
                "%s: rejected message on %s (%d rejected on it so far): %s",
                self.node_name,
                topic,
                self.counts[topic],
                reason,
            )
        else:
            n, _ = self._pending.get(key, (0, reason))
            self._pending[key] = (n + 1, reason)
        self.flush(now)

    def flush(self, now: float | None = None, force: bool = False) -> None:
        """Report the repeats of every kind whose period has passed (all of them with ``force``,
        e.g. at shutdown)."""
        now = self._clock() if now is None else now
        for key, (n, latest) in list(self._pending.items()):
            if not force and abs(now - self._last_log[key]) < self.log_period_s:
                continue
            topic, _ = key
            del self._pending[key]
            self._last_log[key] = now
            self._log(
                "%s: %d more rejected on %s for the same reason (%d in all), latest: %s",
                self.node_name,
                n,
                topic,
                self.reason_counts[key],
                latest,
            )

    @property
    def total(self) -> int:
        return sum(self.counts.values())
