"""Team pose graph: one GTSAM factor graph over the keyframes of every robot.

Parameterisation
----------------
One variable per keyframe, ``X = T_group_cam``: the camera pose in its *group frame*. A group is a
connected component of the graph (robots joined by merge factors); its frame is the map frame of
its smallest robot id, matching :mod:`coop_slam.team.groups`, so the component holding robot 1 is
``world``. Variable keys are ``gtsam.Symbol(chr(ord('a') + map_id), keyframe_id)``, so all robots
live in one graph.

Factors (``BetweenFactorPose3`` measuring ``T_cami_camj = X_i^-1 X_j`` unless said, sigmas
rotation first as in GTSAM's Pose3 tangent space):

- odometry: between a robot's keyframes that are neighbours in keyframe-id order, measured from
  the client's poses ``T_map_cam_i^-1 T_map_cam_j``; sigmas grow with the distance between them.
  ``covisible`` factors are the same measurement to a few covisible keyframes, to stiffen the
  client's local structure. Both are rebuilt whenever the client moves a keyframe (local BA).
- loop (intra-robot) and merge (inter-robot) constraints from place recognition / rendezvous, with
  a robust kernel (Cauchy by default) so one wrong constraint cannot wreck the map.
- a monocular map (``set_scale_drift``) has one more variable per keyframe, its log scale, and
  its odometry / covisible factors measure the translation times the local scale, with a random
  walk of the scale; its loops and links measured by a similarity carry the similarity's scale
  (see :mod:`.scale_drift`; one weak prior per map).
- gauge priors: one stiff prior per connected component, on the first keyframe of its smallest
  robot, at that keyframe's estimate when the prior was created (for a component's first keyframe
  that is ``T_group_map_hint @ T_map_cam``, i.e. the client's own pose for a group root).

Optimisation: :meth:`TeamPoseGraph.optimize_incremental` feeds new factors to iSAM2 as keyframes
arrive; :meth:`TeamPoseGraph.optimize_full` runs batch Levenberg-Marquardt (after a merge or loop
closure) and resets iSAM2 from its result. Changes iSAM2 cannot absorb (a merge re-expresses one
group in another's frame, a culled keyframe removes a variable, a gauge prior moves) make the next
incremental call fall back to a full optimisation. A failing step (GTSAM throws, or the error or
result is not finite) raises PoseGraphError and leaves the estimate as it was; iSAM2, which may
hold half of that step, is dropped, so the next call rebuilds it from the factor list.
"""

from __future__ import annotations

import bisect
import logging
import time
from dataclasses import replace
from typing import NoReturn

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..errors import GeometryError
from ..geometry import check_se3, invert
from ..ids import MAX_MAP_ID, KeyframeKey
from ..registration.camera import RegistrationError
from ..registration.umeyama import umeyama
from .map_scale import scale_translation
from .pose_graph_factors import (
    CLIENT_KINDS,
    KIND_COVISIBLE,
    KIND_LOOP,
    KIND_MERGE,
    KIND_ODOMETRY,
    KIND_PRIOR,
    KIND_SCALE_PRIOR,
    MAX_KEYFRAME_ID,
    ConstraintStatus,
    Factor,
    FactorTable,
    OptimizationStats,
    PoseGraphConfig,
    PoseGraphError,
    finite_error,
    finite_poses,
    gtsam_key,
)
from .scale_drift import pose_sigmas, scale_key

log = logging.getLogger(__name__)


class TeamPoseGraph(FactorTable):
    """Keyframe pose graph of the whole team; see the module docstring for the model."""

    def __init__(self, config: PoseGraphConfig | None = None):
        config = config or PoseGraphConfig()
        config.validate()
        super().__init__(config)
        self._fresh: set[KeyframeKey] = set()  # keyframes no optimisation has seen yet
        self._refinements = 0
        self._values: dict[KeyframeKey, np.ndarray] = {}  # current estimate T_group_cam
        self._chain: dict[int, list[int]] = {}  # map -> sorted keyframe ids
        self._map_hint: dict[int, np.ndarray] = {}  # T_group_map for a map's first keyframe
        self._priors: dict[KeyframeKey, int] = {}  # anchor keyframe -> prior factor id
        self._scale_priors: dict[KeyframeKey, int] = (
            {}
        )  # a drifting map's first keyframe -> factor id
        # iSAM2 state (its factors' slots: FactorTable), the keys it holds.
        self._isam: gtsam.ISAM2 | None = None
        self._isam_keys: set[KeyframeKey] = set()
        self._rebuild = False  # iSAM2 cannot absorb the last changes: next call is a full one
        self.stats = OptimizationStats()

    # --- checks -----------------------------------------------------------------------------------
    @staticmethod
    def _pose(T, name: str) -> np.ndarray:
        try:
            return check_se3(T, name)
        except GeometryError as exc:
            raise PoseGraphError(str(exc)) from None

    def _check_key(self, map_id: int, keyframe_id: int) -> KeyframeKey:
        key = (int(map_id), int(keyframe_id))
        if key not in self._values:
            raise PoseGraphError(
                f"keyframe {keyframe_id} of robot {map_id} is not in the pose "
                "graph (add it with add_keyframe first)"
            )
        return key

    def _check_robot(self, map_id: int) -> None:
        if map_id not in self._chain and map_id not in self._map_hint:
            raise PoseGraphError(
                f"robot {map_id} is unknown to the pose graph " f"(known: {self.robots})"
            )

    # --- keyframes --------------------------------------------------------------------------------
    def set_map_transform(self, map_id: int, T_group_map: np.ndarray) -> None:
        """Where a robot's map sits in its group frame, used for the initial estimate of the robot's
        first keyframe. Later keyframes chain from the robot's existing estimates, which already
        live in the graph's frame; merges align groups themselves (see :meth:`add_merge`)."""
        self._map_hint[int(map_id)] = self._pose(T_group_map, f"T_group_map of robot {map_id}")

    def add_keyframe(
        self,
        map_id: int,
        keyframe_id: int,
        T_map_cam: np.ndarray,
        T_group_map: np.ndarray | None = None,
        covisible_ids=(),
    ) -> None:
        """Add a keyframe with its client pose; links it by odometry to its neighbours in id order
        (normally the robot's previous keyframe) and to up to ``max_covisible_factors`` of the
        given covisible keyframes of the same robot."""
        map_id, keyframe_id = int(map_id), int(keyframe_id)
        if not 0 <= map_id <= MAX_MAP_ID:
            raise PoseGraphError(f"map id {map_id} must be in [0, {MAX_MAP_ID}]")
        if not 0 <= keyframe_id <= MAX_KEYFRAME_ID:
            raise PoseGraphError(f"keyframe id {keyframe_id} must be in [0, 2^55)")
        key = (map_id, keyframe_id)
        if key in self._values:
            raise PoseGraphError(
                f"keyframe {keyframe_id} of robot {map_id} is already in the "
                "pose graph (use update_keyframe)"
            )
        T_map_cam = self._pose(T_map_cam, f"pose of keyframe {keyframe_id} of robot {map_id}")
        if T_group_map is not None:
            self.set_map_transform(map_id, T_group_map)
        chain = self._chain.setdefault(map_id, [])
        pos = bisect.bisect_left(chain, keyframe_id)
        prev = (map_id, chain[pos - 1]) if pos > 0 else None
        nxt = (map_id, chain[pos]) if pos < len(chain) else None
        chain.insert(pos, keyframe_id)
        self._client[key] = T_map_cam
        self._chain_estimate(key, prev or nxt)
        if prev is not None and nxt is not None:
            # Out-of-order arrival: the new keyframe splits an existing odometry edge.
            for fid in self._odometry_between(prev, nxt):
                self._drop_factor(fid)
        for nb in (prev, nxt):
            if nb is not None:
                a, b = (nb, key) if nb[1] < keyframe_id else (key, nb)
                self._client_factor(KIND_ODOMETRY, a, b)
        added = 0
        for cid in covisible_ids:
            ckey = (map_id, int(cid))
            if added >= self.config.max_covisible_factors:
                break
            if ckey in self._values and ckey not in (prev, nxt, key):
                self._client_factor(KIND_COVISIBLE, ckey, key)
                added += 1

    def _chain_estimate(self, key: KeyframeKey, ref: KeyframeKey | None) -> None:
        """Initial estimate of a keyframe no optimisation has seen yet: chained from neighbour
        ``ref``'s estimate (already in the graph's frame) by their client poses; without one, from
        the robot's map hint."""
        if ref is not None:
            T_ref_key = invert(self._client[ref]) @ self._client[key]
            if key[0] in self._scale_drift:
                self._log_scale[key] = s = self._log_scale.get(ref, 0.0)
                T_ref_key = scale_translation(T_ref_key, float(np.exp(s)))
            self._values[key] = self._values[ref] @ T_ref_key
        else:
            self._values[key] = self._map_hint.get(key[0], np.eye(4)) @ self._client[key]
        self._fresh.add(key)

    def update_keyframe(self, map_id: int, keyframe_id: int, T_map_cam: np.ndarray) -> None:
        """The client's local BA moved a keyframe: every odometry / covisible factor touching it is
        rebuilt from the new client pose (loop and merge constraints are camera-to-camera and stay).
        An optimised estimate is left alone (the new measurements act at the next optimisation),
        except for one no optimisation has seen yet and for the robot's newest keyframe when only
        its client factors hold it: those are chained again from the predecessor. A client's first
        pose of a keyframe (from tracking) can sit centimetres off the local-BA poses of the
        keyframes before it, which the chain would otherwise carry into the team map until the next
        optimisation -- at the end of a run, for good."""
        key = self._check_key(map_id, keyframe_id)
        self._client[key] = self._pose(
            T_map_cam, f"pose of keyframe {keyframe_id} of robot " f"{map_id}"
        )
        chain = self._chain[map_id]
        newest_free = chain[-1] == keyframe_id and not any(
            self._factors[fid].kind in (KIND_LOOP, KIND_MERGE) for fid in self._by_key.get(key, ())
        )
        if key in self._fresh or newest_free:
            pos = chain.index(keyframe_id)
            ref = chain[pos - 1] if pos > 0 else (chain[1] if len(chain) > 1 else None)
            self._chain_estimate(key, None if ref is None else (map_id, ref))
        self._refined.pop(key, None)
        for fid in list(self._by_key.get(key, ())):
            f = self._factors[fid]
            if f.kind in CLIENT_KINDS:
                self._drop_factor(fid)
                self._client_factor(f.kind, f.key_i, f.key_j)

    def remove_keyframe(self, map_id: int, keyframe_id: int) -> None:
        """The client culled a keyframe: its neighbours are linked by odometry, loop / merge
        constraints on it move to the previous (else next) keyframe with their measurement composed
        with the client's relative pose, and its own odometry / covisible factors go."""
        key = self._check_key(map_id, keyframe_id)
        chain = self._chain[key[0]]
        pos = chain.index(key[1])
        prev = (key[0], chain[pos - 1]) if pos > 0 else None
        nxt = (key[0], chain[pos + 1]) if pos + 1 < len(chain) else None
        anchor = prev or nxt
        for fid in list(self._by_key.get(key, ())):
            f = self._drop_factor(fid)
            if f.kind not in (KIND_LOOP, KIND_MERGE) or anchor is None:
                continue  # priors are re-created on the new first keyframe by _sync_priors
            T_anchor_k = invert(self._client[anchor]) @ self._client[key]
            if f.key_i == key:  # X_j = X_k T = X_anchor T_anchor_k T
                key_i, key_j, T = anchor, f.key_j, T_anchor_k @ f.T_meas
            else:  # T = X_i^-1 X_k = X_i^-1 X_anchor T_anchor_k, T in i's lengths: j's times s
                T_anchor_k = scale_translation(T_anchor_k, float(np.exp(f.log_scale)))
                key_i, key_j, T = f.key_i, anchor, f.T_meas @ invert(T_anchor_k)
            if key_i != key_j:
                self._add_factor(replace(f, key_i=key_i, key_j=key_j, T_meas=T))
        if prev is not None and nxt is not None:
            self._client_factor(KIND_ODOMETRY, prev, nxt)
        chain.pop(pos)
        del self._values[key], self._client[key]
        self._log_scale.pop(key, None)
        self._fresh.discard(key)
        self._refined.pop(key, None)
        self._by_key.pop(key, None)
        self._priors.pop(key, None)
        self._scale_priors.pop(key, None)
        # iSAM2 cannot drop a variable: rebuild it at the next optimisation.
        self._rebuild = True

    def adopt_estimates(self, poses: dict, components: dict | None = None) -> None:
        """Take refined keyframe poses (e.g. from global bundle adjustment) as the new estimate
        *and* as the measurement of the odometry / covisible factors between two keyframes refined
        together (in one call, and the same of its ``components`` when given: key -> label), so
        later optimizations keep the refinement instead of pulling back to the client's poses.
        Factors to keyframes that were not refined together keep the client's relative pose, and
        a client update of a keyframe (local BA) drops its refinement."""
        self._refinements += 1
        for key, T in poses.items():
            # No components: all refined together; a key given none: refined with no other.
            label = 0 if components is None else components.get(tuple(key), ("alone", tuple(key)))
            key = self._check_key(*key)
            T = self._pose(T, f"refined pose of keyframe {key[1]} of robot {key[0]}")
            self._values[key] = T
            self._refined[key] = (T, (self._refinements, label))
        for fid in {fid for key in poses for fid in self._by_key.get(tuple(key), ())}:
            f = self._factors[fid]
            if f.kind in CLIENT_KINDS:
                self._drop_factor(fid)
                self._client_factor(f.kind, f.key_i, f.key_j)
        self._rebuild = True

    def rescale_robots(self, robots, factor: float, about_maps: bool = False) -> None:
        """The robots' map lengths were multiplied by ``factor`` (a monocular map's scale, see
        :mod:`.map_scale`): client poses, refined poses and estimates follow, client factors are
        rebuilt, loop and merge factors measured in a rescaled map's lengths scale with them (and
        the scale of a similarity to a map not rescaled follows).

        ``about_maps=False``: the robots are whole components (a group before it merges) whose
        group frame is rescaled about its origin, an exact similarity of the estimate.
        ``about_maps=True``: each robot's map is rescaled about its place in the group (its
        ``T_group_map``) while the rest of the group stays; merge factors between two such
        maps stay. The next optimisation is a full one."""
        robots = {int(r) for r in robots}
        centers = {r: self.T_group_map(r) for r in robots if about_maps and r in self._chain}

        def moved(T: np.ndarray, robot: int) -> np.ndarray:
            if not about_maps:
                return scale_translation(T, factor)
            C = centers[robot]
            return C @ scale_translation(invert(C) @ T, factor)

        for key in [k for k in self._values if k[0] in robots]:
            self._client[key] = scale_translation(self._client[key], factor)
            self._values[key] = moved(self._values[key], key[0])
            if key in self._refined:
                T, origin = self._refined[key]
                self._refined[key] = (moved(T, key[0]), origin)
        if not about_maps:
            for r in robots & set(self._map_hint):
                self._map_hint[r] = scale_translation(self._map_hint[r], factor)
        log_f = float(np.log(factor))
        for fid, f in list(self._factors.items()):
            in_i = f.key_i[0] in robots
            in_j = f.key_j is not None and f.key_j[0] in robots
            if f.kind in CLIENT_KINDS:
                if in_i:
                    self._drop_factor(fid)
                    self._client_factor(f.kind, f.key_i, f.key_j)
            elif f.kind == KIND_PRIOR:
                if in_i:
                    f.T_meas = self._values[f.key_i].copy()
            elif f.kind == KIND_SCALE_PRIOR:
                continue
            elif in_i and in_j and about_maps and f.kind == KIND_MERGE:
                # Two maps rescaled each about its place: their relative pose, measured in the
                # group's units, and the ratio of their lengths stay.
                continue
            else:
                # The measurement is in i's lengths and its scale is j's lengths in i's.
                if in_i:
                    f.T_meas = scale_translation(f.T_meas, factor)
                    f.sigmas = (f.sigmas[0], f.sigmas[1] * factor)
                f.log_scale += (log_f if in_i else 0.0) - (log_f if in_j else 0.0)
        self._rebuild = True

    def set_scale_drift(self, map_id: int, on: bool) -> None:
        """Whether a robot's map may drift in scale (a monocular map, see :mod:`.scale_drift`);
        off by config (``scale_drift``). Turning it off keeps the local
        scales the optimizations found in the estimate, not in later measurements."""
        map_id = int(map_id)
        on = bool(on) and self.config.scale_drift
        if on == (map_id in self._scale_drift):
            return
        if on:
            self._scale_drift.add(map_id)
        else:
            self._scale_drift.discard(map_id)
            for k in [k for k in self._log_scale if k[0] == map_id]:
                del self._log_scale[k]
        self._rebuild = True

    def local_scale(self, map_id: int, keyframe_id: int) -> float:
        """A keyframe's map lengths in the graph against its map's (1 unless its scale drifts)."""
        return float(np.exp(self._log_scale.get(self._check_key(map_id, keyframe_id), 0.0)))

    # --- constraints ------------------------------------------------------------------------------
    def add_loop(
        self,
        map_id: int,
        kf_i: int,
        kf_j: int,
        T_cami_camj: np.ndarray,
        kind: str = KIND_LOOP,
        rot_sigma_rad: float | None = None,
        trans_sigma_m: float | None = None,
        robust_k: float | None = None,
        log_scale: float | None = None,
        log_scale_sigma: float | None = None,
    ) -> int:
        """Intra-robot loop closure ``T_cami_camj`` (robust); ``kind`` is a label kept for reports,
        ``robust_k`` overrides the config's kernel width for this factor. ``log_scale``: for a
        loop measured by a similarity, the log of its scale (j's map lengths in i's), with
        ``log_scale_sigma`` (default: the config's ``link_scale_sigma``); it measures the drift
        of a monocular map's scale around the loop (None: no scale measured). Returns the
        constraint's factor id (for :meth:`remove_constraint`)."""
        key_i, key_j = self._check_key(map_id, kf_i), self._check_key(map_id, kf_j)
        if key_i == key_j:
            raise PoseGraphError(f"a loop needs two different keyframes (got {kf_i} twice)")
        T = self._pose(T_cami_camj, "T_cami_camj")
        sig = self._sigmas(
            rot_sigma_rad,
            trans_sigma_m,
            self.config.loop_rot_sigma_rad,
            self.config.loop_trans_sigma_m,
        )
        ls, ls_sig = self._link_scale(log_scale, log_scale_sigma)
        return self._add_factor(Factor(KIND_LOOP, key_i, key_j, T, sig, kind, robust_k, ls, ls_sig))

    def add_merge(
        self,
        robot_a: int,
        kf_a: int,
        robot_b: int,
        kf_b: int,
        T_camA_camB: np.ndarray,
        kind: str = KIND_MERGE,
        rot_sigma_rad: float | None = None,
        trans_sigma_m: float | None = None,
        robust_k: float | None = None,
        log_scale: float | None = None,
        log_scale_sigma: float | None = None,
    ) -> int:
        """Inter-robot constraint ``T_camA_camB`` (robust). When it joins two groups, the group
        whose smallest robot id is larger is moved rigidly into the other's frame so that this
        constraint holds exactly at the current estimate (the first merge of two groups is the
        verified one); the next optimisation is then a full one. ``log_scale`` (b's map lengths
        in a's) and ``log_scale_sigma`` as for :meth:`add_loop`. Returns the factor id."""
        key_a, key_b = self._check_key(robot_a, kf_a), self._check_key(robot_b, kf_b)
        if key_a[0] == key_b[0]:
            raise PoseGraphError("a merge constraint joins two different robots; use add_loop")
        T_ab = self._pose(T_camA_camB, "T_camA_camB")
        sig = self._sigmas(
            rot_sigma_rad,
            trans_sigma_m,
            self.config.merge_rot_sigma_rad,
            self.config.merge_trans_sigma_m,
        )
        comp = self._component_labels()
        ca, cb = comp[key_a], comp[key_b]
        if ca != cb:
            robots_a = {k[0] for k, c in comp.items() if c == ca}
            robots_b = {k[0] for k, c in comp.items() if c == cb}
            Xa, Xb = self._values[key_a], self._values[key_b]
            if min(robots_b) > min(robots_a):
                moving, T_new_old = cb, Xa @ T_ab @ invert(Xb)
            else:
                moving, T_new_old = ca, Xb @ invert(T_ab) @ invert(Xa)
            for k, c in comp.items():
                if c == moving:
                    self._values[k] = T_new_old @ self._values[k]
            self._rebuild = True
        ls, ls_sig = self._link_scale(log_scale, log_scale_sigma)
        return self._add_factor(
            Factor(KIND_MERGE, key_a, key_b, T_ab, sig, kind, robust_k, ls, ls_sig)
        )

    def remove_constraint(self, factor_id: int) -> None:
        """Withdraw a loop / merge constraint (e.g. rejected later by the caller)."""
        f = self._factors.get(factor_id)
        if f is None or f.kind not in (KIND_LOOP, KIND_MERGE):
            raise PoseGraphError(f"{factor_id} is not a loop or merge constraint of the graph")
        self._drop_factor(factor_id)

    # --- gauge ------------------------------------------------------------------------------------
    def _component_labels(self) -> dict[KeyframeKey, int]:
        """Connected component of every keyframe over the between factors."""
        keys = list(self._values)
        if not keys:
            return {}
        index = {k: i for i, k in enumerate(keys)}
        edges = np.array(
            [
                (index[f.key_i], index[f.key_j])
                for f in self._factors.values()
                if f.key_j is not None
            ],
            dtype=int,
        ).reshape(-1, 2)
        adj = coo_matrix(
            (np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(keys), len(keys))
        )
        _, labels = connected_components(adj, directed=False)
        return dict(zip(keys, labels.tolist()))

    def _sync_priors(self) -> bool:
        """One gauge prior per component (first keyframe of its smallest robot); returns True if a
        prior had to be removed or moved (iSAM2 cannot follow: rebuild)."""
        comp = self._component_labels()
        anchors: dict[int, KeyframeKey] = {}
        for k, c in comp.items():
            a = anchors.get(c)
            if a is None or k < a:  # (robot, keyframe) order: smallest robot, then first keyframe
                anchors[c] = k
        s = self.config.prior_sigma
        removed = self._sync_anchored(
            self._priors,
            set(anchors.values()),
            lambda k: Factor(KIND_PRIOR, k, None, self._values[k].copy(), (s, s)),
        )
        # A drifting map's scale: held at its first keyframe.
        s_scale = self.config.scale_prior_sigma
        return (
            self._sync_anchored(
                self._scale_priors,
                {(r, self._chain[r][0]) for r in self._scale_drift if self._chain.get(r)},
                lambda k: Factor(KIND_SCALE_PRIOR, k, None, None, (s_scale, s_scale)),
            )
            or removed
        )

    def _sync_anchored(
        self, priors: dict[KeyframeKey, int], wanted: set[KeyframeKey], make
    ) -> bool:
        """Prior factors (anchor keyframe -> factor id) on exactly the ``wanted`` keyframes, new
        ones from ``make(key)``; True if one had to go."""
        gone = [k for k in priors if k not in wanted]
        for k in gone:
            self._drop_factor(priors.pop(k))
        for k in wanted - set(priors):
            priors[k] = self._add_factor(make(k))
        return bool(gone)

    # --- optimisation -----------------------------------------------------------------------------
    def _graph(self, fids) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        for fid in fids:
            graph.add(self._gtsam_factor(fid))
        return graph

    def _gtsam_values(self, keys) -> gtsam.Values:
        values = gtsam.Values()
        for k in keys:
            values.insert(gtsam_key(*k), gtsam.Pose3(self._values[k]))
            if k[0] in self._scale_drift:
                values.insert(scale_key(*k), float(self._log_scale.get(k, 0.0)))
        return values

    def _read_log_scales(self, values: gtsam.Values) -> dict[KeyframeKey, float]:
        """The drifting maps' log scales of an optimizer's result; RuntimeError if one is not
        finite (as :func:`finite_poses`)."""
        out = {}
        for k in self._values:
            if k[0] in self._scale_drift:
                out[k] = float(values.atDouble(scale_key(*k)))
                if not np.isfinite(out[k]):
                    raise RuntimeError(f"the result holds a non-finite scale (keyframe {k})")
        return out

    def optimize_full(self) -> OptimizationStats:
        """Batch Levenberg-Marquardt over the whole graph from the current estimate (after a merge
        or loop closure). iSAM2 is re-initialised from the result at the next incremental call.
        Raises PoseGraphError, with the estimate left as it was, when the optimizer fails."""
        t0 = time.perf_counter()
        self._sync_priors()
        fids = list(self._factors)
        graph = self._graph(fids)
        initial = self._gtsam_values(self._values)
        stats = OptimizationStats("full", variables=len(self._values), factors=len(fids))
        if fids:
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(self.config.lm_max_iterations)
            params.setRelativeErrorTol(self.config.lm_relative_error_tol)
            try:
                optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
                result = optimizer.optimize()
                stats.error_before = finite_error(graph.error(initial), "before")
                stats.error_after = finite_error(graph.error(result), "after")
                poses = finite_poses(result)
                log_scales = self._read_log_scales(result)
            except RuntimeError as exc:  # GTSAM's exceptions arrive as RuntimeError
                self._step_failed("full", exc)
            stats.iterations = int(optimizer.iterations())
            self._values.update(poses)
            self._log_scale.update(log_scales)
        self._fresh.clear()
        self._reset_isam()
        self._rebuild = False
        stats.time_ms = 1e3 * (time.perf_counter() - t0)
        self.stats = stats
        log.debug("pose graph full optimisation: %s", stats)
        return stats

    def optimize_incremental(self) -> OptimizationStats:
        """iSAM2 update with the factors and keyframes added since the last call. Falls back to
        :meth:`optimize_full` when the graph changed in a way iSAM2 cannot absorb. Raises
        PoseGraphError, with the estimate left as it was, when the optimizer fails."""
        t0 = time.perf_counter()
        if self._sync_priors() or self._rebuild:
            return self.optimize_full()
        if self._isam is None:
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(self.config.isam_relinearize_threshold)
            params.relinearizeSkip = self.config.isam_relinearize_skip
            params.evaluateNonlinearError = True
            self._isam = gtsam.ISAM2(params)
        new_fids = [fid for fid in self._factors if fid not in self._isam_index]
        new_keys = [k for k in self._values if k not in self._isam_keys]
        stats = OptimizationStats(
            "incremental", variables=len(self._values), factors=len(self._factors)
        )
        if new_fids or new_keys or self._isam_remove:
            try:
                result = self._isam.update(
                    self._graph(new_fids), self._gtsam_values(new_keys), list(self._isam_remove)
                )
                stats.error_before = finite_error(result.getErrorBefore(), "before")
                stats.error_after = finite_error(result.getErrorAfter(), "after")
                for _ in range(self.config.isam_extra_updates):
                    stats.error_after = finite_error(self._isam.update().getErrorAfter(), "after")
                estimate = self._isam.calculateEstimate()
                poses = finite_poses(estimate)
                log_scales = self._read_log_scales(estimate)
            except RuntimeError as exc:
                self._step_failed("incremental", exc)
            for fid, slot in zip(new_fids, result.getNewFactorsIndices()):
                self._isam_index[fid] = int(slot)
            self._isam_keys.update(new_keys)
            self._fresh.difference_update(new_keys)
            self._isam_remove.clear()
            stats.iterations = 1 + self.config.isam_extra_updates
            self._values.update(poses)
            self._log_scale.update(log_scales)
        stats.time_ms = 1e3 * (time.perf_counter() - t0)
        self.stats = stats
        return stats

    def _reset_isam(self) -> None:
        self._isam = None
        self._isam_index.clear()
        self._isam_keys.clear()
        self._isam_remove.clear()

    def _step_failed(self, mode: str, exc: Exception) -> NoReturn:
        """A failed optimizer step leaves the graph as it was before the step: the estimate is only
        written after success, and iSAM2, which may hold half of the step (GTSAM inserts the new
        variables before it solves: every later update would fail with "key already exists"), is
        dropped and rebuilt from the factor list by the next call, a full optimisation."""
        self._reset_isam()
        self._rebuild = True
        cause = " ".join(str(exc).split())  # GTSAM's messages span several lines
        raise PoseGraphError(
            f"{mode} optimisation failed, estimate kept as before the step (the next call "
            f"rebuilds the optimizer from the factors): {cause}"
        ) from None

    # --- results ----------------------------------------------------------------------------------
    @property
    def robots(self) -> list[int]:
        return sorted(set(self._chain) | set(self._map_hint))

    def keyframe_ids(self, map_id: int) -> list[int]:
        self._check_robot(map_id)
        return list(self._chain.get(map_id, []))

    def T_group_cam(self, map_id: int, keyframe_id: int) -> np.ndarray:
        """Current estimate of a keyframe's pose in its group frame."""
        return self._values[self._check_key(map_id, keyframe_id)].copy()

    def keyframe_poses(self, map_id: int) -> dict[int, np.ndarray]:
        """keyframe id -> T_group_cam for one robot."""
        self._check_robot(map_id)
        return {k: self._values[(map_id, k)].copy() for k in self._chain.get(map_id, [])}

    def T_group_map(self, map_id: int) -> np.ndarray:
        """A robot's map frame in its group frame, i.e. the map->odom style correction its client
        applies. ``map_anchor='latest'`` (default) anchors it at the robot's latest keyframe, where
        the robot is now, so its corrected current pose is the optimised one; ``'umeyama'`` is the
        least-squares rigid fit of client to optimised keyframe positions (falls back to 'latest'
        for fewer than 3 or collinear keyframes). Without keyframes: the hint (or identity)."""
        self._check_robot(map_id)
        chain = self._chain.get(map_id, [])
        if not chain:
            return self._map_hint.get(map_id, np.eye(4)).copy()
        if self.config.map_anchor == "umeyama" and len(chain) >= 3:
            keys = [(map_id, k) for k in chain]
            points_map = np.array([self._client[k][:3, 3] for k in keys])
            points_group = np.array([self._values[k][:3, 3] for k in keys])
            try:
                return umeyama(points_map, points_group)[0]
            except RegistrationError:
                pass
        last = (map_id, chain[-1])
        return self._values[last] @ invert(self._client[last])

    def components(self) -> list[list[int]]:
        """Robots grouped by connected component of the graph (robots without keyframes alone)."""
        comp = self._component_labels()
        groups: dict[int, set[int]] = {}
        for (rid, _), c in comp.items():
            groups.setdefault(c, set()).add(rid)
        out = [sorted(g) for g in groups.values()]
        out += [[r] for r in self.robots if r not in self._chain or not self._chain[r]]
        return sorted(out)

    def constraint_report(self) -> list[ConstraintStatus]:
        """Residual and robust weight of every loop / merge constraint at the current estimate:
        a wrong constraint shows a large whitened error and a weight near 0."""
        out = []
        for fid, f in self._factors.items():
            if f.kind not in (KIND_LOOP, KIND_MERGE):
                continue
            values = self._gtsam_values((f.key_i, f.key_j))
            e = np.asarray(self._gtsam_factor(fid).unwhitenedError(values), float)
            scale_row = len(e) == 7
            sigmas = pose_sigmas(*f.sigmas, *([f.scale_sigma] if scale_row else []))
            d = float(np.linalg.norm(e / sigmas))
            kernel = self._kernel_of(f)
            w = float(kernel.weight(d)) if kernel is not None else 1.0
            out.append(ConstraintStatus(fid, f.kind, f.label, f.key_i, f.key_j, d, w, scale_row))
        return out
