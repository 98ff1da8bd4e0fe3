"""Team pose graph: one GTSAM factor graph over the keyframes of every robot.

Parameterisation
----------------
One variable per keyframe, ``X = T_group_cam``: the camera pose in its *group frame*. A group is a
connected component of the graph (robots joined by merge factors); its frame is the map frame of
its smallest robot id, matching :mod:`coop_slam.team.groups`, so the component holding robot 1 is
``world``. Variable keys are ``gtsam.Symbol(chr(ord('a') + robot_id), keyframe_id)``, so all robots
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
from dataclasses import dataclass, field, replace
from typing import NoReturn

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..config import require
from ..errors import CoopSlamError, GeometryError
from ..geometry import check_se3, exp_so3, invert
from ..registration.camera import RegistrationError
from ..registration.umeyama import umeyama
from .map_scale import scale_translation
from .scale_drift import (
    SCALE_BIT,
    is_scale_key,
    pose_sigmas,
    scale_key,
    scale_prior_factor,
    scaled_between_factor,
    scaled_link_factor,
)

log = logging.getLogger(__name__)

KIND_ODOMETRY = "odometry"
KIND_COVISIBLE = "covisible"
KIND_LOOP = "loop"
KIND_MERGE = "merge"
KIND_PRIOR = "prior"
KIND_SCALE_PRIOR = "scale_prior"  # a drifting map's scale at its first keyframe
_CLIENT_KINDS = (KIND_ODOMETRY, KIND_COVISIBLE)  # measured from the client's poses
_ROBUST_KERNELS = ("huber", "cauchy", "none")
_MAP_ANCHORS = ("latest", "umeyama")
_MAX_ROBOT_ID = 255 - ord("a")  # gtsam.Symbol holds one byte for the character
_MAX_KEYFRAME_ID = SCALE_BIT - 1  # and 56 bits for the index, the top one for scale variables

Key = tuple[int, int]  # (robot_id, keyframe_id)


class PoseGraphError(CoopSlamError):
    """Unknown keyframe or robot, duplicate keyframe, or invalid constraint for the pose graph."""


@dataclass
class PoseGraphConfig:
    odom_rot_sigma_rad: float = 0.005  # odometry between neighbouring keyframes ...
    odom_trans_sigma_m: float = 0.01
    odom_rot_sigma_per_m: float = 0.005  # ... plus this much per metre between them
    odom_trans_sigma_per_m: float = 0.02
    max_covisible_factors: int = 3  # extra client-pose factors per keyframe to covisible ones
    loop_rot_sigma_rad: float = 0.02
    loop_trans_sigma_m: float = 0.05
    merge_rot_sigma_rad: float = 0.02
    merge_trans_sigma_m: float = 0.05
    robust_kernel: str = "cauchy"  # huber | cauchy | none, for loop and merge factors
    # On the whitened 6-D residual norm: an inlier's norm is about sqrt(6) = 2.4.
    robust_k: float = 3.0
    prior_sigma: float = 1e-4  # gauge prior [rad and m]
    map_anchor: str = "latest"  # how T_group_map is read off the optimised poses: latest | umeyama
    lm_max_iterations: int = 100
    lm_relative_error_tol: float = 1e-5
    isam_relinearize_threshold: float = 0.01
    isam_relinearize_skip: int = 1
    isam_extra_updates: int = 1  # extra iSAM2 iterations per incremental call
    # Monocular maps (see set_scale_drift and .scale_drift): a log-scale variable per keyframe;
    # the drift between two keyframes has sigma scale_drift_sigma plus scale_drift_sigma_per_m
    # per metre between them; the map's first keyframe is held at the map's own scale with
    # scale_prior_sigma; a loop or link's measured scale has log sigma link_scale_sigma unless
    # its caller gives one.
    scale_drift: bool = True
    scale_drift_sigma: float = 0.002
    scale_drift_sigma_per_m: float = 0.1
    scale_prior_sigma: float = 0.1
    link_scale_sigma: float = 0.05

    def validate(self) -> None:
        for name in (
            "odom_rot_sigma_rad",
            "odom_trans_sigma_m",
            "loop_rot_sigma_rad",
            "loop_trans_sigma_m",
            "merge_rot_sigma_rad",
            "merge_trans_sigma_m",
            "prior_sigma",
            "robust_k",
            "scale_drift_sigma",
            "scale_prior_sigma",
            "link_scale_sigma",
        ):
            require(getattr(self, name) > 0, f"pose_graph.{name} must be > 0")
        for name in ("odom_rot_sigma_per_m", "odom_trans_sigma_per_m", "scale_drift_sigma_per_m"):
            require(getattr(self, name) >= 0, f"pose_graph.{name} must be >= 0")
        require(self.max_covisible_factors >= 0, "pose_graph.max_covisible_factors must be >= 0")
        require(
            self.robust_kernel in _ROBUST_KERNELS,
            f"pose_graph.robust_kernel must be one of {', '.join(_ROBUST_KERNELS)}",
        )
        require(
            self.map_anchor in _MAP_ANCHORS,
            f"pose_graph.map_anchor must be one of {', '.join(_MAP_ANCHORS)}",
        )
        require(self.lm_max_iterations >= 1, "pose_graph.lm_max_iterations must be >= 1")
        require(self.lm_relative_error_tol > 0, "pose_graph.lm_relative_error_tol must be > 0")
        require(
            self.isam_relinearize_threshold > 0, "pose_graph.isam_relinearize_threshold must be > 0"
        )
        require(self.isam_relinearize_skip >= 1, "pose_graph.isam_relinearize_skip must be >= 1")
        require(self.isam_extra_updates >= 0, "pose_graph.isam_extra_updates must be >= 0")


@dataclass
class OptimizationStats:
    mode: str = "none"  # none | incremental | full
    time_ms: float = 0.0  # wall time of the whole call (graph building included)
    iterations: int = 0
    error_before: float = 0.0  # factor-graph error (robust loss for robust factors)
    error_after: float = 0.0
    variables: int = 0
    factors: int = 0


@dataclass
class ConstraintStatus:
    """How well the current estimate agrees with one loop / merge constraint."""

    factor_id: int
    kind: str  # loop | merge
    label: str  # caller's label (e.g. place_recognition, rendezvous)
    key_i: Key
    key_j: Key
    whitened_error: float  # Mahalanobis norm of the residual (6-D, 7-D with a scale row)
    weight: float  # robust-kernel weight at that residual (1 = fully trusted)
    scale_row: bool = False  # its similarity's scale is in the graph (a drifting map's end)


@dataclass
class _Factor:
    kind: str
    key_i: Key
    key_j: Key | None  # None for a prior
    T_meas: np.ndarray  # T_cami_camj (between) or T_group_cam (prior)
    sigmas: tuple[float, float]  # (rotation rad, translation m)
    label: str = ""
    robust_k: float | None = None  # per-factor kernel width (whitened); None: the config's
    # A loop / merge measured by a similarity: log of key_j's map lengths in key_i's (T_meas's
    # translation is in key_i's) and its sigma (None: not measured); used where an end's scale
    # may drift.
    log_scale: float = 0.0
    scale_sigma: float | None = None


def gtsam_key(robot_id: int, keyframe_id: int) -> int:
    """Graph key of a keyframe: one symbol character per robot, so all robots share one graph."""
    return gtsam.Symbol(chr(ord("a") + robot_id), keyframe_id).key()


def _key_of(gkey: int) -> Key:
    s = gtsam.Symbol(gkey)
    return s.chr() - ord("a"), s.index()


def _poses_from_values(values: gtsam.Values) -> dict[Key, np.ndarray]:
    """All Pose3 values as 4x4 arrays, converted in one call (rows follow the key order)."""
    keys = [_key_of(k) for k in values.keys() if not is_scale_key(k)]  # noqa: SIM118 (not iterable)
    rows = gtsam.utilities.extractPose3(values)
    T = np.tile(np.eye(4), (len(keys), 1, 1))
    T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = rows[:, 9:]
    return dict(zip(keys, T))


def _finite_error(error: float | None, when: str) -> float:
    """A factor-graph error as a float; RuntimeError if it is NaN or inf (a keyframe or constraint
    with absurd values: Levenberg-Marquardt then returns its start unchanged, without throwing)."""
    error = float(error or 0.0)
    if not np.isfinite(error):
        raise RuntimeError(f"the graph's error {when} the step is {error}")
    return error


def _finite_poses(values: gtsam.Values) -> dict[Key, np.ndarray]:
    """The poses of an optimizer's result; RuntimeError if any is NaN or inf (an optimizer can
    diverge without throwing, e.g. from a pose of 1e300 m)."""
    poses = _poses_from_values(values)
    bad = [k for k, T in poses.items() if not np.all(np.isfinite(T))]
    if bad:
        raise RuntimeError(
            f"the result holds non-finite poses ({len(bad)}, e.g. keyframe {bad[0][1]} of robot "
            f"{bad[0][0]})"
        )
    return poses


class TeamPoseGraph:
    """Keyframe pose graph of the whole team; see the module docstring for the model."""

    def __init__(self, config: PoseGraphConfig | None = None):
        self.config = config or PoseGraphConfig()
        self.config.validate()
        cfg = self.config
        self._kernel = self._make_kernel(cfg.robust_k)
        self._client: dict[Key, np.ndarray] = {}  # T_map_cam as the client last sent it
        self._fresh: set[Key] = set()  # keyframes no optimisation has seen yet
        # Pose from global BA, until the client moves it, and which refinement it came from
        # (a run and a component of it: poses are refined against each other only within one).
        self._refined: dict[Key, tuple[np.ndarray, tuple]] = {}
        self._refinements = 0
        self._values: dict[Key, np.ndarray] = {}  # current estimate T_group_cam
        # Monocular maps whose scale may drift (see set_scale_drift): keyframe -> log scale
        self._scale_drift: set[int] = set()
        self._log_scale: dict[Key, float] = {}
        self._chain: dict[int, list[int]] = {}  # robot -> sorted keyframe ids
        self._map_hint: dict[int, np.ndarray] = {}  # T_group_map for a robot's first keyframe
        self._factors: dict[int, _Factor] = {}
        self._gtsam_cache: dict[int, tuple] = {}  # factor id -> (T_meas, sigmas, GTSAM factor)
        self._by_key: dict[Key, set[int]] = {}
        self._priors: dict[Key, int] = {}  # anchor keyframe -> prior factor id
        self._scale_priors: dict[Key, int] = {}  # a drifting map's first keyframe -> factor id
        self._next_fid = 0
        # iSAM2 state: factor id -> iSAM2 slot, keys it holds, slots to remove at the next update.
        self._isam: gtsam.ISAM2 | None = None
        self._isam_index: dict[int, int] = {}
        self._isam_keys: set[Key] = set()
        self._isam_remove: list[int] = []
        self._rebuild = False  # iSAM2 cannot absorb the last changes: next call is a full one
        self.stats = OptimizationStats()

    # --- checks -----------------------------------------------------------------------------------
    @staticmethod
    def _pose(T, name: str) -> np.ndarray:
        try:
            return check_se3(T, name)
        except GeometryError as exc:
            raise PoseGraphError(str(exc)) from None

    def _check_key(self, robot_id: int, keyframe_id: int) -> Key:
        key = (int(robot_id), int(keyframe_id))
        if key not in self._values:
            raise PoseGraphError(
                f"keyframe {keyframe_id} of robot {robot_id} is not in the pose "
                "graph (add it with add_keyframe first)"
            )
        return key

    def _check_robot(self, robot_id: int) -> None:
        if robot_id not in self._chain and robot_id not in self._map_hint:
            raise PoseGraphError(
                f"robot {robot_id} is unknown to the pose graph " f"(known: {self.robots})"
            )

    # --- factor bookkeeping -----------------------------------------------------------------------
    def _add_factor(self, f: _Factor) -> int:
        fid = self._next_fid
        self._next_fid += 1
        self._factors[fid] = f
        for k in (f.key_i, f.key_j):
            if k is not None:
                self._by_key.setdefault(k, set()).add(fid)
        return fid

    def _drop_factor(self, fid: int) -> _Factor:
        f = self._factors.pop(fid)
        self._gtsam_cache.pop(fid, None)
        for k in (f.key_i, f.key_j):
            if k is not None and k in self._by_key:
                self._by_key[k].discard(fid)
        slot = self._isam_index.pop(fid, None)
        if slot is not None:
            self._isam_remove.append(slot)
        return f

    def _client_factor(self, kind: str, key_i: Key, key_j: Key) -> int:
        """Odometry-type factor from the client's current poses of two keyframes of one robot (from
        the refined poses when both were refined together, see :meth:`adopt_estimates`)."""
        cfg = self.config
        ref_i, ref_j = self._refined.get(key_i), self._refined.get(key_j)
        if ref_i is not None and ref_j is not None and ref_i[1] == ref_j[1]:
            T_i_j = invert(ref_i[0]) @ ref_j[0]
            if key_i[0] in self._scale_drift:
                # Refined poses hold the local scale; the factor applies it to map units.
                s = 0.5 * (self._log_scale.get(key_i, 0.0) + self._log_scale.get(key_j, 0.0))
                T_i_j = scale_translation(T_i_j, float(np.exp(-s)))
        else:
            T_i_j = invert(self._client[key_i]) @ self._client[key_j]
        dist_m = float(np.linalg.norm(T_i_j[:3, 3]))
        sigmas = (
            cfg.odom_rot_sigma_rad + cfg.odom_rot_sigma_per_m * dist_m,
            cfg.odom_trans_sigma_m + cfg.odom_trans_sigma_per_m * dist_m,
        )
        return self._add_factor(_Factor(kind, key_i, key_j, T_i_j, sigmas))

    def _make_kernel(self, k: float):
        if self.config.robust_kernel == "huber":
            return gtsam.noiseModel.mEstimator.Huber.Create(k)
        if self.config.robust_kernel == "cauchy":
            return gtsam.noiseModel.mEstimator.Cauchy.Create(k)
        return None

    def _kernel_of(self, f: _Factor):
        """The robust kernel of a factor: a loop / merge's (None: none, and for the others)."""
        if self._kernel is None or f.kind not in (KIND_LOOP, KIND_MERGE):
            return None
        return self._kernel if f.robust_k is None else self._make_kernel(f.robust_k)

    def _noise(self, f: _Factor):
        base = gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas(*f.sigmas))
        kernel = self._kernel_of(f)
        return base if kernel is None else gtsam.noiseModel.Robust.Create(kernel, base)

    def _gtsam_factor(self, fid: int):
        """The GTSAM factor of a factor id; kept until the factor goes or its measurement or
        sigmas are replaced (every optimization rebuilds the graph from them, and converting
        hundreds of factors each time was a tenth of an eight-robot server's time)."""
        f = self._factors[fid]
        cached = self._gtsam_cache.get(fid)
        version = (f.sigmas, f.robust_k, self._drifts(f), self._link_drifts(f), f.log_scale)
        if cached is not None and cached[0] is f.T_meas and cached[1] == version:
            return cached[2]
        factor = self._make_gtsam_factor(f)
        self._gtsam_cache[fid] = (f.T_meas, version, factor)
        return factor

    def _drifts(self, f: _Factor) -> bool:
        """Whether a factor is a client factor of a map whose scale may drift."""
        return f.kind in _CLIENT_KINDS and f.key_i[0] in self._scale_drift

    def _link_drifts(self, f: _Factor) -> tuple[bool, bool]:
        """For a loop / merge factor, whether the scale of each end's map may drift."""
        if f.kind not in (KIND_LOOP, KIND_MERGE):
            return (False, False)
        return (f.key_i[0] in self._scale_drift, f.key_j[0] in self._scale_drift)

    def _make_gtsam_factor(self, f: _Factor):
        drift_i, drift_j = self._link_drifts(f)
        if drift_i or drift_j:
            return scaled_link_factor(
                gtsam_key(*f.key_i),
                gtsam_key(*f.key_j),
                scale_key(*f.key_i) if drift_i else None,
                scale_key(*f.key_j) if drift_j else None,
                f.T_meas,
                None if f.scale_sigma is None else f.log_scale,
                *f.sigmas,
                f.scale_sigma,
                self._kernel_of(f),
            )
        if self._drifts(f):
            cfg = self.config
            dist_m = float(np.linalg.norm(f.T_meas[:3, 3]))
            return scaled_between_factor(
                gtsam_key(*f.key_i),
                gtsam_key(*f.key_j),
                scale_key(*f.key_i),
                scale_key(*f.key_j),
                f.T_meas,
                *f.sigmas,
                cfg.scale_drift_sigma + cfg.scale_drift_sigma_per_m * dist_m,
            )
        if f.kind == KIND_SCALE_PRIOR:
            return scale_prior_factor(scale_key(*f.key_i), f.sigmas[0])
        noise = self._noise(f)
        if f.key_j is None:
            return gtsam.PriorFactorPose3(gtsam_key(*f.key_i), gtsam.Pose3(f.T_meas), noise)
        return gtsam.BetweenFactorPose3(
            gtsam_key(*f.key_i), gtsam_key(*f.key_j), gtsam.Pose3(f.T_meas), noise
        )

    def _odometry_between(self, key_i: Key, key_j: Key) -> list[int]:
        return [
            fid
            for fid in self._by_key.get(key_i, ())
            if self._factors[fid].kind == KIND_ODOMETRY
            and {self._factors[fid].key_i, self._factors[fid].key_j} == {key_i, key_j}
        ]

    # --- keyframes --------------------------------------------------------------------------------
    def set_map_transform(self, robot_id: int, T_group_map: np.ndarray) -> None:
        """Where a robot's map sits in its group frame, used for the initial estimate of the robot's
        first keyframe. Later keyframes chain from the robot's existing estimates, which already
        live in the graph's frame; merges align groups themselves (see :meth:`add_merge`)."""
        self._map_hint[int(robot_id)] = self._pose(T_group_map, f"T_group_map of robot {robot_id}")

    def add_keyframe(
        self,
        robot_id: int,
        keyframe_id: int,
        T_map_cam: np.ndarray,
        T_group_map: np.ndarray | None = None,
        covisible_ids=(),
    ) -> None:
        """Add a keyframe with its client pose; links it by odometry to its neighbours in id order
        (normally the robot's previous keyframe) and to up to ``max_covisible_factors`` of the
        given covisible keyframes of the same robot."""
        robot_id, keyframe_id = int(robot_id), int(keyframe_id)
        if not 0 <= robot_id <= _MAX_ROBOT_ID:
            raise PoseGraphError(f"robot id {robot_id} must be in [0, {_MAX_ROBOT_ID}]")
        if not 0 <= keyframe_id <= _MAX_KEYFRAME_ID:
            raise PoseGraphError(f"keyframe id {keyframe_id} must be in [0, 2^55)")
        key = (robot_id, keyframe_id)
        if key in self._values:
            raise PoseGraphError(
                f"keyframe {keyframe_id} of robot {robot_id} is already in the "
                "pose graph (use update_keyframe)"
            )
        T_map_cam = self._pose(T_map_cam, f"pose of keyframe {keyframe_id} of robot {robot_id}")
        if T_group_map is not None:
            self.set_map_transform(robot_id, T_group_map)
        chain = self._chain.setdefault(robot_id, [])
        pos = bisect.bisect_left(chain, keyframe_id)
        prev = (robot_id, chain[pos - 1]) if pos > 0 else None
        nxt = (robot_id, chain[pos]) if pos < len(chain) else None
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
            ckey = (robot_id, int(cid))
            if added >= self.config.max_covisible_factors:
                break
            if ckey in self._values and ckey not in (prev, nxt, key):
                self._client_factor(KIND_COVISIBLE, ckey, key)
                added += 1

    def _chain_estimate(self, key: Key, ref: Key | None) -> None:
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

    def update_keyframe(self, robot_id: int, keyframe_id: int, T_map_cam: np.ndarray) -> None:
        """The client's local BA moved a keyframe: every odometry / covisible factor touching it is
        rebuilt from the new client pose (loop and merge constraints are camera-to-camera and stay).
        An optimised estimate is left alone (the new measurements act at the next optimisation),
        except for one no optimisation has seen yet and for the robot's newest keyframe when only
        its client factors hold it: those are chained again from the predecessor. A client's first
        pose of a keyframe (from tracking) can sit centimetres off the local-BA poses of the
        keyframes before it, which the chain would otherwise carry into the team map until the next
        optimisation -- at the end of a run, for good."""
        key = self._check_key(robot_id, keyframe_id)
        self._client[key] = self._pose(
            T_map_cam, f"pose of keyframe {keyframe_id} of robot " f"{robot_id}"
        )
        chain = self._chain[robot_id]
        newest_free = chain[-1] == keyframe_id and not any(
            self._factors[fid].kind in (KIND_LOOP, KIND_MERGE) for fid in self._by_key.get(key, ())
        )
        if key in self._fresh or newest_free:
            pos = chain.index(keyframe_id)
            ref = chain[pos - 1] if pos > 0 else (chain[1] if len(chain) > 1 else None)
            self._chain_estimate(key, None if ref is None else (robot_id, ref))
        self._refined.pop(key, None)
        for fid in list(self._by_key.get(key, ())):
            f = self._factors[fid]
            if f.kind in _CLIENT_KINDS:
                self._drop_factor(fid)
                self._client_factor(f.kind, f.key_i, f.key_j)

    def remove_keyframe(self, robot_id: int, keyframe_id: int) -> None:
        """The client culled a keyframe: its neighbours are linked by odometry, loop / merge
        constraints on it move to the previous (else next) keyframe with their measurement composed
        with the client's relative pose, and its own odometry / covisible factors go."""
        key = self._check_key(robot_id, keyframe_id)
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
            if f.kind in _CLIENT_KINDS:
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
            if f.kind in _CLIENT_KINDS:
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

    def set_scale_drift(self, robot_id: int, on: bool) -> None:
        """Whether a robot's map may drift in scale (a monocular map, see :mod:`.scale_drift`);
        off by config (``scale_drift``). Turning it off keeps the local
        scales the optimizations found in the estimate, not in later measurements."""
        robot_id = int(robot_id)
        on = bool(on) and self.config.scale_drift
        if on == (robot_id in self._scale_drift):
            return
        if on:
            self._scale_drift.add(robot_id)
        else:
            self._scale_drift.discard(robot_id)
            for k in [k for k in self._log_scale if k[0] == robot_id]:
                del self._log_scale[k]
        self._rebuild = True

    def local_scale(self, robot_id: int, keyframe_id: int) -> float:
        """A keyframe's map lengths in the graph against its map's (1 unless its scale drifts)."""
        return float(np.exp(self._log_scale.get(self._check_key(robot_id, keyframe_id), 0.0)))

    # --- constraints ------------------------------------------------------------------------------
    def _sigmas(self, rot, trans, default_rot, default_trans) -> tuple[float, float]:
        sig = (
            default_rot if rot is None else float(rot),
            default_trans if trans is None else float(trans),
        )
        if not (sig[0] > 0 and sig[1] > 0):
            raise PoseGraphError(f"constraint sigmas must be > 0, got {sig}")
        return sig

    def add_loop(
        self,
        robot_id: int,
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
        key_i, key_j = self._check_key(robot_id, kf_i), self._check_key(robot_id, kf_j)
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
        return self._add_factor(
            _Factor(KIND_LOOP, key_i, key_j, T, sig, kind, robust_k, ls, ls_sig)
        )

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
            _Factor(KIND_MERGE, key_a, key_b, T_ab, sig, kind, robust_k, ls, ls_sig)
        )

    def _link_scale(self, log_scale, sigma) -> tuple[float, float | None]:
        """(log scale, its sigma) of a constraint's scale row; sigma None: no row."""
        if log_scale is None:
            return 0.0, None
        log_scale = float(log_scale)
        if not np.isfinite(log_scale):
            raise PoseGraphError(f"a constraint's log scale must be finite, got {log_scale}")
        sigma = self.config.link_scale_sigma if sigma is None else float(sigma)
        if not (np.isfinite(sigma) and sigma > 0):
            raise PoseGraphError(f"a constraint's log-scale sigma must be > 0, got {sigma}")
        return log_scale, sigma

    def remove_constraint(self, factor_id: int) -> None:
        """Withdraw a loop / merge constraint (e.g. rejected later by the caller)."""
        f = self._factors.get(factor_id)
        if f is None or f.kind not in (KIND_LOOP, KIND_MERGE):
            raise PoseGraphError(f"{factor_id} is not a loop or merge constraint of the graph")
        self._drop_factor(factor_id)

    # --- gauge ------------------------------------------------------------------------------------
    def _component_labels(self) -> dict[Key, int]:
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
        anchors: dict[int, Key] = {}
        for k, c in comp.items():
            a = anchors.get(c)
            if a is None or k < a:  # (robot, keyframe) order: smallest robot, then first keyframe
                anchors[c] = k
        s = self.config.prior_sigma
        removed = self._sync_anchored(
            self._priors,
            set(anchors.values()),
            lambda k: _Factor(KIND_PRIOR, k, None, self._values[k].copy(), (s, s)),
        )
        # A drifting map's scale: held at its first keyframe.
        s_scale = self.config.scale_prior_sigma
        return (
            self._sync_anchored(
                self._scale_priors,
                {(r, self._chain[r][0]) for r in self._scale_drift if self._chain.get(r)},
                lambda k: _Factor(KIND_SCALE_PRIOR, k, None, None, (s_scale, s_scale)),
            )
            or removed
        )

    def _sync_anchored(self, priors: dict[Key, int], wanted: set[Key], make) -> bool:
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

    def _read_log_scales(self, values: gtsam.Values) -> dict[Key, float]:
        """The drifting maps' log scales of an optimizer's result; RuntimeError if one is not
        finite (as :func:`_finite_poses`)."""
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
                stats.error_before = _finite_error(graph.error(initial), "before")
                stats.error_after = _finite_error(graph.error(result), "after")
                poses = _finite_poses(result)
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
                stats.error_before = _finite_error(result.getErrorBefore(), "before")
                stats.error_after = _finite_error(result.getErrorAfter(), "after")
                for _ in range(self.config.isam_extra_updates):
                    stats.error_after = _finite_error(self._isam.update().getErrorAfter(), "after")
                estimate = self._isam.calculateEstimate()
                poses = _finite_poses(estimate)
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

    def keyframe_ids(self, robot_id: int) -> list[int]:
        self._check_robot(robot_id)
        return list(self._chain.get(robot_id, []))

    def T_group_cam(self, robot_id: int, keyframe_id: int) -> np.ndarray:
        """Current estimate of a keyframe's pose in its group frame."""
        return self._values[self._check_key(robot_id, keyframe_id)].copy()

    def keyframe_poses(self, robot_id: int) -> dict[int, np.ndarray]:
        """keyframe id -> T_group_cam for one robot."""
        self._check_robot(robot_id)
        return {k: self._values[(robot_id, k)].copy() for k in self._chain.get(robot_id, [])}

    def T_group_map(self, robot_id: int) -> np.ndarray:
        """A robot's map frame in its group frame, i.e. the map->odom style correction its client
        applies. ``map_anchor='latest'`` (default) anchors it at the robot's latest keyframe, where
        the robot is now, so its corrected current pose is the optimised one; ``'umeyama'`` is the
        least-squares rigid fit of client to optimised keyframe positions (falls back to 'latest'
        for fewer than 3 or collinear keyframes). Without keyframes: the hint (or identity)."""
        self._check_robot(robot_id)
        chain = self._chain.get(robot_id, [])
        if not chain:
            return self._map_hint.get(robot_id, np.eye(4)).copy()
        if self.config.map_anchor == "umeyama" and len(chain) >= 3:
            keys = [(robot_id, k) for k in chain]
            points_map = np.array([self._client[k][:3, 3] for k in keys])
            points_group = np.array([self._values[k][:3, 3] for k in keys])
            try:
                return umeyama(points_map, points_group)[0]
            except RegistrationError:
                pass
        last = (robot_id, chain[-1])
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

    def edges(self, kind: str | None = None) -> list[tuple[str, Key, Key | None]]:
        """(kind, key_i, key_j) of every factor, optionally of one kind (for inspection / tests)."""
        return [
            (f.kind, f.key_i, f.key_j)
            for f in self._factors.values()
            if kind is None or f.kind == kind
        ]

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


# --- synthetic team and benchmark -----------------------------------------------------------------
@dataclass
class SyntheticTeam:
    """Ground truth, drifting client poses and constraints for pose-graph tests and benchmarks."""

    T_world_cam_gt: dict[int, np.ndarray]  # robot -> (N, 4, 4), keyframe ids 1..N
    T_map_cam: dict[int, np.ndarray]  # robot -> (N, 4, 4), client poses (map = first camera)
    loops: list[tuple[int, int, int, np.ndarray]] = field(default_factory=list)  # r, i, j, T
    merges: list[tuple[int, int, int, int, np.ndarray]] = field(default_factory=list)  # ra,i,rb,j,T


def synthetic_team(
    keyframes_per_robot: int = 60,
    robots: int = 3,
    seed: int = 0,
    odom_rot_noise_rad: float = 0.002,
    odom_trans_noise_m: float = 0.005,
    yaw_drift_rad: float = 0.003,
    meas_rot_noise_rad: float = 0.002,
    meas_trans_noise_m: float = 0.005,
    max_merges_per_pair: int = 6,
    loop_every: int = 4,
) -> SyntheticTeam:
    """Robots circling overlapping 4 m rings (one lap per 60 keyframes, camera looking ahead,
    gently bobbing in z); clients integrate noisy, yaw-drifting odometry from their first pose;
    loop / merge constraints come from the truth with small noise where keyframes are close in
    position (< 0.8 m) and heading (< 30 deg)."""
    rng = np.random.default_rng(seed)
    radius, per_lap = 4.0, 60
    gt, client = {}, {}
    for r in range(1, robots + 1):
        theta = 2 * np.pi * (np.arange(keyframes_per_robot) / per_lap + (r - 1) / robots)
        centre = np.array([0.8 * (r - 1), 0.4 * (r - 1), 0.0])
        pos = centre + np.column_stack(
            [radius * np.cos(theta), radius * np.sin(theta), 0.3 * np.sin(3 * theta)]
        )
        fwd = np.column_stack([-np.sin(theta), np.cos(theta), np.zeros_like(theta)])
        down = np.tile([0.0, 0.0, -1.0], (len(theta), 1))
        right = np.cross(down, fwd)
        T = np.tile(np.eye(4), (len(theta), 1, 1))
        T[:, :3, :3] = np.stack([right, down, fwd], axis=2)
        T[:, :3, 3] = pos
        gt[r] = T
        C = np.tile(np.eye(4), (len(theta), 1, 1))
        for k in range(1, len(theta)):
            D = invert(T[k - 1]) @ T[k]
            noise = np.eye(4)
            # Drift about the camera's y axis (down): yaw in the world.
            noise[:3, :3] = exp_so3(rng.normal(0, odom_rot_noise_rad, 3) + [0, yaw_drift_rad, 0])
            noise[:3, 3] = rng.normal(0, odom_trans_noise_m, 3)
            C[k] = C[k - 1] @ D @ noise
        client[r] = C

    def measure(Ta, Tb):
        noise = np.eye(4)
        noise[:3, :3] = exp_so3(rng.normal(0, meas_rot_noise_rad, 3))
        noise[:3, 3] = rng.normal(0, meas_trans_noise_m, 3)
        return invert(Ta) @ Tb @ noise

    def close_pairs(Ta, Tb):
        d = np.linalg.norm(Ta[:, None, :3, 3] - Tb[None, :, :3, 3], axis=2)
        cos = np.einsum("ik,jk->ij", Ta[:, :3, 2], Tb[:, :3, 2])
        return np.argwhere((d < 0.8) & (cos > np.cos(np.radians(30))))

    team = SyntheticTeam(gt, client)
    for r, T_r in gt.items():
        pairs = close_pairs(T_r, T_r)
        pairs = pairs[pairs[:, 1] - pairs[:, 0] > 20]
        for i, j in pairs[::loop_every]:
            team.loops.append((r, int(i) + 1, int(j) + 1, measure(T_r[i], T_r[j])))
    for ra, T_a in gt.items():
        for rb, T_b in gt.items():
            if rb <= ra:
                continue
            pairs = close_pairs(T_a, T_b)
            if len(pairs) == 0:
                continue
            pick = np.linspace(0, len(pairs) - 1, min(max_merges_per_pair, len(pairs))).astype(int)
            for i, j in pairs[pick]:
                team.merges.append((ra, int(i) + 1, rb, int(j) + 1, measure(T_a[i], T_b[j])))
    return team


def build_graph(team: SyntheticTeam, config: PoseGraphConfig | None = None) -> TeamPoseGraph:
    """A pose graph holding all keyframes, loops and merges of a synthetic team (not optimised)."""
    graph = TeamPoseGraph(config)
    for r, poses in team.T_map_cam.items():
        for k, T in enumerate(poses):
            graph.add_keyframe(r, k + 1, T)
    for r, i, j, T in team.loops:
        graph.add_loop(r, i, j, T)
    for ra, i, rb, j, T in team.merges:
        graph.add_merge(ra, i, rb, j, T)
    return graph


def bench_full_optimization(
    n_keyframes: int = 1000, robots: int = 4, seed: int = 0, repeats: int = 3
) -> float:
    """Median wall time [ms] of :meth:`TeamPoseGraph.optimize_full` right after the merges of a
    synthetic team of ``robots`` robots with ``n_keyframes`` keyframes in total."""
    team = synthetic_team(n_keyframes // robots, robots, seed)
    times = []
    for _ in range(repeats):
        graph = build_graph(team)
        times.append(graph.optimize_full().time_ms)
    return float(np.median(times))
