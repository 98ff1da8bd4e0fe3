"""From verified matches to the team map: a match between two groups merges them (in the merge
order of :mod:`.merge_order`), a match inside one group becomes a constraint -- a robot's own loop
closure or a further link between merged robots -- gated against the current estimate. Both go into
the team pose graph, and the map points they matched are linked for global BA.

Wrong merges are worse than late ones: the stages before this one (place recognition, rendezvous)
decide what is verified; this one decides how much weight it gets.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ..geometry import invert, transform_error
from ..registration.relative_pose import RelativePoseResult
from .config import LoopClosureConfig
from .groups import MergeGroups, chain_map_transform
from .keyframe_store import KeyframeStore
from .merge_order import plan_merge_steps
from .overlap_links import OverlapLinks
from .pose_graph import PoseGraphError, TeamPoseGraph
from .results import TYPE_LOOP, ConstraintResult, MergeResult, Verified, map_pair

log = logging.getLogger(__name__)


def graph_call(fn, *args, **kwargs) -> None:
    """Call a pose-graph method; its errors are logged, never raised: the graph must never take
    the server down."""
    try:
        fn(*args, **kwargs)
    except PoseGraphError as exc:
        log.warning("pose graph: %s", exc)


class Stitcher:
    """Turns verified matches into merges and constraints (see module docstring).

    ``kf_count(robot)`` is the number of keyframes the robot has sent so far: a robot adds a
    constraint at most every ``loops.min_interval_kf`` keyframes."""

    def __init__(
        self,
        config: LoopClosureConfig,
        store: KeyframeStore,
        groups: MergeGroups,
        graph: TeamPoseGraph,
        kf_count: Callable[[int], int],
        links: OverlapLinks | None = None,
        prepare_merge: Callable[[Verified], Verified] | None = None,
        on_constraint: Callable[[Verified], None] | None = None,
        map_name: Callable[[int], str] = lambda m: f"robot {m}",
    ):
        self.config = config
        self.store = store
        self.groups = groups
        self.graph = graph
        self.links = links  # welding windows of merges; None: a merge rests on its one pair
        self._kf_count = kf_count
        # A merge by a similarity first brings both sides to one length unit (see .map_scale) and
        # returns the match as a rigid one; every accepted constraint is shown to on_constraint.
        self._prepare_merge = prepare_merge
        self._on_constraint = on_constraint
        self._map_name = map_name  # a map id as the user knows it (see .segments)
        self.merges: list[MergeResult] = []
        self.constraints: list[ConstraintResult] = []  # loop closures and in-group links
        self.rejected_constraints = 0  # verified, but too far from the current estimate
        # (robot, map point id) pairs that merges / loops matched: one physical point each
        self.point_links: list[tuple[tuple[int, int], tuple[int, int]]] = []
        self.need_full = False  # a constraint was added: the next optimization must be full
        self._last_constraint: dict[int, int] = {}  # robot -> its keyframe count at the last one

    def constraint_due(self, robot_id: int) -> bool:
        """Whether the robot sent loops.min_interval_kf keyframes since its last constraint."""
        due = self._kf_count(robot_id) - self._last_constraint.get(robot_id, -(10**9))
        return due >= self.config.min_interval_kf

    # --- merges -----------------------------------------------------------------------------------
    def apply_plan(
        self, pending: dict[tuple[int, int], Verified], match_counts: dict
    ) -> list[MergeResult]:
        """Execute verified cross-group matches (robot pair -> match) in merge order (DSM-SLAM):
        the pair of groups sharing the most keyframe matches first; matches left linking robots of
        one group after that become constraints."""
        if not pending:
            return []
        counts = {pair: max(1, match_counts.get(pair, 0)) for pair in pending}
        merges = []
        for step in plan_merge_steps(counts, self.groups.groups()):
            merges.append(self.merge(pending.pop(map_pair(step.map_a, step.map_b))))
        for v in pending.values():
            self.add_constraint(v)
        pending.clear()
        return merges

    def merge(self, v: Verified) -> MergeResult:
        """Join the groups of the two keyframes' robots on the verified match, welded on the
        pairs around it that the match predicts and registration confirms (see
        :mod:`.overlap_links`); the optimization that follows estimates the map transform from
        all of them."""
        measured_scale = float(v.result.scale)  # the merge's own, before a rescale
        if self._prepare_merge is not None:
            v = self._prepare_merge(v)
        key_a, key_b, res = v.key_a, v.key_b, v.result
        rec_a, rec_b = self.store.record(key_a), self.store.record(key_b)
        robots_a = set(self.groups.members(key_a[0]))
        robots_b = set(self.groups.members(key_b[0]))
        T_mapA_mapB = chain_map_transform(rec_a.T_map_cam, res.T_a_b, rec_b.T_map_cam)
        group = self.groups.merge(key_a[0], key_b[0], T_mapA_mapB)
        self._add_factor(v.kind, key_a, key_b, res)
        welded, swept = [], []
        if self.links is not None and self.links.config.enabled:
            # The graph has moved b's group onto a's at this match: its estimate predicts
            # the pairs.
            tried: set = set()
            welded = self.links.weld(key_a, key_b, robots_a, robots_b, v.stamp_s, tried)
            for w in welded:
                self._add_factor(v.kind, w.key_a, w.key_b, w.result)
                if self._on_constraint is not None:
                    self._on_constraint(w)
            if welded:
                self.need_full = True
            swept = self.links.sweep(robots_a, robots_b, v.stamp_s, tried)
        merge = MergeResult(
            v.kind,
            key_a[0],
            key_b[0],
            key_a[1],
            key_b[1],
            v.stamp_s,
            T_mapA_mapB,
            res.T_a_b,
            int(res.n_inliers),
            float(res.residual_px),
            group,
            len(welded),
            measured_scale,
        )
        self.merges.append(merge)
        log.info(
            "merged %s into %s's map (%s, %d inliers, %.2f px, welded on %d more pairs): "
            "group %s",
            self._map_name(key_b[0]),
            self._map_name(key_a[0]),
            v.kind,
            merge.inliers,
            merge.residual_px,
            len(welded),
            group,
        )
        # Links across the rest of the overlap, each judged as any link (gates, robust kernel).
        for w in swept:
            self.add_constraint(w)
        return merge

    # --- constraints inside a group ---------------------------------------------------------------
    def add_constraint(self, v: Verified) -> bool:
        """A verified relative pose between keyframes of one group goes into the pose graph as a
        robust loop (same robot) or merge (two robots) factor, unless it contradicts the current
        estimate by more than the gate. A full optimization follows."""
        key_a, key_b, res = v.key_a, v.key_b, v.result
        loops = self.config
        try:
            T_est = invert(self.graph.T_group_cam(*key_a)) @ self.graph.T_group_cam(*key_b)
        except PoseGraphError as exc:
            log.warning("constraint %s - %s skipped: %s", key_a, key_b, exc)
            return False
        dt, dr = transform_error(res.T_a_b, T_est)
        # A well-supported constraint may correct drift up to the gate; a weakly supported one
        # (registration accepted, fewer than min_inliers) only where it agrees with the estimate,
        # which on real images it mostly does: it then refines rather than moves the map.
        strong = res.n_inliers >= loops.min_inliers
        gate_t, gate_r = (
            (loops.gate_trans_m, loops.gate_rot_deg)
            if strong
            else (loops.weak_gate_trans_m, loops.weak_gate_rot_deg)
        )
        if dt > gate_t or dr > gate_r:
            self.rejected_constraints += 1
            log.info(
                "constraint %s - %s refused: %d inliers, %.2f m / %.1f deg from the current "
                "estimate",
                key_a,
                key_b,
                res.n_inliers,
                dt,
                dr,
            )
            return False
        sig_rot, sig_trans = self._sigmas(res)
        # The disagreement the gate let through is drift of the odometry chain, not an error of
        # this (precise) constraint: the kernel is widened by it, else the robust loss would
        # down-weight exactly the loops that correct the most drift. A constraint that later
        # disagrees with the rest of the graph by more is still down-weighted.
        d2 = 0.0
        if sig_rot is not None:
            d2 = (dt / sig_trans) ** 2 + (np.radians(dr) / sig_rot) ** 2
        ds = self._add_factor(v.kind, key_a, key_b, res, d2)  # None: no scale measured
        self.constraints.append(
            ConstraintResult(
                TYPE_LOOP if key_a[0] == key_b[0] else v.kind,
                key_a,
                key_b,
                v.stamp_s,
                res.T_a_b,
                int(res.n_inliers),
                float(res.residual_px),
            )
        )
        self._last_constraint[key_b[0]] = self._kf_count(key_b[0])
        cfg = self.config
        far_scale = ds is not None and abs(ds) > cfg.full_above_scale
        if dt > cfg.full_above_trans_m or dr > cfg.full_above_rot_deg or far_scale:
            self.need_full = True
        if self._on_constraint is not None:
            self._on_constraint(v)
        log.info(
            "%s constraint %s - %s (%d inliers, %.2f px; %.3f m / %.2f deg%s from estimate)",
            self.constraints[-1].type,
            key_a,
            key_b,
            res.n_inliers,
            res.residual_px,
            dt,
            dr,
            "" if ds is None else f" / scale {100 * ds:+.1f} %",
        )
        return True

    # --- pose graph -------------------------------------------------------------------------------
    def _add_factor(self, kind: str, key_a, key_b, res: RelativePoseResult, d2=0.0) -> float | None:
        """A verified relative pose into the pose graph (loop factor within one robot, merge factor
        between two), its matched map points into the links for global BA. Its robust kernel is
        widened by ``d2``, its pose's squared whitened disagreement with the estimate, and by its
        scale's (a similarity's) with the graph's local scales; returns the latter, relative
        (None without a scale)."""
        sig_rot, sig_trans = self._sigmas(res)
        scale = self._scale_row(res)
        ds = None
        if scale:
            ds = scale["log_scale"] - (self._log_scale(key_b) - self._log_scale(key_a))
            d2 += (ds / scale["log_scale_sigma"]) ** 2
        robust_k = self.graph.config.robust_k * float(np.sqrt(1.0 + d2)) if d2 > 0 else None
        if key_a[0] == key_b[0]:
            graph_call(
                self.graph.add_loop,
                key_a[0],
                key_a[1],
                key_b[1],
                res.T_a_b,
                TYPE_LOOP,
                sig_rot,
                sig_trans,
                robust_k,
                **scale,
            )
        else:
            graph_call(
                self.graph.add_merge,
                key_a[0],
                key_a[1],
                key_b[0],
                key_b[1],
                res.T_a_b,
                kind,
                sig_rot,
                sig_trans,
                robust_k,
                **scale,
            )
        self._record_links(key_a, key_b, res)
        return None if ds is None else float(np.expm1(ds))

    def _log_scale(self, key) -> float:
        try:
            return float(np.log(self.graph.local_scale(*key)))
        except PoseGraphError:
            return 0.0

    def _record_links(self, key_a, key_b, res: RelativePoseResult) -> None:
        """Map points matched by an accepted registration are one physical point."""
        ids_a = self.store.record(key_a).map_point_ids
        ids_b = self.store.record(key_b).map_point_ids
        for ia, ib in np.asarray(res.inlier_idx, int).reshape(-1, 2):
            if ia < len(ids_a) and ib < len(ids_b) and ids_a[ia] and ids_b[ib]:
                self.point_links.append(((key_a[0], int(ids_a[ia])), (key_b[0], int(ids_b[ib]))))

    def _sigmas(self, res: RelativePoseResult) -> tuple[float, float]:
        """(rotation [rad], translation [m]) std of a loop / merge factor from the registration."""
        cfg = self.config
        rot_deg = max(cfg.min_sigma_rot_deg, cfg.sigma_scale * res.sigma_rot_deg)
        trans_m = max(cfg.min_sigma_trans_m, cfg.sigma_scale * res.sigma_trans_m)
        if not np.isfinite(rot_deg * trans_m):  # no marginals: the pose graph's defaults
            return None, None
        return float(np.radians(rot_deg)), float(trans_m)

    def _scale_row(self, res: RelativePoseResult) -> dict:
        """A similarity's scale (a monocular side) and its log std, which measure the maps'
        local scales where it was taken; none for a rigid estimate (or without a marginal)."""
        if not np.isfinite(res.sigma_log_scale):
            return {}
        sigma = max(self.config.min_sigma_log_scale, self.config.sigma_scale * res.sigma_log_scale)
        return {"log_scale": float(np.log(res.scale)), "log_scale_sigma": float(sigma)}
