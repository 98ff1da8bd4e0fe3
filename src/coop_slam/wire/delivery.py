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
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

from ..errors import CoopSlamError

RATE_WINDOW_S = 10.0  # the link's rate: what arrived over this long [s]
# A link slower than what a robot makes queues megabytes: a message behind them cannot arrive for
# minutes, and sending it again sooner only lengthens the queue. The bound only guards against a
# rate measured while the link was nearly idle [s].
MAX_CROSSING_S = 300.0

UNSEQUENCED = 0


class DeliveryError(CoopSlamError):
    """Bad delivery settings."""


class OutboxFull(DeliveryError):
    """The outbox holds ``max_unacked`` messages the server has not acknowledged."""


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


@dataclass
class DeliveryConfig:
    """How a client sends again what the server has not acknowledged (``client.launch``
    parameters of the same names)."""

    max_unacked: int = 1000  # messages kept for the server; beyond it new ones are refused
    resend_after_s: float = 2.0  # the first wait before a message goes again [s]
    resend_window: int = 100  # at most this many go again at once
    max_resend_after_s: float = 30.0  # the longest wait between sends of one message [s]


@dataclass
class _Pending:
    """A message the server has not acknowledged, as the outbox keeps it."""

    message: Any
    sent_s: float  # when it was last sent
    wait_s: float  # the wait before it goes again (backs off)
    received_s: float | None = None  # when the server said it received it
    nbytes: int = 0  # its size on the wire (0: not known)
    first_mark: int = 0  # the link's byte count after its first copy ...
    last_mark: int = 0  # ... and after its last one


class Outbox:
    """The client side: messages sent and not yet acknowledged, to send again.

    The server takes a robot's messages in order, so the oldest unacknowledged message is the one
    it needs to make progress (a radio lost it, or it never arrived): it goes again every
    ``resend_after_s``. Any other goes again ``resend_after_s`` after it was sent, then after
    twice as long, up to ``max_resend_after_s``; at most ``resend_window`` messages per call. A
    server that lags behind (its queue tens of seconds long with eight robots) thus gets each
    waiting message a few times, not every two seconds: sending everything again every two
    seconds made a resend storm that buried it further. Backing off the oldest message too
    stalled delivery after a server restart.

    The server also says which messages it has received (:meth:`received`) before it stores
    them: a server busy for seconds (a merge, a global BA) got every message that came meanwhile
    twice. (A wait that follows the acknowledgements' delay, as TCP's does, grew without bound
    behind a lossy radio: a lost message holds back the acknowledgement of all after it.)

    Full (``max_unacked``), it refuses new messages (:meth:`add` raises :class:`OutboxFull`;
    check :attr:`full` first) and keeps the oldest: the server takes a robot's messages in order,
    so giving up the oldest would leave a gap it waits at for good, and every later message would
    be held and dropped there.

    Behind a slow radio a message takes seconds to cross (a 30 kB keyframe at 64 kbit/s: 4 s),
    and one sent again while its first copy is still on its way only queues behind it: the link
    filled with copies and the newest keyframes never got through. So the outbox counts the
    bytes it hands the link (copies too) and, from the server's receipts and acknowledgements,
    how far the link has delivered them; a message goes again only once the bytes handed to the
    link up to its last copy could have crossed, at the rate the link has been delivering
    (without receipts or sizes, no extra wait). A message the link has gone past (a later one
    arrived) was lost: it goes again after ``resend_after_s``.

    A restarted client continues the session of the messages it kept on disk (:meth:`restore`)
    or numbers them anew in a session of its own (:meth:`renumber`), see
    :mod:`coop_slam.uplink.spool`."""

    def __init__(
        self,
        max_unacked: int = 1000,
        resend_after_s: float = 2.0,
        resend_window: int = 100,
        max_resend_after_s: float = 30.0,
    ):
        """See :class:`DeliveryConfig` (``Outbox(**vars(config))``)."""
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
        self._unacked: OrderedDict[int, _Pending] = OrderedDict()  # sequence -> its message
        self.resent = 0
        self._server_session = 0  # the server run acknowledging
        self.sent_bytes = 0  # handed to the link so far, copies included
        self.delivered_bytes = 0  # of those, known to have crossed (receipts, acknowledgements)
        self.link_Bps = 0.0  # the rate the link delivers (0: not known yet)
        self._delivered: deque = deque()  # (when, delivered_bytes), newest last

    @property
    def full(self) -> bool:
        """No room for another message until the server acknowledges."""
        return len(self._unacked) >= self.max_unacked

    def add(self, message: Any, now: float | None = None, nbytes: int = 0) -> tuple[int, int]:
        """Number a new message (sent now; ``nbytes`` its size on the wire, 0 = not known):
        (session, sequence). OutboxFull when :attr:`full`."""
        if self.full:
            raise OutboxFull(
                f"{len(self._unacked)} messages not acknowledged (max_unacked): the newest is "
                "refused"
            )
        now = time.monotonic() if now is None else now
        self.sequence += 1
        self.sent_bytes += nbytes
        mark = self.sent_bytes
        self._unacked[self.sequence] = _Pending(
            message, now, self.resend_after_s, None, nbytes, mark, mark
        )
        return self.session, self.sequence

    def restore(
        self, session: int, sequence: int, messages: list[tuple[int, Any]], now: float | None = None
    ) -> None:
        """Continue ``session`` after ``sequence`` with ``messages`` ((sequence, message), in
        order) not acknowledged yet, as if sent ``now`` (a restarted client's, from its disk)."""
        now = time.monotonic() if now is None else now
        self.session, self.sequence = session, sequence
        self._unacked = OrderedDict(
            (int(q), _Pending(m, now, self.resend_after_s)) for q, m in messages
        )

    def renumber(self, session: int) -> list[tuple[int, Any]]:
        """Number every message kept anew, 1, 2, ... in ``session`` (in their order); returns
        (new sequence, message)."""
        entries = list(self._unacked.values())
        self.session, self.sequence = session, len(entries)
        for entry in entries:
            entry.received_s = None
        self._unacked = OrderedDict((i + 1, e) for i, e in enumerate(entries))
        return [(q, e.message) for q, e in self._unacked.items()]

    def pending(self, now: float | None = None) -> list[Any]:
        """Every message kept, oldest first, as sent ``now``."""
        now = time.monotonic() if now is None else now
        for entry in self._unacked.values():
            entry.sent_s = now
            self._handed(entry)
        return [entry.message for entry in self._unacked.values()]

    def _handed(self, entry: _Pending) -> None:
        """A copy of ``entry`` went to the link."""
        self.sent_bytes += entry.nbytes
        entry.last_mark = self.sent_bytes

    def ack(self, session: int, sequence: int, now: float | None = None) -> int:
        """The server stored everything up to ``sequence``: forget those; returns how many."""
        if session != self.session:
            return 0
        now = time.monotonic() if now is None else now
        done = [s for s in self._unacked if s <= sequence]
        for s in done:
            self._arrived(self._unacked.pop(s), now)
        return len(done)

    def server_is(self, server_session: int) -> None:
        """Acknowledgements come from this server run. A new one (the server restarted) lost
        what it had received and not stored: those messages go again as any others."""
        if server_session != self._server_session:
            self._server_session = server_session
            for entry in self._unacked.values():
                entry.received_s = None

    def received(self, session: int, sequence: int, now: float | None = None) -> None:
        """The server has received this message and queued it to store: it does not go again
        while the server is busy storing what came before it, for up to ``max_resend_after_s``
        (then it goes again as any other: the server may have dropped it, e.g. beyond what it
        holds out of order) or until another server run acknowledges."""
        if session != self.session:
            return
        now = time.monotonic() if now is None else now
        entry = self._unacked.get(sequence)
        if entry is not None:
            entry.received_s = now
            self._arrived(entry, now)

    def _arrived(self, entry: _Pending, now: float) -> None:
        """A copy of ``entry`` crossed: the link delivered at least everything handed to it up to
        its first copy. The link's rate is how fast that count grew over the last
        ``RATE_WINDOW_S`` (under load what the link carries; idle, less: waits a little longer,
        which is safe). (Each message's own crossing time misled: a radio's token bucket lets a
        burst of small messages through at once.)"""
        if entry.first_mark <= self.delivered_bytes:
            return
        self.delivered_bytes = entry.first_mark
        self._delivered.append((now, self.delivered_bytes))
        while len(self._delivered) > 2 and self._delivered[1][0] < now - RATE_WINDOW_S:
            self._delivered.popleft()
        t0, b0 = self._delivered[0]
        if len(self._delivered) >= 2 and now > t0:
            self.link_Bps = (self.delivered_bytes - b0) / max(now - t0, 1.0)

    def due(self, now: float | None = None) -> list[Any]:
        """The messages to send again now (oldest first), or none."""
        now = time.monotonic() if now is None else now
        out = []
        for i, entry in enumerate(self._unacked.values()):
            if len(out) >= self.resend_window:
                break
            oldest = i == 0  # what the server waits for: never backed off
            if entry.received_s is not None and now - entry.received_s < self.max_resend_after_s:
                continue  # the server has it
            in_link = entry.last_mark - self.delivered_bytes  # handed over up to its last copy
            crossing_s = (
                min(in_link / self.link_Bps, MAX_CROSSING_S)
                if self.link_Bps > 0 and in_link > 0
                else 0.0
            )
            if now - entry.sent_s >= (self.resend_after_s if oldest else entry.wait_s) + crossing_s:
                if not oldest:
                    entry.wait_s = min(2.0 * entry.wait_s, self.max_resend_after_s)
                entry.sent_s = now
                self._handed(entry)
                out.append(entry.message)
        self.resent += len(out)
        return out

    @property
    def unacked(self) -> int:
        return len(self._unacked)
