"""Place recognition on the server: a new keyframe against every robot's keyframes -- BoW retrieval
in the team database, temporal consistency, PnP RANSAC + two-view BA, acceptance.

Candidates in another group are merge candidates (a merge joins two maps on one constraint, so it
needs ``merge_min_inliers``); candidates in the keyframe's own group are loop closures or further
links between merged robots (see :mod:`.stitching`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from ..bow.database import ConsistencyChecker, ConsistencyConfig
from ..bow.vocabulary import BowVector
from ..ids import KeyframeKey
from ..registration.relative_pose import RelativePoseResult, estimate_pnp
from ..wire.record import KeyframeRecord
from .config import LoopClosureConfig, PlaceRecognitionConfig, RendezvousConfig
from .groups import MergeGroups
from .keyframe_store import KeyframeStore
from .map_scale import MapScales, register_pair
from .plausibility import match_is_look_alike
from .results import TYPE_PLACE_RECOGNITION, Verified, map_pair

log = logging.getLogger(__name__)


@dataclass
class PlaceMatches:
    """What one query found: verified matches with other groups (at most one per group, not yet
    merged), and consistent candidates inside the keyframe's own group (not yet verified)."""

    cross: list[Verified] = field(default_factory=list)
    inner: list[KeyframeKey] = field(default_factory=list)
    budget: int = 0  # verifications left for this keyframe


class PlaceRecognition:
    def __init__(
        self,
        config: PlaceRecognitionConfig,
        loops: LoopClosureConfig,
        rendezvous: RendezvousConfig,
        store: KeyframeStore,
        groups: MergeGroups,
        scales: MapScales | None = None,
    ):
        self.config = config
        self.scales = scales  # None: every map metric
        self.loops = loops
        self.rendezvous = rendezvous  # for the look-alike check
        self.store = store
        self.groups = groups
        self.consistency = ConsistencyChecker(
            ConsistencyConfig(min_consecutive=config.min_consecutive)
        )
        self.match_counts: dict[tuple[int, int], int] = {}  # robot pair -> keyframe matches
        self.verifications = 0

    def query(
        self,
        rec: KeyframeRecord,
        bow: BowVector,
        covisible: list[KeyframeKey],
        consistent_already: bool = False,
    ) -> PlaceMatches:
        """Consistent candidates of a new keyframe; those in other groups verified, best first,
        within ``max_verifications``. ``consistent_already``: the query's candidates passed a
        consistency check elsewhere (a keyframe the pull planner asked for)."""
        rb, key_b = rec.map_id, rec.key
        candidates = [
            c
            for c in self.store.database.query(
                bow,
                rb,
                rec.keyframe_id,
                covisible=covisible,
                other_robots_only=not self.loops.enabled,
            )
            if c.key in self.store
            and not (
                c.key[0] == rb
                and rec.stamp_s - self.store.stamp(c.key) < self.loops.min_separation_s
            )
        ]
        if consistent_already:
            consistent = [c.key for c in candidates]
        else:
            consistent = self.consistency.check(rb, candidates, self.store.database)
        cross = [k for k in consistent if not self.groups.same_group(k[0], rb)]
        found = PlaceMatches(inner=[k for k in consistent if self.groups.same_group(k[0], rb)])
        for k in cross:
            pair = map_pair(k[0], rb)
            self.match_counts[pair] = self.match_counts.get(pair, 0) + 1
        budget = self.config.max_verifications
        verified_roots = set()
        for cand_key in cross:
            root = self.groups.root(cand_key[0])
            if budget == 0 or root in verified_roots:
                continue
            budget -= 1
            res = self.verify(cand_key, key_b)
            need = (
                self.config.merge_min_inliers
                if res.scale == 1.0
                else self.config.merge_min_inliers_similarity
            )
            if res.accepted and res.n_inliers < need:
                log.info(
                    "place recognition %s - %s: %d inliers, fewer than a merge needs (%d)",
                    cand_key,
                    key_b,
                    res.n_inliers,
                    need,
                )
            elif res.accepted and not match_is_look_alike(
                self.store, self.rendezvous, self.scales, "place recognition", cand_key, key_b, res
            ):
                verified_roots.add(root)
                found.cross.append(
                    Verified(TYPE_PLACE_RECOGNITION, cand_key, key_b, res, rec.stamp_s)
                )
        found.budget = budget
        return found

    def verify(self, key_a: KeyframeKey, key_b: KeyframeKey) -> RelativePoseResult:
        """PnP RANSAC of b's keypoints against a's points, refined by two-view BA; a similarity
        when either keyframe is monocular (PnP would give b's pose, not b's map's scale)."""
        self.verifications += 1
        res = register_pair(self.store, key_a, key_b, self.config.registration, estimate_pnp)
        log.debug("place recognition %s vs %s: %s", key_a, key_b, res.reason)
        return res

    def merged(self, robot_id: int) -> None:
        """A robot's group changed: its consistency history refers to the old groups."""
        self.consistency.reset(robot_id)
