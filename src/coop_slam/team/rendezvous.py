"""Rendezvous on the server: two robots seeing one scene at the same time. The path from a cue to a
verified match, before :mod:`.stitching` makes it a merge:

- **Co-observation** (automatic, no cue): each new keyframe against the other unmerged robots'
  keyframes taken at about the same time, pre-filtered by BoW similarity, verified 3D-3D (feature
  matching, RANSAC, ICP, two-view BA). Identical textures in two places pass any two-view check, so
  it needs ``auto_confirmations`` verifications from different keyframes agreeing on the map
  transform -- unless the pair is *together*.
- **Requests**: a marker sighting (``T_cam_body`` of the sighted robot gives an initial guess and
  a weak prior) or the operator (``/server/rendezvous``) says two robots are together. The
  keyframes around the cue are verified at once; a request that finds no overlap stays open for
  ``request_window_s`` and is retried with the robots' next keyframes.
- **Together**: after a cue the pair counts as together for ``together_s``: its co-observations
  merge on one verification (the cue rules out look-alike places), and a merge between them by any
  path is a rendezvous.

Every verification also passes the look-alike check (:mod:`.plausibility`). A pair with a
monocular keyframe is verified as a similarity (:func:`.map_scale.register_pair`); its confirmations
must then agree on the maps' scale too.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..geometry import transform_error
from ..ids import KeyframeKey
from ..registration.relative_pose import RelativePoseResult, estimate_3d3d
from ..registration.sim3 import sim3_inverse, sim3_matrix
from ..wire.record import KeyframeRecord
from .config import RendezvousConfig
from .groups import MergeGroups
from .keyframe_store import KeyframeStore
from .map_scale import MapScales, chain_similarity, register_pair, split_similarity
from .plausibility import match_is_look_alike
from .results import TYPE_RENDEZVOUS, Verified, map_pair

log = logging.getLogger(__name__)
_CLOCK_RESET_S = 10.0  # a keyframe this much older than the newest seen restarts the budget's clock


@dataclass
class _OpenRequest:
    robot_a: int
    robot_b: int
    stamp_s: float
    T_init: np.ndarray | None  # camera A -> camera B from the marker, when there is one


class Rendezvous:
    def __init__(
        self,
        config: RendezvousConfig,
        store: KeyframeStore,
        groups: MergeGroups,
        scales: MapScales | None = None,
    ):
        self.config = config
        self.store = store
        self.groups = groups
        self.scales = scales  # None: every map metric
        self.verifications = 0
        # Cued requests (marker sighting, operator) not verified yet: the keyframes that show the
        # shared scene often reach the server just after the cue. robot pair -> _OpenRequest
        self._open_requests: dict[tuple[int, int], _OpenRequest] = {}
        self._seen_together: dict[tuple[int, int], float] = {}  # robot pair -> latest cue [s]
        # (low robot, high robot) -> [((key_low, key_high), T_mapLow_mapHigh)] of automatic
        # co-observations, for their confirmation (a similarity as its 4x4 matrix)
        self._co_observations: dict[tuple[int, int], list] = {}
        self._last_sighting: dict[tuple[int, int], float] = {}  # (observer, observed) -> [s]
        # automatic verifications the team-wide budget allows now, and the stamp it last refilled
        self._auto_tokens, self._auto_stamp_s = float(2 * config.auto_max_verifications), None

    # --- cues -------------------------------------------------------------------------------------
    def sighting_due(self, observer: int, observed: int, stamp_s: float) -> bool:
        """Whether a marker sighting becomes a request: at most once per observer/observed pair
        and ``sighting_period_s`` (each request costs up to ``max_pairs`` verifications)."""
        pair = (observer, observed)
        if stamp_s - self._last_sighting.get(pair, -1e9) < self.config.sighting_period_s:
            return False
        self._last_sighting[pair] = stamp_s
        return True

    def together(self, robot_a: int, robot_b: int, stamp_s: float) -> bool:
        """Whether a sighting / operator request put the two robots together shortly before
        (or after: keyframes reach the server late) stamp_s."""
        cue = self._seen_together.get(map_pair(robot_a, robot_b))
        return cue is not None and abs(stamp_s - cue) <= self.config.together_s

    def kind_of(self, v: Verified) -> str:
        """A match seen at (about) the same time or while the robots are known to be together is
        a rendezvous, whichever path verified it; else it keeps its kind."""
        dt = abs(self.store.stamp(v.key_a) - v.stamp_s)
        if dt <= self.config.window_s or self.together(v.key_a[0], v.key_b[0], v.stamp_s):
            return TYPE_RENDEZVOUS
        return v.kind

    # --- automatic co-observation -----------------------------------------------------------------
    def co_observation(self, rec: KeyframeRecord) -> Verified | None:
        """The new keyframe against other unmerged robots' keyframes taken at (about) the same
        time (the two nearest in time per robot; robots with the most similar keyframe first, at
        most ``auto_max_verifications`` 3D-3D verifications per keyframe: with eight robots every
        pair at every keyframe was most of the server's time; and at most
        ``auto_verifications_per_s`` over the team); the first verified match."""
        key_b = rec.key
        bow_b = self.store.bow(key_b)
        candidates = []
        for other in self.groups.robots:
            if self.groups.same_group(other, rec.map_id):
                continue
            keys = self.store.near_in_time(other, rec.stamp_s, self.config.window_s)[:2]
            if keys:
                best = max(self.store.vocabulary.score(self.store.bow(k), bow_b) for k in keys)
                candidates.append((-best, other, keys))
        budget = self.verifications + self._auto_budget(rec.stamp_s)
        for _, other, keys in sorted(candidates):
            cued = self.together(other, rec.map_id, rec.stamp_s)
            for key_a in keys:
                if self.verifications >= budget:
                    return None
                tried = self.verifications
                v = self._verify(key_a, key_b, rec.stamp_s, confirm=not cued)
                if self.config.auto_verifications_per_s > 0:
                    self._auto_tokens -= self.verifications - tried
                if v is not None:
                    return v
        return None

    def _auto_budget(self, stamp_s: float) -> int:
        """Automatic verifications a new keyframe of this stamp may make: at most
        ``auto_max_verifications``, and what the team-wide budget holds after refilling it at
        ``auto_verifications_per_s`` for the data time since the newest stamp seen."""
        cfg = self.config
        if cfg.auto_verifications_per_s <= 0:
            return cfg.auto_max_verifications
        newest = self._auto_stamp_s
        if newest is not None:  # keyframes of several robots: stamps may go back a little
            gained = max(stamp_s - newest, 0.0) * cfg.auto_verifications_per_s
            self._auto_tokens = min(self._auto_tokens + gained, 2.0 * cfg.auto_max_verifications)
        # Far back is another clock (a new session, a replay from 0), not a late keyframe: the
        # budget refills from there, else it would wait for data time to pass the old newest.
        if newest is None or stamp_s > newest or stamp_s < newest - _CLOCK_RESET_S:
            self._auto_stamp_s = stamp_s
        return min(cfg.auto_max_verifications, int(self._auto_tokens))

    def _confirmed(self, key_a, key_b, res: RelativePoseResult) -> bool:
        """Whether earlier automatic verifications of this robot pair (either direction, other
        keyframes) agree with this one on the map transform; this one is remembered either way."""
        cfg = self.config
        T, s = chain_similarity(
            self.store.record(key_a).T_map_cam,
            res.T_a_b,
            res.scale,
            self.store.record(key_b).T_map_cam,
        )
        if key_a[0] > key_b[0]:  # one direction per pair: T_mapLow_mapHigh
            (T, s), key_a, key_b = sim3_inverse(T, s), key_b, key_a
        hits = self._co_observations.setdefault((key_a[0], key_b[0]), [])
        tolerance = (cfg.confirm_trans_m, cfg.confirm_rot_deg)

        def agrees(S_prev: np.ndarray) -> bool:
            T_prev, s_prev = split_similarity(S_prev)
            errors = transform_error(T, T_prev)
            return all(e <= tol for e, tol in zip(errors, tolerance)) and abs(
                np.log(s / s_prev)
            ) <= np.log1p(cfg.confirm_scale_rel)

        agreeing = {
            keys
            for keys, S_prev in hits
            if key_a not in keys and key_b not in keys and agrees(S_prev)
        }
        hits.append(((key_a, key_b), sim3_matrix(T, s)))
        if len(agreeing) + 1 < cfg.auto_confirmations:
            log.info(
                "co-observation %s - %s verified (%d inliers); waiting for %d more agreeing",
                key_a,
                key_b,
                res.n_inliers,
                cfg.auto_confirmations - 1 - len(agreeing),
            )
            return False
        return True

    def _verify(
        self,
        key_a: KeyframeKey,
        key_b: KeyframeKey,
        stamp_s: float,
        T_init=None,
        prior_sigma=None,
        confirm=False,
    ) -> Verified | None:
        """3D-3D verification of one keyframe pair, with every acceptance rule of a merge."""
        cfg = self.config
        score = self.store.vocabulary.score(self.store.bow(key_a), self.store.bow(key_b))
        if score < cfg.min_bow_score and T_init is None:
            return None
        self.verifications += 1
        res = register_pair(
            self.store,
            key_a,
            key_b,
            cfg.registration,
            estimate_3d3d,
            T_init=T_init,
            prior_sigma=prior_sigma,
        )
        log.debug("rendezvous %s vs %s (bow %.3f): %s", key_a, key_b, score, res.reason)
        if not res.accepted:
            return None
        if match_is_look_alike(self.store, cfg, self.scales, "rendezvous", key_a, key_b, res):
            return None
        if res.n_inliers < cfg.merge_min_inliers:
            log.info(
                "rendezvous %s - %s: %d inliers, fewer than a merge needs (%d)",
                key_a,
                key_b,
                res.n_inliers,
                cfg.merge_min_inliers,
            )
            return None
        if confirm and not self._confirmed(key_a, key_b, res):
            return None
        return Verified(TYPE_RENDEZVOUS, key_a, key_b, res, stamp_s)

    # --- cued requests ----------------------------------------------------------------------------
    def request(
        self,
        robot_a: int,
        robot_b: int,
        stamp_s: float | None = None,
        T_init: np.ndarray | None = None,
    ) -> tuple[Verified | None, str]:
        """Robots a and b are together at stamp_s (default: now, their latest keyframes).
        ``T_init`` (camera A -> camera B, from a marker) is only an initial guess and a weak
        prior. Returns (the verified match or None, why not). The robots must be known and not in
        one group (the server checks)."""
        cfg = self.config
        if stamp_s is None:
            latest = [self.store.latest_stamp(r) for r in (robot_a, robot_b)]
            if None in latest:
                return None, "no keyframes yet from one of the robots"
            stamp_s = max(latest)  # now; a robot that stands still falls back to its latest
        pair = map_pair(robot_a, robot_b)
        self._seen_together[pair] = max(stamp_s, self._seen_together.get(pair, stamp_s))
        near = self.store.near_in_time
        keys_a = near(robot_a, stamp_s, cfg.request_window_s, latest_fallback=True)
        keys_b = near(robot_b, stamp_s, cfg.request_window_s, latest_fallback=True)
        if not keys_a or not keys_b:
            return (
                None,
                f"no keyframes of both robots within {cfg.request_window_s} s of {stamp_s:.2f} s",
            )
        request = _OpenRequest(robot_a, robot_b, stamp_s, T_init)
        v = self._verify_request(request, keys_a[:3], keys_b[:3], cfg.max_pairs)
        if v is not None:
            return v, ""
        self._open_requests[pair] = request
        return None, (
            f"no verified overlap between robots {robot_a} and {robot_b} around "
            f"{stamp_s:.2f} s yet: not merged (a marker sighting alone is not enough); "
            f"keyframes up to {stamp_s + cfg.request_window_s:.2f} s will be tried as they arrive"
        )

    def _verify_request(self, request: _OpenRequest, keys_a, keys_b, max_pairs: int):
        """Verify keyframe pairs of a cued request, closest in time first; the match or None."""
        stamp = self.store.stamp
        pairs = sorted(
            ((ka, kb) for ka in keys_a for kb in keys_b),
            key=lambda p: abs(stamp(p[0]) - stamp(p[1])),
        )
        prior = (np.radians(10.0), 0.2) if request.T_init is not None else None
        for key_a, key_b in pairs[:max_pairs]:
            # The merge happens when both the cue and the keyframes exist.
            stamp_s = max(request.stamp_s, stamp(key_a), stamp(key_b))
            v = self._verify(key_a, key_b, stamp_s, request.T_init, prior)
            if v is not None:
                return v
        return None

    def retry_requests(self, rec: KeyframeRecord) -> Verified | None:
        """A new keyframe taken within the window of an open cued request of its robot is
        verified against the other robot's keyframes nearest the cue; requests whose window has
        passed (or whose robots merged meanwhile) are closed."""
        window = self.config.request_window_s
        for pair, request in list(self._open_requests.items()):
            if self.groups.same_group(request.robot_a, request.robot_b) or (
                rec.map_id in pair and rec.stamp_s > request.stamp_s + window
            ):
                del self._open_requests[pair]
                continue
            if rec.map_id not in pair or abs(rec.stamp_s - request.stamp_s) > window:
                continue
            key_new = rec.key
            other = request.robot_b if rec.map_id == request.robot_a else request.robot_a
            # The other robot's views nearest the cue, and nearest this keyframe (what it saw at
            # the same moment: keyframes reach the server a while after they were made, so the
            # ones nearest the cue can be older than this one).
            near = self.store.near_in_time
            keys_other = list(
                dict.fromkeys(
                    near(other, rec.stamp_s, window, latest_fallback=True)[:3]
                    + near(other, request.stamp_s, window, latest_fallback=True)[:3]
                )
            )
            if rec.map_id == request.robot_a:
                v = self._verify_request(request, [key_new], keys_other, len(keys_other))
            else:
                v = self._verify_request(request, keys_other, [key_new], len(keys_other))
            if v is not None:
                del self._open_requests[pair]
                log.info("rendezvous request %s / %s: verified on a later keyframe", *pair)
                return v
        return None

    @property
    def has_open_requests(self) -> bool:
        return bool(self._open_requests)
