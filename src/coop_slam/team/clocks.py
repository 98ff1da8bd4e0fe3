"""Each robot's clock against the server's, and the team's stamps in the server's time.

Robots stamp their keyframes and sightings with their own clocks. Place recognition does not
care, but a rendezvous does: it takes keyframes of two robots within a couple of seconds of a
sighting as seen at once, and a sighting's marker pose as where the other robot was then. A robot
whose clock runs 0.3 s ahead puts its keyframes 0.3 s late (12 cm at 0.4 m/s).

Every keyframe message says when it was sent on the robot's clock; the server notes when it
arrived on its own. ``sent - arrived`` is the robot's offset minus the message's transit time,
so the largest values seen are the offset minus the smallest transit times (the estimate is low
by that much: milliseconds on a LAN, more on a slow radio, where a robot with a right clock reads
as behind by the radio's least delay; the correction then moves its stamps by that delay). Not
the largest itself but a high percentile (``percentile``) of the newest ``window`` messages: a
server whose own clock reading is late (ROS sim time, ``/clock`` delivered after a message that
raced it) would otherwise raise the estimate for good. Once a robot's estimate is beyond
``correct_above_s`` its stamps are taken in the server's time (the estimate subtracted) before
anything is stored, so every comparison across robots is in one time; beyond ``max_offset_s``
the clock is broken (never set), not drifting, and rendezvous involving that robot are refused
with the fix: synchronize the clocks (chrony/NTP).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..config import require
from ..wire.codec import Decoded, Incomplete
from ..wire.record import PlaceSignature

log = logging.getLogger(__name__)


@dataclass
class ClockConfig:
    """Robots' clocks against the server's."""

    # A robot's stamps are moved to the server's time when its offset is beyond this [s]
    # (below, the estimate's own bias -- the smallest transit time -- would be all it moves).
    correct_above_s: float = 0.02
    warn_above_s: float = 0.1  # the server warns (with the fix) beyond this offset [s]
    # Beyond this a clock is broken (never set), not drifting: rendezvous with that robot are
    # refused [s]. Far above any radio's delay, which reads as a clock behind (see above).
    max_offset_s: float = 60.0
    # Messages before an offset is estimated: the first already bounds it (keyframes stored
    # before it would stay on the robot's clock)
    min_messages: int = 1
    # The newest messages an estimate is made of: many, so that a backlog after an outage (each
    # message late by its wait) does not read as a clock behind
    window: int = 500
    percentile: float = 90.0  # of their sent - arrived [%]

    def validate(self) -> None:
        require(self.correct_above_s >= 0, "correct_above_s must be >= 0 [s]")
        require(
            self.max_offset_s > self.warn_above_s >= 0,
            "max_offset_s must be > warn_above_s >= 0 [s]",
        )
        require(self.window >= self.min_messages >= 1, "window >= min_messages >= 1")
        require(50.0 <= self.percentile <= 100.0, "percentile must be in [50, 100] [%]")


class RobotClocks:
    def __init__(self, config: ClockConfig | None = None):
        self.config = config or ClockConfig()
        self.config.validate()
        self._samples: dict[int, deque] = {}  # robot -> the newest sent - arrived [s]
        self._warned: set[int] = set()
        # Messages are observed in the subscribers' threads, offsets read in the worker's.
        self._lock = threading.Lock()

    def observe(self, robot_id: int, sent_s: float, arrived_s: float) -> None:
        """A message robot ``robot_id`` sent at ``sent_s`` (its clock; 0 = not said) arrived at
        ``arrived_s`` (the server's)."""
        if sent_s <= 0 or arrived_s <= 0:
            return
        with self._lock:
            window = self._samples.setdefault(robot_id, deque(maxlen=self.config.window))
            window.append(sent_s - arrived_s)
        if robot_id in self._warned:
            return  # said once
        offset = self.offset(robot_id)
        if offset is not None and abs(offset) > self.config.warn_above_s:
            self._warned.add(robot_id)
            log.warning(
                "robot %d's clock is %.3f s %s the server's: synchronize the robots' clocks "
                "(chrony or NTP against the master robot); %s",
                robot_id,
                abs(offset),
                "ahead of" if offset > 0 else "behind",
                self._consequence(offset),
            )

    def _consequence(self, offset: float) -> str:
        if abs(offset) > self.config.max_offset_s:
            return (
                f"beyond {self.config.max_offset_s:g} s (clock.max_offset_s) rendezvous with it "
                "are refused"
            )
        return "its stamps are taken in the server's time meanwhile"

    def offset(self, robot_id: int) -> float | None:
        """Robot clock minus server clock [s] (low by the smallest transit time), or None."""
        with self._lock:
            window = np.asarray(self._samples.get(robot_id, ()), float)
        if len(window) < self.config.min_messages:
            return None
        return float(np.percentile(window, self.config.percentile))

    def offsets(self) -> dict[int, float]:
        with self._lock:
            robots = list(self._samples)
        return {r: o for r in robots if (o := self.offset(r)) is not None}

    def correction(self, robot_id: int) -> float:
        """What to subtract from the robot's stamps to have them in the server's time."""
        offset = self.offset(robot_id)
        if offset is None or abs(offset) <= self.config.correct_above_s:
            return 0.0
        return offset

    def to_server_time(self, item: Decoded, shift_s: float | None = None) -> Decoded:
        """A decoded keyframe message with its stamps in the server's time (``shift_s``: its
        robot's :meth:`correction`, when the caller has it already)."""
        shift = self.correction(item.robot_id) if shift_s is None else shift_s
        return _shifted(item, shift) if shift else item

    def said(self) -> dict[int, float]:
        """Robot id -> estimated offset [s] of every robot with one (for /server/stats)."""
        return {r: round(o, 4) for r, o in self.offsets().items()}

    def refusal(self, *robot_ids: int) -> str | None:
        """Why timing across these robots cannot be trusted (None: it can)."""
        for r in robot_ids:
            offset = self.offset(r)
            if offset is not None and abs(offset) > self.config.max_offset_s:
                return (
                    f"robot {r}'s clock is {abs(offset):.1f} s "
                    f"{'ahead of' if offset > 0 else 'behind'} the server's (more than "
                    f"clock.max_offset_s = {self.config.max_offset_s:g} s): a rendezvous needs "
                    "the robots' clocks synchronized (chrony or NTP against the master robot)"
                )
        return None


def _shifted(item: Decoded, shift_s: float) -> Decoded:
    if isinstance(item, PlaceSignature):
        return dataclasses.replace(item, record=_shifted(item.record, shift_s))
    if item.stamp_s <= 0:  # a removal carries no stamp
        return item
    if isinstance(item, Incomplete):  # completed when taken: its record shifted then
        complete = item.complete
        return dataclasses.replace(
            item,
            stamp_s=item.stamp_s - shift_s,
            complete=lambda stored: _shifted(complete(stored), shift_s),
        )
    return dataclasses.replace(item, stamp_s=item.stamp_s - shift_s)
