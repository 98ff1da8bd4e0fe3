"""Reliable keyframe delivery over lossy topics: nothing a client sends is lost while the server
is down, restarting, or behind a radio that drops messages.

Every keyframe message of a client carries its client *session* (chosen at start, increasing
across restarts) and a *sequence* number (1, 2, ... within the session). The server takes a
robot's messages in sequence order only (:class:`InOrder`): a duplicate is dropped, a message
after a gap is held until the gap is filled, and a newer session replaces an older one. After
it has committed a message to the map store it acknowledges the highest sequence stored. The
client keeps every message not yet acknowledged (:class:`Outbox`, bounded) and sends them again
when no acknowledgement came for a while. Session 0 means unsequenced (recorded bags, tests):
taken as it comes.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from .errors import CoopSlamError

UNSEQUENCED = 0


class DeliveryError(CoopSlamError):
    """Bad delivery settings."""


def new_session() -> int:
    """A client session id: wall-clock tenths of a second (uint32), so a restarted client's
    session is newer than the one before it."""
    return max(1, int(time.time() * 10) & 0xFFFFFFFF)


@dataclass
class Verdict:
    """What to do with an arriving message: ``take`` these (in order), or nothing."""

    take: list[Any] = field(default_factory=list)
    duplicate: bool = False
    held: bool = False
    stale: bool = False  # from a session older than the current one


class InOrder:
    """The server side: one robot's messages in sequence order, each taken exactly once."""

    def __init__(self, max_held: int = 1000, session: int = UNSEQUENCED, last: int = 0):
        if max_held < 1:
            raise DeliveryError(f"max_held must be >= 1, got {max_held}")
        self.max_held = max_held
        self.session, self.last = session, last  # highest sequence taken in ``session``
        self._held: dict[int, Any] = {}

    def arrive(self, session: int, sequence: int, item: Any) -> Verdict:
        if session == UNSEQUENCED:
            return Verdict(take=[item])
        if session < self.session:
            return Verdict(stale=True)
        if session > self.session:  # a restarted client: its first message is sequence 1
            self.session, self.last = session, 0
            self._held.clear()
        if sequence <= self.last or sequence in self._held:
            return Verdict(duplicate=True)
        if sequence > self.last + 1:
            # Full: keep the messages nearest the gap; the client sends the others again.
            if len(self._held) >= self.max_held:
                if sequence > max(self._held):
                    return Verdict()
                self._held.pop(max(self._held))
            self._held[sequence] = item
            return Verdict(held=True)
        take = [item]
        nxt = sequence + 1
        while nxt in self._held:
            take.append(self._held.pop(nxt))
            nxt += 1
        return Verdict(take=take)

    def taken(self, sequence: int) -> None:
        """The message with this sequence was committed (advance what is acknowledged)."""
        self.last = max(self.last, sequence)

    @property
    def held(self) -> int:
        return len(self._held)


class Outbox:
    """The client side: messages sent and not yet acknowledged, to send again.

    Without progress (no acknowledgement) for ``resend_after_s`` it sends the oldest
    ``resend_window`` unacknowledged messages again, then waits twice as long before the next
    resend, up to ``max_resend_after_s``; an acknowledgement resets the wait. A server that lags
    behind (its queue tens of seconds long with eight robots) acknowledges late, not never: sending
    everything again every two seconds made a resend storm that buried it further. The server takes
    a robot's messages in order, so the oldest missing ones are what it needs first."""

    def __init__(
        self,
        max_unacked: int = 1000,
        resend_after_s: float = 2.0,
        resend_window: int = 20,
        max_resend_after_s: float = 30.0,
    ):
        if max_unacked < 1:
            raise DeliveryError(f"max_unacked must be >= 1, got {max_unacked}")
        if resend_after_s <= 0:
            raise DeliveryError(f"resend_after_s must be > 0, got {resend_after_s}")
        if resend_window < 1:
            raise DeliveryError(f"resend_window must be >= 1, got {resend_window}")
        if max_resend_after_s < resend_after_s:
            raise DeliveryError(
                f"max_resend_after_s ({max_resend_after_s}) must be >= resend_after_s "
                f"({resend_after_s})"
            )
        self.max_unacked, self.resend_after_s = max_unacked, resend_after_s
        self.resend_window, self.max_resend_after_s = resend_window, max_resend_after_s
        self.session = new_session()
        self.sequence = 0  # of the last message
        self._unacked: OrderedDict[int, Any] = OrderedDict()
        self._last_progress = time.monotonic()  # last send or acknowledgement
        self._wait_s = resend_after_s  # before the next resend (doubles while no progress)
        self.dropped = 0  # unacknowledged messages given up because the bound was reached
        self.resent = 0

    def add(self, message: Any) -> tuple[int, int, bool]:
        """Number a new message: (session, sequence, whether an old message was given up)."""
        self.sequence += 1
        self._unacked[self.sequence] = message
        overflow = len(self._unacked) > self.max_unacked
        if overflow:
            self._unacked.popitem(last=False)
            self.dropped += 1
        if len(self._unacked) == 1:
            self._last_progress = time.monotonic()
            self._wait_s = self.resend_after_s
        return self.session, self.sequence, overflow

    def ack(self, session: int, sequence: int) -> int:
        """The server stored everything up to ``sequence``: forget those; returns how many."""
        if session != self.session:
            return 0
        done = [s for s in self._unacked if s <= sequence]
        for s in done:
            del self._unacked[s]
        if done:
            self._last_progress = time.monotonic()
            self._wait_s = self.resend_after_s
        return len(done)

    def due(self, now: float | None = None) -> list[Any]:
        """The messages to send again now (the oldest unacknowledged ones), or none."""
        now = time.monotonic() if now is None else now
        if not self._unacked or now - self._last_progress < self._wait_s:
            return []
        self._last_progress = now
        self._wait_s = min(2.0 * self._wait_s, self.max_resend_after_s)
        batch = list(self._unacked.values())[: self.resend_window]
        self.resent += len(batch)
        return batch

    @property
    def unacked(self) -> int:
        return len(self._unacked)
