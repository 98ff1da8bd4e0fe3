"""The server core made durable: every input it takes is committed to the map store (one
transaction: the logged input, the derived tables, the acknowledgement) before it is
acknowledged, each robot's keyframe messages are taken in order exactly once (see
:mod:`coop_slam.wire.delivery`), and a server started on an existing map file rebuilds the team
state from it and carries on (``resume``), or starts from a saved map of an earlier session
(``load``).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time
import uuid
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import CoopSlamError
from ..wire.codec import Incomplete
from ..wire.delivery import UNSEQUENCED, InOrder
from ..wire.record import ACTION_NEW, ACTION_REMOVE, KeyframeRecord, PlaceSignature
from .config import ServerConfig
from .global_ba import GlobalBaError
from .map_store import (
    KIND_GLOBAL_BA,
    KIND_RENDEZVOUS,
    KIND_SIGHTING,
    MapStore,
    MapStoreError,
    RebuildReport,
    collision_free_ids,
    rebuild,
)
from .pull import PullPlanner
from .results import MergeResult

log = logging.getLogger(__name__)


def _has_inputs(path: str) -> bool:
    """A map file with something in it (a file created and left empty counts as new)."""
    if not os.path.exists(path) or not os.path.getsize(path):
        return False
    store = MapStore(path)
    try:
        return store.count_inputs() > 0
    finally:
        store.close()


REFUSED_KEPT = 64  # refused keyframes acknowledged per robot (the newest)


@dataclass
class Taken:
    """What became of one arriving keyframe message."""

    merges: list[MergeResult]
    taken: int = 0  # messages taken now (held ones included)
    duplicate: bool = False
    held: bool = False
    stale: bool = False
    rejected: list[str] | None = None  # reasons of messages the core refused


class DurableServer:
    """A :class:`TeamServer` whose accepted input is in a :class:`MapStore` first."""

    def __init__(
        self,
        config: ServerConfig,
        make_server: Callable[[ServerConfig], object],
        store_path: str | None,
        resume: bool = False,
        load_path: str | None = None,
        vocabulary_sha256: str = "",
        progress: Callable[[int, int], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        defer_global_ba: bool = False,
    ):
        self.rebuilt: RebuildReport | None = None
        self.loaded: RebuildReport | None = None
        robots = list(config.robots)
        source_resume = None
        existing = bool(store_path) and _has_inputs(store_path)
        if existing and resume:
            source_resume = MapStore(store_path)
            robots = sorted(set(robots) | set(source_resume.robots))
        elif existing:
            raise MapStoreError(
                f"map file {store_path} exists: resume from it (resume:=true), or give another "
                "file (map:=...)"
            )
        source_load, remap = None, {}
        if load_path:
            if not os.path.isfile(load_path):
                raise MapStoreError(f"map to load not found: {load_path}")
            if source_resume is not None:
                raise MapStoreError(
                    "resume and load_map together: a resumed map already holds what was loaded"
                )
            source_load = MapStore(load_path)
            remap = collision_free_ids(source_load.robots, robots)
            robots = sorted(set(robots) | {remap.get(r, r) for r in source_load.robots})
        config.robots = robots
        self.pull: PullPlanner | None = None
        self.clock = clock
        min_consecutive = config.place_recognition.min_consecutive
        if config.pull.enabled:
            # Low-bandwidth mode: place recognition's consistency check runs on the signatures
            # (every keyframe), so the server verifies a pulled pair at once.
            config.place_recognition.min_consecutive = 1
        self.server = make_server(config)
        # Before a rebuild: a deferred global BA is in the file as a call of its own.
        self.server.defer_global_ba = defer_global_ba
        self._pull_settings = (config.pull, config.place_recognition.database, min_consecutive)
        if config.pull.enabled:
            self.pull = self._new_pull_planner()
        self.order = {r: InOrder() for r in robots}
        # robot -> keyframe ids whose last message the core refused, newest last (acknowledged
        # with them: the client must not count on the server holding them)
        self._refused: dict[int, deque[int]] = {r: deque(maxlen=REFUSED_KEPT) for r in robots}
        if source_resume is not None:
            self.store = source_resume
            self.store.set_robots(robots)
            self.rebuilt = rebuild(self.store, self.server, progress=progress)
            for r, (session, seq) in self.store.acks().items():
                if r in self.order:
                    self.order[r].session, self.order[r].last = session, seq
        elif store_path:
            self.store = MapStore(store_path, robots, vocabulary_sha256)
            self.store.set_robots(robots)  # a file created before and left empty
        else:
            self.store = None
        if source_load is not None:
            if remap:
                log.warning(
                    "loaded map: robot ids %s are running now; the loaded robots are %s here",
                    sorted(remap),
                    ", ".join(f"{a} -> {b}" for a, b in sorted(remap.items())),
                )
            self.loaded = rebuild(source_load, self.server, self.store, remap, progress)
            source_load.close()
        # The team map's id: a client's spool made for another is not sent into it.
        self.map_id = self.store.map_id if self.store is not None else uuid.uuid4().hex
        # robot -> (keyframe ids taken, highest map segment): what a restarted client continues
        # above, kept here rather than asked of the file for every message.
        self._logged: dict[int, tuple[set[int], int]] = {}
        # robot -> ids of keyframes heard of only as place signatures (not in the map file)
        self._signatures_only: dict[int, set[int]] = {}
        if self.store is not None:
            self._logged = self.store.logged_keyframes()
        else:  # a map loaded without a file of its own: the keyframes the server holds
            for mid, kf in self.server.store.keys():
                self._note_taken(
                    self.server.robot_of(mid), kf, self.server.segments.segment_of(mid)
                )
        if self.pull is not None:  # signatures are not stored: only what the server holds
            for mid, kf in self.server.store.keys():
                self.pull.hold(self.server.robot_of(mid), kf)

    @property
    def low_bandwidth(self) -> bool:
        """The server is in low-bandwidth mode (``pull.enabled``), not only taking the
        signatures some robot's radio budget sends."""
        return self._pull_settings[0].enabled

    def _new_pull_planner(self) -> PullPlanner:
        server = self.server

        def same_group(a: int, b: int) -> bool:
            return server.groups.same_group(server.current_map(a), server.current_map(b))

        config, database, min_consecutive = self._pull_settings
        if not config.enabled:  # signatures of what a robot's radio budget holds back
            config = dataclasses.replace(
                config,
                min_score_ratio=config.budget_min_score_ratio,
                keyframes_per_min=config.budget_keyframes_per_min,
            )
        return PullPlanner(config, database, min_consecutive, same_group)

    def _pull_for_signatures(self) -> PullPlanner:
        """The pull planner, made when the first place signature comes to a server not in
        low-bandwidth mode (a robot's radio budget sends signatures of the keyframes it holds
        back): it holds what the server holds, and asks for whole keyframes as in low-bandwidth
        mode."""
        if self.pull is None:
            self.pull = self._new_pull_planner()
            for rec in self.server.store.records():
                self._view_of_whole(rec)
        return self.pull

    def _view_of_whole(self, rec) -> None:
        """A whole keyframe the server holds, to the pull planner of a server not in low-bandwidth
        mode (see :meth:`_pull_for_signatures`): held, and a view signatures can match."""
        self.pull.hold(rec.robot_id, rec.keyframe_id)
        bow, _ = self.server.vocabulary.transform(rec.descriptors)
        self.pull.add_view(rec.robot_id, rec.keyframe_id, bow, rec.covisible_ids, self.clock())

    @property
    def robots(self) -> list[int]:
        return sorted(self.server.known_robots)

    def acknowledged(self, robot_id: int) -> tuple[int, int]:
        """(session, highest sequence stored) of a robot's client."""
        o = self.order[robot_id]
        return o.session, o.last

    def refused(self, robot_id: int) -> list[int]:
        """The keyframes of a robot whose last message the server refused (the newest
        ``REFUSED_KEPT``)."""
        return list(self._refused.get(robot_id, ()))

    def last_ids(self) -> dict[int, tuple[int, int]]:
        """robot -> (highest keyframe id, highest map segment) taken: a restarted client goes
        on above them."""
        return {r: (max(ids), seg) for r, (ids, seg) in self._logged.items() if ids}

    def keyframes_stored(self) -> dict[int, int]:
        """robot -> keyframes taken whole (culled ones included; not those heard of only as
        place signatures, which the map file does not keep)."""
        return {
            r: len(ids - self._signatures_only.get(r, set()))
            for r, (ids, _) in self._logged.items()
        }

    def _note_taken(
        self, robot_id: int, keyframe_id: int, segment: int, signature: bool = False
    ) -> None:
        ids, top = self._logged.get(robot_id, (set(), 0))
        only = self._signatures_only.setdefault(robot_id, set())
        if not signature:
            only.discard(keyframe_id)
        elif keyframe_id not in ids:  # (a keyframe taken whole before stays whole)
            only.add(keyframe_id)
        ids.add(keyframe_id)
        self._logged[robot_id] = (ids, max(top, segment))

    # --- inputs ---------------------------------------------------------------------------------
    def add_keyframe(
        self,
        rec: KeyframeRecord | Incomplete | PlaceSignature,
        session: int = UNSEQUENCED,
        sequence: int = 0,
    ) -> Taken:
        order = self.order.get(rec.robot_id)
        if order is None:
            if isinstance(rec, (KeyframeRecord, PlaceSignature)):
                rec.validate(self.server.known_robots)  # names the robots the server knows
            raise MapStoreError(
                f"robot {rec.robot_id} is unknown to the server (known: {self.robots})"
            )
        v = order.arrive(session, sequence, (rec, sequence))
        out = Taken([], duplicate=v.duplicate, held=v.held, stale=v.stale)
        for item, seq in v.take:
            refused, keyframe_id = self._refused[item.robot_id], int(item.keyframe_id)
            if keyframe_id in refused:
                refused.remove(keyframe_id)
            try:
                out.merges += self._take(item, seq)
            except CoopSlamError as exc:
                out.rejected = (out.rejected or []) + [str(exc)]
                if keyframe_id:
                    refused.append(keyframe_id)
            out.taken += 1
        return out

    def _take(self, rec: KeyframeRecord | Incomplete | PlaceSignature, sequence: int):
        """Apply one input and commit it (with the acknowledgement) in one transaction. A message
        the core refuses is not logged, but acknowledged (sending it again changes nothing).
        In low-bandwidth mode, signatures (and removals of keyframes the server never held) go to
        the pull planner only: they are not stored."""
        order, store, robot_id = self.order[rec.robot_id], self.store, rec.robot_id
        if store is not None:
            store.begin()
        logged = False
        try:
            if isinstance(rec, Incomplete):  # completed from the keyframes as stored now
                rec = rec.complete(
                    functools.partial(self.server.stored_record, rec.robot_id, rec.map_segment)
                )
            pull = self.pull
            if isinstance(rec, PlaceSignature):
                pull = self._pull_for_signatures()
                pull.add(rec.validate(self.server.known_robots), self.clock())
                self._note_taken(
                    rec.robot_id, rec.keyframe_id, rec.record.map_segment, signature=True
                )
                return []
            if pull is not None and rec.action == ACTION_REMOVE:
                held = pull.holds(rec.robot_id, rec.keyframe_id)
                pull.remove(rec.robot_id, rec.keyframe_id)
                if not held:
                    return []
            pulled = (
                pull is not None
                and not self.low_bandwidth  # (there the server checks no consistency)
                and (rec.robot_id, rec.keyframe_id) in pull.pending
            )
            merges = self.server.add_keyframe(rec, pulled=pulled)
            if pull is not None and rec.action == ACTION_NEW:
                if self.low_bandwidth:
                    pull.hold(rec.robot_id, rec.keyframe_id)
                else:  # a budgeted robot's whole keyframe: also a view signatures can match
                    self._view_of_whole(rec)
            self._note_taken(rec.robot_id, rec.keyframe_id, rec.map_segment)
            if store is not None:
                store.log_keyframe(rec)
                logged = True
                moved = bool(merges) or self.server.map_moved
                mid = self.server.segments.find(rec.robot_id, rec.map_segment)
                store.write_state(self.server, None if moved else [(mid, rec.keyframe_id)])
            return merges
        except CoopSlamError:
            raise
        except Exception:
            # The core failed part-way: its state may have changed, so the input is logged all
            # the same (a rebuild repeats the same failure and reaches the same state).
            if store is not None and not logged and isinstance(rec, KeyframeRecord):
                store.log_keyframe(rec)
            raise
        finally:
            if order.session != UNSEQUENCED:
                order.taken(sequence)
                if store is not None:
                    store.set_ack(robot_id, order.session, order.last)
            if store is not None:
                store.commit()

    def _call(self, kind: str, apply, **args):
        if self.store is None:
            return apply()
        self.store.begin()
        try:
            return apply()
        finally:
            self.store.log_call(kind, **args)
            self.store.write_state(self.server)
            self.store.commit()

    def _seen_together(self, robot_a: int, robot_b: int) -> None:
        """Low-bandwidth mode: robots seen together -- their alike views are a rendezvous."""
        if self.pull is not None and robot_a in self.order and robot_b in self.order:
            self.pull.seen_together(robot_a, robot_b, self.clock())

    def sighting(self, observer, observed, stamp_s, T_camA_bodyB=None, T_body_cam=None):
        self._seen_together(observer, observed)
        return self._call(
            KIND_SIGHTING,
            lambda: self.server.sighting(observer, observed, stamp_s, T_camA_bodyB, T_body_cam),
            robot_a=observer,
            robot_b=observed,
            stamp_s=stamp_s,
            T_camA_bodyB=T_camA_bodyB,
            T_body_cam=T_body_cam,
        )

    def request_rendezvous(
        self, robot_a, robot_b, stamp_s=None, T_camA_bodyB=None, T_body_cam=None
    ):
        self._seen_together(robot_a, robot_b)
        return self._call(
            KIND_RENDEZVOUS,
            lambda: self.server.request_rendezvous(
                robot_a, robot_b, stamp_s, T_camA_bodyB, T_body_cam
            ),
            robot_a=robot_a,
            robot_b=robot_b,
            stamp_s=stamp_s,
            T_camA_bodyB=T_camA_bodyB,
            T_body_cam=T_body_cam,
        )

    def run_due_global_ba(self) -> bool:
        """The global BA a merge left due (``defer_global_ba``), now, as a logged call; whether
        it ran. The server node calls it when no message waits."""
        robot = self.server.global_ba_due
        self.server.global_ba_due = None
        if robot is None or not self.server.global_ba_is_cheap(robot):
            return False
        try:
            self.global_bundle_adjustment(robot)
        except GlobalBaError as exc:
            log.warning("global BA after the merge: %s", exc)
        return True

    def global_bundle_adjustment(self, robot_id: int | None = None):
        return self._call(
            KIND_GLOBAL_BA,
            lambda: self.server.global_bundle_adjustment(robot_id),
            robot_id=robot_id,
        )

    def save(self, path: str) -> str:
        if self.store is None:
            raise MapStoreError("the server keeps no map file (map:= empty): nothing to save")
        self.store.save_copy(path)
        return os.path.abspath(path)

    def close(self) -> None:
        if self.store is not None:
            self.store.close()


def poses_equal(a, b, tol_m: float = 1e-9) -> bool:
    """Two servers' optimized keyframe poses are the same (robots, keyframes and positions)."""
    for r in set(a.groups.robots) | set(b.groups.robots):  # map ids
        pa, pb = a.optimized_keyframes(r), b.optimized_keyframes(r)
        if pa.keys() != pb.keys():
            return False
        if any(np.abs(pa[k] - pb[k]).max() > tol_m for k in pa):
            return False
    return True
