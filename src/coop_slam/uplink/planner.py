"""How each keyframe record goes to the server: whole, as a delta update with only what changed,
as a place signature, or not at all; and which descriptors the server can take from keyframes it
holds. The planner keeps what the server holds of each keyframe to decide it."""

from __future__ import annotations

import heapq
import threading
from typing import NamedTuple

import numpy as np

from ..descriptors import hamming_rows
from ..wire.codec import Outgoing
from ..wire.observations import (
    apply_moves,
    apply_observation_patch,
    observation_index,
    observation_patch,
    split_moves,
)
from ..wire.record import ACTION_NEW, ACTION_UPDATE, KeyframeRecord
from .budget import BudgetGate, RadioBudget
from .config import UplinkConfig
from .holdback import Holdback


class _Held(NamedTuple):
    """What the server holds of a keyframe: the digest of what it saw (as sent), its
    observations (map point ids, per-keypoint points, NaN where none), its map segment and its
    descriptors."""

    digest: bytes
    ids: np.ndarray
    points: np.ndarray
    segment: int
    descriptors: np.ndarray  # (N, 32) as the server holds them


class Planner:
    """What each keyframe message carries. An update goes as a delta (without what the keyframe
    saw) when its keypoints, octaves, descriptors and depths are the ones sent with
    the keyframe as new (the server has them), and then with only the observations that changed
    since they last went:
    keypoints that observe another map point (or none), or whose map point moved more than
    ``point_move_m`` (local BA moves most points of a keyframe a little, and an update that
    sent them all was most of a client's traffic); a point that only moved goes as its move in
    int16 steps of ``MOVE_STEP_M`` (when ``point_move_m`` is at least a step). ``delta_updates``
    False: every update goes in full.

    In pull mode a new keyframe goes as its place signature, and whole only when the server asks
    (:meth:`answer`); updates of keyframes the server holds move their pose only (no points),
    those of the others are not sent; removals are.

    A whole keyframe leaves out the descriptors of keypoints observing a map point that a
    keyframe the server holds observes too (``share_descriptors``): the server takes them there.

    It keeps, per keyframe, the observations as the server holds them (the messages reach the
    server in order, and every one does: :class:`coop_slam.wire.delivery.Outbox`); a keyframe the
    server refused (:meth:`forget`, from its acknowledgement) is no longer counted on.

    When records go is :class:`Holdback`'s (full mode; in pull mode each goes as it comes):
    :meth:`offer` a record as the odometry makes it, send what it and :meth:`due` return.

    Whether they go at all is the radio budget's (``budget_kBps``,
    :class:`~coop_slam.uplink.budget.BudgetGate`). Keyframes the server asks for always go."""

    def __init__(self, config: UplinkConfig | None = None):
        config = config or UplinkConfig()
        config.validate()
        self.enabled, self.min_point_move_m = config.delta_updates, config.point_move_m
        self.pull = config.mode == "pull"
        self.idle_flush_s = config.idle_flush_s
        self.share = config.share_descriptors and not self.pull
        self.max_refs, self.max_bits = config.ref_keyframes, config.share_max_bits
        self.holdback = (
            Holdback() if self.pull else Holdback(config.hold_new_s, config.coalesce_updates_s)
        )
        self._held: dict[int, _Held] = {}  # keyframe id -> what the server holds of it
        self.gate = BudgetGate(
            # (in full mode a whole keyframe in hand for the server's requests)
            RadioBudget(
                config.pull_budget_kBps if self.pull else config.budget_kBps,
                reserve=None if self.pull else "whole",
            ),
            "signature" if self.pull else "whole",
            config.budget_defer_s,
        )
        self._now_s = 0.0  # the latest data time seen
        # Keyframes the server refused, to forget before the next message is prepared (said by
        # the acknowledgement's thread)
        self._refused: set[int] = set()
        self._refused_lock = threading.Lock()

    def offer(self, rec: KeyframeRecord, now_s: float) -> list[tuple[KeyframeRecord, Outgoing]]:
        """A record the odometry made at data time ``now_s``: what goes now, and how."""
        self._now_s = max(self._now_s, now_s)
        return self._planned(self.holdback.offer(rec, now_s))

    def due(self, now_s: float) -> list[tuple[KeyframeRecord, Outgoing]]:
        """The held records that go at data time ``now_s``, and how."""
        self._now_s = max(self._now_s, now_s)
        return self._planned(self.holdback.due(now_s))

    def flush(self) -> list[tuple[KeyframeRecord, Outgoing]]:
        """Every held record, and how it goes (the radio budget's candidates too)."""
        return self._planned(self.holdback.flush(), flush=True)

    def _planned(
        self, records: list[KeyframeRecord], flush: bool = False
    ) -> list[tuple[KeyframeRecord, Outgoing]]:
        admitted = self.gate.admit(records, self._now_s, self._held.__contains__, flush)
        return [(r, self.prepare(r)) for r in admitted]

    def holds(self, keyframe_id: int) -> bool:
        """Whether the server holds this keyframe whole (as far as this uplink knows)."""
        with self._refused_lock:
            if int(keyframe_id) in self._refused:
                return False
        return int(keyframe_id) in self._held

    @staticmethod
    def kind_of(how: Outgoing) -> str:
        """The budget's kind of a message that goes ``how``."""
        return "signature" if how.signature else "delta" if how.delta else "whole"

    def forget(self, keyframe_ids) -> None:
        """The server refused these keyframes' last messages: it does not hold them as this
        uplink thinks, so no message refers to them and their next update goes whole (any
        thread)."""
        with self._refused_lock:
            self._refused.update(int(k) for k in keyframe_ids)

    def prepare(self, rec: KeyframeRecord) -> Outgoing:
        """How ``rec`` (about to be sent) goes; remembers what the server will hold after it."""
        with self._refused_lock:
            refused, self._refused = self._refused, set()
        for k in refused:
            self._held.pop(k, None)
        if rec.action == ACTION_NEW:
            if self.pull or rec.keyframe_id in self.gate.signed:
                return Outgoing(False, signature=True)
            refs, descriptors = self._refs(rec)
            self._hold(rec.keyframe_id, rec.static_digest(), rec, descriptors)
            return Outgoing(False, refs=refs)
        held = self._held.get(rec.keyframe_id)
        if self.pull and rec.action == ACTION_UPDATE and held is None:
            return Outgoing(False, skip=True)
        if rec.action != ACTION_UPDATE or held is None:  # a removal, or it goes whole
            self._held.pop(rec.keyframe_id, None)
            return Outgoing(False)
        if not self.enabled:  # every update whole: the server holds it as it goes
            self._hold(rec.keyframe_id, rec.static_digest(), rec)
            return Outgoing(False)
        digest = rec.static_digest()
        if held.digest != digest:  # what the keyframe saw changed: it goes in full
            refs, descriptors = self._refs(rec)
            self._hold(rec.keyframe_id, digest, rec, descriptors)
            return Outgoing(False, refs=refs)
        if self.pull:  # the radio's budget goes to whole keyframes: updates move the pose
            return Outgoing(True, np.zeros(0, np.uint32))
        per_keypoint = rec.map_points_per_keypoint()
        patched = observation_patch(
            held.ids, held.points, rec.map_point_ids, per_keypoint, self.min_point_move_m
        )
        patched, moved, moves = split_moves(
            held.ids, held.points, patched, rec.map_point_ids, per_keypoint, self.min_point_move_m
        )
        ids = rec.map_point_ids[patched]
        held_ids, held_points = apply_observation_patch(
            held.ids, held.points, patched, ids, per_keypoint[patched][ids != 0]
        )
        held_points = apply_moves(held_ids, held_points, moved, moves)
        self._held[rec.keyframe_id] = held._replace(ids=held_ids, points=held_points)
        return Outgoing(True, patched, moves=(moved, moves) if len(moved) else None)

    def answer(self, rec: KeyframeRecord) -> Outgoing:
        """A keyframe the server asked for (pull mode, or one the budget sent as a signature):
        it goes whole, as new, and its updates from now on."""
        self.gate.answered(rec)
        self._hold(rec.keyframe_id, rec.static_digest(), rec)
        return Outgoing(False)

    def _hold(
        self,
        keyframe_id: int,
        digest: bytes,
        rec: KeyframeRecord,
        descriptors: np.ndarray | None = None,
    ) -> None:
        """Remember what the server holds of ``rec`` once it got it: its descriptors are
        ``descriptors`` (those it took from other keyframes) or the record's."""
        self._held[keyframe_id] = _Held(
            digest,
            np.array(rec.map_point_ids, np.uint32),
            rec.map_points_per_keypoint(),
            int(rec.map_segment),
            np.array(rec.descriptors if descriptors is None else descriptors, np.uint8),
        )

    def _refs(self, rec: KeyframeRecord) -> tuple[tuple[np.ndarray, np.ndarray] | None, np.ndarray]:
        """Which of ``rec``'s descriptors the server can take from keyframes it holds: a
        keypoint's map point's descriptor there within ``share_max_bits`` of its own. Returns
        the keyframes (``rec``'s covisible ones first, then the newest, at most
        ``ref_keyframes``, of its map segment) and per keypoint the one to take it from (0: it
        travels) -- None when every descriptor travels -- and the descriptors the server then
        holds."""
        own = np.asarray(rec.descriptors, np.uint8)
        if not self.share:
            return None, own
        server = own.copy()
        ids = np.asarray(rec.map_point_ids, np.uint32)
        same = {k for k, h in self._held.items() if h.segment == rec.map_segment}
        same.discard(rec.keyframe_id)
        by_weight = np.argsort(-np.asarray(rec.covisible_weights, np.int64), kind="stable")
        covisible = [k for k in (int(rec.covisible_ids[i]) for i in by_weight) if k in same]
        newest = heapq.nlargest(self.max_refs, same)
        order = list(dict.fromkeys(covisible + newest))[: self.max_refs]
        refs = np.zeros(len(ids), np.uint8)
        used: list[int] = []
        for kf_id in order:
            open_ = np.flatnonzero((refs == 0) & (ids != 0))
            if not len(open_):
                break
            held = self._held[kf_id]
            at = observation_index(held.ids, ids[open_])
            open_, at = open_[at >= 0], at[at >= 0]
            close = hamming_rows(own[open_], held.descriptors[at]) <= self.max_bits
            if np.any(close):
                used.append(kf_id)
                refs[open_[close]] = len(used)
                server[open_[close]] = held.descriptors[at[close]]
        if not used:
            return None, own
        return (np.asarray(used, np.uint32), refs), server
