"""The team pose graph's factors: the model's types (configuration, factor, statistics), the
graph keys of keyframes, and the bookkeeping every factor goes through -- added, dropped, found
by keyframe, and turned into the GTSAM factor of its kind (cached). :mod:`.pose_graph` builds on
it; see there for the model."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..config import require
from ..errors import CoopSlamError
from ..geometry import invert
from ..ids import KeyframeKey
from .map_scale import scale_translation
from .results import TYPE_LOOP
from .scale_drift import (
    SCALE_BIT,
    is_scale_key,
    pose_sigmas,
    scale_key,
    scale_prior_factor,
    scaled_between_factor,
    scaled_link_factor,
)

KIND_ODOMETRY = "odometry"
KIND_COVISIBLE = "covisible"
KIND_LOOP = TYPE_LOOP
KIND_MERGE = "merge"
KIND_PRIOR = "prior"
KIND_SCALE_PRIOR = "scale_prior"  # a drifting map's scale at its first keyframe
CLIENT_KINDS = (KIND_ODOMETRY, KIND_COVISIBLE)  # measured from the client's poses
_ROBUST_KERNELS = ("huber", "cauchy", "none")
_MAP_ANCHORS = ("latest", "umeyama")
MAX_KEYFRAME_ID = SCALE_BIT - 1  # and 56 bits for the index, the top one for scale variables


class PoseGraphError(CoopSlamError):
    """Unknown keyframe or robot, duplicate keyframe, or invalid constraint for the pose graph."""


@dataclass
class PoseGraphConfig:
    """The team pose graph: factor sigmas, robust kernel, optimisation and scale drift."""

    odom_rot_sigma_rad: float = 0.005  # odometry between neighbouring keyframes ...
    odom_trans_sigma_m: float = 0.01  # [m]
    odom_rot_sigma_per_m: float = 0.005  # ... plus this much per metre between them
    odom_trans_sigma_per_m: float = 0.02  # [m per m]
    max_covisible_factors: int = 3  # extra client-pose factors per keyframe to covisible ones
    loop_rot_sigma_rad: float = 0.02  # a loop closure's rotation sigma (unless it gives one) [rad]
    loop_trans_sigma_m: float = 0.05  # ... and translation sigma [m]
    merge_rot_sigma_rad: float = 0.02  # a merge's or link's rotation sigma (unless given) [rad]
    merge_trans_sigma_m: float = 0.05  # ... and translation sigma [m]
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
    key_i: KeyframeKey
    key_j: KeyframeKey
    whitened_error: float  # Mahalanobis norm of the residual (6-D, 7-D with a scale row)
    weight: float  # robust-kernel weight at that residual (1 = fully trusted)
    scale_row: bool = False  # its similarity's scale is in the graph (a drifting map's end)


@dataclass
class Factor:
    kind: str
    key_i: KeyframeKey
    key_j: KeyframeKey | None  # None for a prior
    T_meas: np.ndarray  # T_cami_camj (between) or T_group_cam (prior)
    sigmas: tuple[float, float]  # (rotation rad, translation m)
    label: str = ""
    robust_k: float | None = None  # per-factor kernel width (whitened); None: the config's
    # A loop / merge measured by a similarity: log of key_j's map lengths in key_i's (T_meas's
    # translation is in key_i's) and its sigma (None: not measured); used where an end's scale
    # may drift.
    log_scale: float = 0.0
    scale_sigma: float | None = None


def gtsam_key(map_id: int, keyframe_id: int) -> int:
    """Graph key of a keyframe: one symbol character per robot, so all robots share one graph."""
    return gtsam.Symbol(chr(ord("a") + map_id), keyframe_id).key()


def key_of(gkey: int) -> KeyframeKey:
    s = gtsam.Symbol(gkey)
    return s.chr() - ord("a"), s.index()


def poses_from_values(values: gtsam.Values) -> dict[KeyframeKey, np.ndarray]:
    """All Pose3 values as 4x4 arrays, converted in one call (rows follow the key order)."""
    keys = [key_of(k) for k in values.keys() if not is_scale_key(k)]  # noqa: SIM118 (not iterable)
    rows = gtsam.utilities.extractPose3(values)
    T = np.tile(np.eye(4), (len(keys), 1, 1))
    T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = rows[:, 9:]
    return dict(zip(keys, T))


def finite_error(error: float | None, when: str) -> float:
    """A factor-graph error as a float; RuntimeError if it is NaN or inf (a keyframe or constraint
    with absurd values: Levenberg-Marquardt then returns its start unchanged, without throwing)."""
    error = float(error or 0.0)
    if not np.isfinite(error):
        raise RuntimeError(f"the graph's error {when} the step is {error}")
    return error


def finite_poses(values: gtsam.Values) -> dict[KeyframeKey, np.ndarray]:
    """The poses of an optimizer's result; RuntimeError if any is NaN or inf (an optimizer can
    diverge without throwing, e.g. from a pose of 1e300 m)."""
    poses = poses_from_values(values)
    bad = [k for k, T in poses.items() if not np.all(np.isfinite(T))]
    if bad:
        raise RuntimeError(
            f"the result holds non-finite poses ({len(bad)}, e.g. keyframe {bad[0][1]} of robot "
            f"{bad[0][0]})"
        )
    return poses


class FactorTable:
    """The factors of a pose graph by id, by keyframe, and as GTSAM factors; the scale-drift
    state they depend on (which maps' scales may drift, their keyframes' log scales) and the
    poses client factors are measured from."""

    def __init__(self, config: PoseGraphConfig):
        self.config = config
        self._kernel = self._make_kernel(config.robust_k)
        self._client: dict[KeyframeKey, np.ndarray] = {}  # T_map_cam as the client last sent it
        # Pose from global BA, until the client moves it, and which refinement it came from
        # (a run and a component of it: poses are refined against each other only within one).
        self._refined: dict[KeyframeKey, tuple[np.ndarray, tuple]] = {}
        # Monocular maps whose scale may drift (see set_scale_drift): keyframe -> log scale
        self._scale_drift: set[int] = set()
        self._log_scale: dict[KeyframeKey, float] = {}
        self._factors: dict[int, Factor] = {}
        self._gtsam_cache: dict[int, tuple] = {}  # factor id -> (T_meas, sigmas, GTSAM factor)
        self._by_key: dict[KeyframeKey, set[int]] = {}
        self._next_fid = 0
        # iSAM2 slots of factors, and those to remove at the next update
        self._isam_index: dict[int, int] = {}
        self._isam_remove: list[int] = []

    def _add_factor(self, f: Factor) -> int:
        fid = self._next_fid
        self._next_fid += 1
        self._factors[fid] = f
        for k in (f.key_i, f.key_j):
            if k is not None:
                self._by_key.setdefault(k, set()).add(fid)
        return fid

    def _drop_factor(self, fid: int) -> Factor:
        f = self._factors.pop(fid)
        self._gtsam_cache.pop(fid, None)
        for k in (f.key_i, f.key_j):
            if k is not None and k in self._by_key:
                self._by_key[k].discard(fid)
        slot = self._isam_index.pop(fid, None)
        if slot is not None:
            self._isam_remove.append(slot)
        return f

    def _client_factor(self, kind: str, key_i: KeyframeKey, key_j: KeyframeKey) -> int:
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
        return self._add_factor(Factor(kind, key_i, key_j, T_i_j, sigmas))

    def _make_kernel(self, k: float):
        if self.config.robust_kernel == "huber":
            return gtsam.noiseModel.mEstimator.Huber.Create(k)
        if self.config.robust_kernel == "cauchy":
            return gtsam.noiseModel.mEstimator.Cauchy.Create(k)
        return None

    def _kernel_of(self, f: Factor):
        """The robust kernel of a factor: a loop / merge's (None: none, and for the others)."""
        if self._kernel is None or f.kind not in (KIND_LOOP, KIND_MERGE):
            return None
        return self._kernel if f.robust_k is None else self._make_kernel(f.robust_k)

    def _noise(self, f: Factor):
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

    def _drifts(self, f: Factor) -> bool:
        """Whether a factor is a client factor of a map whose scale may drift."""
        return f.kind in CLIENT_KINDS and f.key_i[0] in self._scale_drift

    def _link_drifts(self, f: Factor) -> tuple[bool, bool]:
        """For a loop / merge factor, whether the scale of each end's map may drift."""
        if f.kind not in (KIND_LOOP, KIND_MERGE):
            return (False, False)
        return (f.key_i[0] in self._scale_drift, f.key_j[0] in self._scale_drift)

    def _make_gtsam_factor(self, f: Factor):
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

    def _odometry_between(self, key_i: KeyframeKey, key_j: KeyframeKey) -> list[int]:
        return [
            fid
            for fid in self._by_key.get(key_i, ())
            if self._factors[fid].kind == KIND_ODOMETRY
            and {self._factors[fid].key_i, self._factors[fid].key_j} == {key_i, key_j}
        ]

    def _sigmas(self, rot, trans, default_rot, default_trans) -> tuple[float, float]:
        sig = (
            default_rot if rot is None else float(rot),
            default_trans if trans is None else float(trans),
        )
        if not (sig[0] > 0 and sig[1] > 0):
            raise PoseGraphError(f"constraint sigmas must be > 0, got {sig}")
        return sig

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

    def edges(self, kind: str | None = None) -> list[tuple[str, KeyframeKey, KeyframeKey | None]]:
        """(kind, key_i, key_j) of every factor, optionally of one kind (for inspection / tests)."""
        return [
            (f.kind, f.key_i, f.key_j)
            for f in self._factors.values()
            if kind is None or f.kind == kind
        ]
