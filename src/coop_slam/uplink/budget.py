"""A robot's radio budget: a token bucket over data time that the uplink's planner asks before a
keyframe message goes, so a robot sends at most ``uplink.budget_kBps`` whatever its camera makes,
spread evenly rather than in bursts a radio would queue."""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ..wire.record import ACTION_NEW, ACTION_UPDATE, KeyframeRecord

KINDS = ("whole", "delta", "signature")


class RadioBudget:
    """Tokens (bytes) accrue at ``kBps`` per second of data time, from none, up to ``burst_s``
    seconds' worth or the cost of the largest kind of message, whichever is more (a whole RGB-D
    keyframe is more than half a second of a small budget). A message goes when the tokens cover
    what a message of its kind has cost lately (:meth:`take`), and is settled at what it really
    cost (:meth:`settle`); one that must go -- the server asked for it, a place signature -- may
    leave the bucket in debt, which later messages wait out. So what a robot sends up to data
    time t is at most ``kBps`` x t and what must go. ``reserve``: a kind of message the bucket
    keeps one of in hand for what must go (full mode: a whole keyframe the server asks for), so
    that even that stays within ``kBps`` x t unless the server asks for more at once. ``kBps``
    0: no budget."""

    def __init__(self, kBps: float = 0.0, burst_s: float = 0.5, reserve: str | None = None):
        self.rate_Bps = 1000.0 * float(kBps)
        self.burst = self.rate_Bps * float(burst_s)
        self.reserve = reserve
        self.tokens = 0.0
        self._t: float | None = None
        # What a message of each kind cost lately [bytes]; until one went, half a second's worth
        self._cost = {kind: self.burst for kind in KINDS}
        self._seen: set[str] = set()

    @property
    def limited(self) -> bool:
        return self.rate_Bps > 0

    @property
    def held_in_hand(self) -> float:
        """Tokens kept for what must go [bytes]."""
        return self._cost[self.reserve] if self.reserve else 0.0

    @property
    def capacity(self) -> float:
        return max(self.burst, max(self._cost.values())) + self.held_in_hand

    def _refill(self, now_s: float) -> None:
        if self._t is not None and now_s > self._t:
            self.tokens = min(self.capacity, self.tokens + (now_s - self._t) * self.rate_Bps)
        if self._t is None or now_s > self._t:
            self._t = now_s

    def affords(self, kind: str, now_s: float) -> bool:
        """Whether a message of ``kind`` fits the budget at data time ``now_s`` (nothing taken)."""
        if not self.limited:
            return True
        self._refill(now_s)
        return self.tokens >= self._cost[kind] + self.held_in_hand

    def take(self, kind: str, now_s: float) -> float | None:
        """When a message of ``kind`` fits the budget at data time ``now_s``: what it is charged
        (what one cost lately, taken now); else None."""
        if not self.limited:
            return 0.0
        if not self.affords(kind, now_s):
            return None
        charge = self._cost[kind]
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

    New keyframes are candidates for ``defer_s`` of data time; whenever the budget affords one,
    the candidate that adds most to what the server has goes (:meth:`novelty`: the share of its
    map points no keyframe the server has a view of observes -- a new view of the scene first,
    one much like what went already last). In full mode every candidate's place signature goes at
    once (a few kB: the server can recognise the place and ask for the keyframe whole), and a
    candidate the budget then affords goes whole after it (:attr:`signed` holds those the server
    has only as signatures: their updates do not go, their removal does); in pull mode a
    candidate is its signature, and one the budget never affords stays on the robot (the server
    never hears of it). An update of a keyframe the server holds goes when the budget affords it,
    else waits, the oldest first, until it does (a newer update of the keyframe replaces it and
    carries both; when the camera stops, it goes). Candidates go before updates. Records of one
    keyframe keep their order: a candidate's update replaces it (it goes as new, as it is then),
    its removal takes it out of the candidates."""

    def __init__(self, budget: RadioBudget, new_kind: str, defer_s: float):
        self.budget, self.new_kind, self.defer_s = budget, new_kind, float(defer_s)
        self._candidates: dict[int, tuple[float, KeyframeRecord]] = {}  # id -> (since, latest)
        self._given_up: set[int] = set()  # not sent at all
        # The latest update of a keyframe the server holds that the budget could not afford yet
        # (a keyframe's last local-BA refinement must reach the server), oldest first
        self._unsent: dict[int, KeyframeRecord] = {}
        # Sent as place signatures only (full mode): the server may ask for them whole
        self.signed: set[int] = set()
        # Full mode: what the budget holds back goes as its signature (the uplink says when it
        # has no vocabulary to make them)
        self.sign = new_kind == "whole"
        self._given_up_count = 0
        # What the message of a keyframe that goes was charged (the planner may send an update
        # it was charged for as a delta whole: it is settled at what it cost all the same)
        self._taken: dict[int, float] = {}
        # Map point ids of each keyframe the server has a view of (whole in full mode, its
        # signature in pull mode), as it went: what a candidate's novelty is measured against.
        self._views: dict[int, np.ndarray] = {}
        self._seen: np.ndarray | None = None  # the map point ids of all views, sorted (None: stale)

    @property
    def waiting(self) -> int:
        """Candidates the server has not heard of yet (read by other threads: no iteration)."""
        return len(self._candidates.keys() - self.signed)

    @property
    def held_back(self) -> int:
        """New keyframes the budget has kept from the server altogether (candidates that have
        not gone in any form included)."""
        return self._given_up_count + self.waiting

    def novelty(self, rec: KeyframeRecord) -> float:
        """The share of ``rec``'s map points that no keyframe the server has a view of observes
        (1: a new view of the scene; 0: nothing the server has not seen)."""
        ids = np.asarray(rec.map_point_ids)
        ids = ids[ids != 0]
        if self._seen is None:  # (rebuilt after a view went; kept sorted for the lookups)
            views = list(self._views.values())
            self._seen = np.unique(np.concatenate(views)) if views else np.zeros(0, np.uint32)
        if len(ids) == 0 or len(self._seen) == 0:
            return 1.0
        at = np.minimum(np.searchsorted(self._seen, ids), len(self._seen) - 1)
        return 1.0 - float(np.mean(self._seen[at] == ids))

    def admit(
        self,
        records: list[KeyframeRecord],
        now_s: float,
        server_has: Callable[[int], bool],
        flush: bool = False,
    ) -> list[KeyframeRecord]:
        """Of ``records`` (and the candidates), what goes at data time ``now_s``. ``flush``: the
        candidates' time is up (the camera stopped, the map ends): in pull mode their
        signatures go, whatever the budget."""
        if not self.budget.limited or (self.new_kind == "whole" and not self.sign):
            # (full mode without the server's vocabulary -- a client started before the server:
            # without signatures the server could not ask for what the budget held back, so
            # everything goes whole, charged to the budget, rather than be lost)
            return records
        updates = []
        for rec in records:
            k = rec.keyframe_id
            if rec.action == ACTION_NEW:
                self._candidates[k] = (now_s, rec)
            elif k in self._candidates:
                if rec.action == ACTION_UPDATE:  # still new to the server: as it is now
                    since = self._candidates[k][0]
                    self._candidates[k] = (since, dataclasses.replace(rec, action=ACTION_NEW))
                else:
                    del self._candidates[k]
                    if k in self.signed:
                        self._forget(k)
                        updates.append(rec)
            elif k in self._given_up:
                if rec.action != ACTION_UPDATE:
                    self._given_up.discard(k)
            elif k in self.signed:  # the server has its signature: a removal goes, updates not
                if rec.action != ACTION_UPDATE:
                    self._forget(k)
                    updates.append(rec)
            elif rec.action != ACTION_UPDATE or not server_has(k):
                self._unsent.pop(k, None)
                if rec.action != ACTION_UPDATE:
                    self._forget(k)
                updates.append(rec)  # a removal, or an update the planner sends whole
            elif self._take(k, "delta", now_s):
                self._unsent.pop(k, None)
                updates.append(rec)
            else:  # it goes when the budget affords it (or with the keyframe's next update)
                self._unsent[k] = rec
        new = self._release(now_s, flush)
        for k in list(self._unsent):  # the oldest first
            if not (flush or self._take(k, "delta", now_s)):
                break
            updates.append(self._unsent.pop(k))
        return new + updates

    def _release(self, now_s: float, flush: bool) -> list[KeyframeRecord]:
        out = []
        # Ranked by novelty (once per call, against the views as they are before any goes): all
        # candidates when one can go whole, else those whose signature goes now (a candidate's
        # novelty costs a lookup of its map points: every candidate on every frame was most of a
        # hand-held camera's frame time)
        if self.budget.affords(self.new_kind, now_s):
            rank = list(self._candidates)
        else:
            rank = [k for k in self._candidates if self.sign and k not in self.signed]
        novelty = {k: self.novelty(self._candidates[k][1]) for k in rank}
        ranked = sorted(novelty, key=lambda k: -novelty[k])
        ranked += [k for k in self._candidates if k not in novelty]
        affords = True
        for k in ranked:
            since, rec = self._candidates[k]
            if affords and self._take(k, self.new_kind, now_s):
                del self._candidates[k]
                self.signed.discard(k)  # (its signature may have gone: now it goes whole)
                self._add_view(rec)
                out.append(rec)
                continue
            affords = False  # (every candidate costs the same)
            if self.sign and k not in self.signed:  # its place signature goes now
                self.signed.add(k)
                out.append(rec)
            if flush or now_s - since >= self.defer_s or now_s < since:
                del self._candidates[k]
                if self.sign:
                    continue
                if flush and self.new_kind == "signature":  # (a few kB each)
                    self._add_view(rec)
                    out.append(rec)
                else:
                    self._given_up.add(k)
                    self._given_up_count += 1
        return out

    def _add_view(self, rec: KeyframeRecord) -> None:
        ids = np.asarray(rec.map_point_ids)
        self._views[rec.keyframe_id] = ids[ids != 0]
        self._seen = None

    def _forget(self, keyframe_id: int) -> None:
        """A keyframe removed: the server no longer has it."""
        self.signed.discard(keyframe_id)
        if self._views.pop(keyframe_id, None) is not None:
            self._seen = None

    def answered(self, rec: KeyframeRecord) -> None:
        """The server asked for this keyframe and it went whole: its updates go from now on."""
        k = rec.keyframe_id
        self.signed.discard(k)
        self._given_up.discard(k)
        self._candidates.pop(k, None)
        if self.budget.limited:
            self._add_view(rec)

    def _take(self, keyframe_id: int, kind: str, now_s: float) -> bool:
        charge = self.budget.take(kind, now_s)
        if charge is None:
            return False
        self._taken[keyframe_id] = charge
        return True

    def sent(self, keyframe_id: int, kind: str, nbytes: int) -> None:
        """A message went: what it cost (a message the budget did not let through -- one the
        server asked for, a signature -- is charged now). Not in full mode before the server's
        vocabulary came: nothing was budgeted then, and a debt run up while a client waits for
        its server (unbounded: every keyframe goes whole) would silence it for as long once the
        budget applies."""
        if self.new_kind == "whole" and not self.sign:
            return
        self.budget.settle(kind, self._taken.pop(keyframe_id, 0.0), nbytes)
