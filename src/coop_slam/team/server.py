"""The server's pure core: team keyframe store, shared-vocabulary database, place-recognition
stitching (BoW retrieval -> consistency -> PnP RANSAC -> two-view BA -> acceptance) and merge groups.

Wrong merges are worse than late ones: a candidate must be temporally consistent and pass the
registration's geometric acceptance tests before two maps are joined.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from ..bow import Vocabulary
from ..bow.database import ConsistencyChecker, ConsistencyConfig, DatabaseConfig, KeyframeDatabase
from ..config import require
from ..errors import CoopSlamError
from ..keyframe import ACTION_NEW, ACTION_REMOVE, ACTION_UPDATE, KeyframeRecord
from ..registration.keyframe import KeyframeView
from ..registration.relative_pose import RegistrationConfig, RelativePoseResult, estimate_pnp
from .groups import MergeGroups, chain_map_transform

log = logging.getLogger(__name__)

TYPE_PLACE_RECOGNITION = "place_recognition"
TYPE_RENDEZVOUS = "rendezvous"


class ServerError(CoopSlamError):
    """Keyframes or requests the server cannot take (unknown robot, inconsistent ids, ...)."""


@dataclass
class PlaceRecognitionConfig:
    enabled: bool = True
    min_consecutive: int = 2  # consecutive consistent queries before a candidate is verified
    max_verifications: int = 2  # candidates geometrically verified per keyframe (bounds the cost)
    database: DatabaseConfig = field(default_factory=DatabaseConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)

    def validate(self) -> None:
        require(self.min_consecutive >= 1, "place_recognition.min_consecutive must be >= 1")
        require(self.max_verifications >= 1, "place_recognition.max_verifications must be >= 1")
        self.database.validate()
        self.registration.validate()


@dataclass
class ServerConfig:
    robots: list[int] = field(default_factory=lambda: [1, 2])  # robot ids the server accepts
    place_recognition: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)

    def validate(self) -> None:
        require(len(self.robots) >= 1, "server: robots must list at least one robot id")
        require(all(r >= 1 for r in self.robots), "server: robot ids must be >= 1")
        require(len(set(self.robots)) == len(self.robots), "server: robot ids must be unique")
        self.place_recognition.validate()


@dataclass
class MergeResult:
    type: str
    robot_a: int  # reference robot (its group's frame is kept)
    robot_b: int
    keyframe_a: int
    keyframe_b: int
    stamp_s: float  # stamp of the keyframe that triggered the merge
    T_mapA_mapB: np.ndarray
    T_camA_camB: np.ndarray
    inliers: int
    residual_px: float
    group: list[int]


@dataclass
class _Stored:
    record: KeyframeRecord
    view: KeyframeView | None = None


class TeamServer:
    """Consumes validated keyframes from all robots and stitches their maps."""

    def __init__(self, config: ServerConfig, vocabulary: Vocabulary):
        config.validate()
        self.config = config
        self.vocabulary = vocabulary
        self.known_robots = set(config.robots)
        self.groups = MergeGroups(config.robots)
        pr = config.place_recognition
        self.database = KeyframeDatabase(pr.database)
        self.consistency = ConsistencyChecker(ConsistencyConfig(min_consecutive=pr.min_consecutive))
        self.keyframes: dict[tuple[int, int], _Stored] = {}
        self.merges: list[MergeResult] = []
        self.keyframe_ms: list[float] = []  # server time per incoming keyframe
        self.verifications = 0

    # --- keyframes ----------------------------------------------------------------------------------
    def add_keyframe(self, rec: KeyframeRecord) -> list[MergeResult]:
        """Store (or update / remove) one keyframe; returns the merges it caused."""
        t0 = time.perf_counter()
        rec.validate(self.known_robots)
        key = (rec.robot_id, rec.keyframe_id)
        merges: list[MergeResult] = []
        if rec.action == ACTION_REMOVE:
            if key in self.keyframes:
                del self.keyframes[key]
                self.database.remove(*key)
        elif rec.action == ACTION_UPDATE and key in self.keyframes:
            # Local BA moved the pose / points; descriptors (and so the BoW vector) are unchanged.
            self.keyframes[key] = _Stored(rec)
        elif rec.action in (ACTION_NEW, ACTION_UPDATE):
            if key in self.keyframes:
                raise ServerError(f"keyframe {rec.keyframe_id} of robot {rec.robot_id} was "
                                  "already received as new")
            bow, _ = self.vocabulary.transform(rec.descriptors)
            covisible = [(rec.robot_id, int(k)) for k in rec.covisible_ids]
            self.keyframes[key] = _Stored(rec)
            self.database.add(rec.robot_id, rec.keyframe_id, bow, covisible)
            if self.config.place_recognition.enabled:
                merges = self._place_recognition(rec, bow, covisible)
        self.keyframe_ms.append(1e3 * (time.perf_counter() - t0))
        return merges

    def _view(self, key) -> KeyframeView:
        stored = self.keyframes[key]
        if stored.view is None:
            r = stored.record
            stored.view = KeyframeView(r.uv_px, r.descriptors, r.depths_m, r.camera.K)
        return stored.view

    def _place_recognition(self, rec: KeyframeRecord, bow, covisible) -> list[MergeResult]:
        rb = rec.robot_id
        members = set(self.groups.members(rb))
        candidates = [c for c in self.database.query(bow, rb, rec.keyframe_id, covisible=covisible,
                                                     other_robots_only=True)
                      if c.key[0] not in members]
        consistent = self.consistency.check(rb, candidates, self.database)
        merges = []
        for cand_key in consistent[: self.config.place_recognition.max_verifications]:
            if cand_key not in self.keyframes or self.groups.same_group(cand_key[0], rb):
                continue
            self.verifications += 1
            res = estimate_pnp(self._view(cand_key), self._view((rb, rec.keyframe_id)),
                               self.config.place_recognition.registration)
            log.debug("place recognition %s vs %s: %s", cand_key, (rb, rec.keyframe_id), res.reason)
            if res.accepted:
                merges.append(self._merge(TYPE_PLACE_RECOGNITION, cand_key, (rb, rec.keyframe_id),
                                          res, rec.stamp_s))
                break
        return merges

    def _merge(self, kind: str, key_a, key_b, res: RelativePoseResult, stamp_s: float) -> MergeResult:
        rec_a, rec_b = self.keyframes[key_a].record, self.keyframes[key_b].record
        T_mapA_mapB = chain_map_transform(rec_a.T_map_cam, res.T_a_b, rec_b.T_map_cam)
        group = self.groups.merge(key_a[0], key_b[0], T_mapA_mapB)
        merge = MergeResult(kind, key_a[0], key_b[0], key_a[1], key_b[1], stamp_s, T_mapA_mapB,
                            res.T_a_b, int(res.n_inliers), float(res.residual_px), group)
        self.merges.append(merge)
        self.consistency.reset(key_b[0])
        log.info("merged robot %d into robot %d's map (%s, %d inliers, %.2f px): group %s",
                 key_b[0], key_a[0], kind, merge.inliers, merge.residual_px, group)
        return merge

    # --- team frame ---------------------------------------------------------------------------------
    def T_world_map(self, robot_id: int) -> tuple[np.ndarray, bool]:
        """Robot's map in its group's frame, and whether that group is the world (holds robot 1 /
        the smallest id of the team)."""
        world_root = min(self.known_robots)
        return self.groups.T_root_map(robot_id), self.groups.root(robot_id) == world_root
