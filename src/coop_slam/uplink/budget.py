"""A robot's radio budget: a token bucket over data time that the uplink's planner asks before a
keyframe message goes, so a robot sends at most ``uplink.budget_kBps`` whatever its camera makes,
spread evenly rather than in bursts a radio would queue."""

from __future__ import annotations

import dataclasses
from typing import Callable

from ..wire.record import ACTION_NEW, ACTION_UPDATE, KeyframeRecord

KINDS = ("whole", "delta", "signature")


class RadioBudget:
    """Tokens (bytes) accrue at ``kBps`` per second of data time up to ``burst_s`` seconds'
    worth. A message goes when the tokens cover what a message of its kind has cost lately
    (:meth:`take`; at most a full bucket: a whole RGB-D keyframe may be larger, and then leaves
    the bucket in debt), and is settled at what it really cost (:meth:`settle`; one that must go
    -- the server asked for it -- may leave the bucket in debt too, which later messages wait
    out). ``kBps`` 0: no budget."""

    def __init__(self, kBps: float = 0.0, burst_s: float = 0.5):
        self.rate_Bps = 1000.0 * float(kBps)
        self.capacity = self.rate_Bps * float(burst_s)
        self.tokens = self.capacity
        self._t: float | None = None
        # What a message of each kind cost lately [bytes]; until one went, a full bucket
        self._cost = {kind: self.capacity for kind in KINDS}
        self._seen: set[str] = set()

    @property
    def limited(self) -> bool:
        return self.rate_Bps > 0

    def _refill(self, now_s: float) -> None:
        if self._t is not None and now_s > self._t:
            self.tokens = min(self.capacity, self.tokens + (now_s - self._t) * self.rate_Bps)
        if self._t is None or now_s > self._t:
            self._t = now_s

    def take(self, kind: str, now_s: float) -> float | None:
        """When a message of ``kind`` fits the budget at data time ``now_s``: what it is charged
        (what one cost lately, taken now); else None."""
        if not self.limited:
            return 0.0
        self._refill(now_s)
        charge = min(self._cost[kind], self.capacity)
        if self.tokens < charge:
            return None
        self.tokens -= charge
        return charge

    def settle(self, kind: str, charged: float, nbytes: int) -> None:
        """A message of ``kind`` charged ``charged`` went with ``nbytes`` on the wire."""
        if not self.limited:
            return
        self.tokens += charged - nbytes
        if kind in self._seen:
            self._cost[kind] = 0.7 * self._cost[kind] + 0.3 * nbytes
        else:
            self._cost[kind] = float(nbytes)
            self._seen.add(kind)


class BudgetGate:
    """Which keyframe records the radio budget lets through, in order.

    A new keyframe (its signature in pull mode) waits in a queue until the budget affords it --
    a short peak of keyframes goes a little later -- and is held back for good once it has waited
    ``defer_s`` (newer keyframes see what it saw by then): the client keeps tracking on it; in
    full mode its place signature goes instead (:attr:`signed`: the server may ask for it whole,
    its updates do not go, its removal does), in pull mode the server never hears of it. An
    update of a keyframe the server holds goes when the budget affords it, else waits for the
    keyframe's next update (which then carries both). Waiting new keyframes go before updates.
    Records of one keyframe keep their order: a waiting keyframe's update replaces it (it goes
    as new, as it is then), its removal takes it out of the queue."""

    def __init__(self, budget: RadioBudget, new_kind: str, defer_s: float):
        self.budget, self.new_kind, self.defer_s = budget, new_kind, float(defer_s)
        self._waiting: dict[int, tuple[float, KeyframeRecord]] = {}  # oldest first
        self._given_up: set[int] = set()  # not sent at all
        # Sent as place signatures instead (full mode): the server may ask for them whole
        self.signed: set[int] = set()
        self.sign = new_kind == "whole"  # (the uplink says when it has no vocabulary for them)
        self._given_up_count = 0
        self._taken: dict[tuple[int, str], float] = {}  # what a message that goes was charged

    @property
    def held_back(self) -> int:
        """New keyframes the budget has kept from the server (waiting ones included)."""
        return self._given_up_count + len(self._waiting)

    def admit(
        self, records: list[KeyframeRecord], now_s: float, server_has: Callable[[int], bool]
    ) -> list[KeyframeRecord]:
        """Of ``records`` (and those waiting), what goes at data time ``now_s``."""
        if not self.budget.limited:
            return records
        updates = []
        for rec in records:
            k = rec.keyframe_id
            if rec.action == ACTION_NEW:
                self._waiting[k] = (now_s, rec)
            elif k in self._waiting:
                if rec.action == ACTION_UPDATE:  # still new to the server: as it is now
                    since = self._waiting[k][0]
                    self._waiting[k] = (since, dataclasses.replace(rec, action=ACTION_NEW))
                else:
                    del self._waiting[k]
            elif k in self._given_up:
                if rec.action != ACTION_UPDATE:
                    self._given_up.discard(k)
            elif k in self.signed:  # the server has its signature: a removal goes, updates not
                if rec.action != ACTION_UPDATE:
                    self.signed.discard(k)
                    updates.append(rec)
            elif rec.action != ACTION_UPDATE or not server_has(k):
                updates.append(rec)  # a removal, or an update the planner sends whole
            elif self._take(k, "delta", now_s):
                updates.append(rec)
        return self._release(now_s) + updates

    def _release(self, now_s: float) -> list[KeyframeRecord]:
        out = []
        for k in list(self._waiting):
            since, rec = self._waiting[k]
            if self._take(k, self.new_kind, now_s):
                out.append(self._waiting.pop(k)[1])
            elif now_s - since >= self.defer_s:
                del self._waiting[k]
                self._given_up_count += 1
                if self.sign and self.new_kind == "whole":  # its signature goes (a few kB)
                    self.signed.add(k)
                    out.append(rec)
                else:
                    self._given_up.add(k)
        return out

    def answered(self, keyframe_id: int) -> None:
        """The server asked for this keyframe and it went whole: its updates go from now on."""
        self.signed.discard(keyframe_id)
        self._given_up.discard(keyframe_id)

    def _take(self, keyframe_id: int, kind: str, now_s: float) -> bool:
        charge = self.budget.take(kind, now_s)
        if charge is None:
            return False
        self._taken[(keyframe_id, kind)] = charge
        return True

    def sent(self, keyframe_id: int, kind: str, nbytes: int) -> None:
        """A message went: what it cost (a message the budget did not let through -- one the
        server asked for -- is charged now)."""
        self.budget.settle(kind, self._taken.pop((keyframe_id, kind), 0.0), nbytes)
