"""Two-view bundle adjustment (GTSAM, Levenberg-Marquardt) refining ``T_camA_camB``.

Variables: the pose of camera A (held at identity by a tight prior, so the problem is expressed in
camera A's frame), the pose of camera B (= ``T_camA_camB``) and one 3D point per correspondence.
Cost: the sum over both images of ``||u - pi(K, T, X)||^2`` (GenericProjectionFactorCal3_S2) under
a Huber m-estimator, plus, where a keypoint has depth, a weak range factor from that camera (its
sigma grows with depth^2) that fixes the scale and keeps points near their measured depth, plus an
optional weak prior on ``T_camA_camB`` (e.g. from a marker sighting). Correspondences whose error
exceeds the inlier threshold in either image after a round are dropped and the problem re-solved.

Graph construction adds per-point factors in Python (GTSAM has no batch API for priors or range
factors); projection factors use the batch helper ``utilities.insertProjectionFactors``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import gtsam
import numpy as np

from ..errors import GeometryError
from ..geometry import check_se3, invert, transform_points
from .camera import RegistrationError, check_intrinsics, check_points, project, ray_norms

# Plain integer keys (not gtsam.symbol): insertProjectionFactors takes point keys as float64, which
# cannot hold symbol keys exactly.
KEY_CAM_A, KEY_CAM_B, KEY_POINT0 = 0, 1, 2
_FIX_SIGMA = 1e-6  # camera A prior: effectively a constant, but keeps the Cholesky solve regular


@dataclass
class BaResult:
    T_camA_camB: np.ndarray
    points_camA: np.ndarray  # (K, 3) refined points in camera A
    errors_a_px: np.ndarray  # (K,) reprojection error in A (inf behind the camera)
    errors_b_px: np.ndarray  # (K,) reprojection error in B
    inliers: np.ndarray  # (K,) bool: error below the threshold in both images
    rms_px: float  # RMS per-image reprojection error over the inliers
    initial_rms_px: float  # same measure at the initial guess, over the same inliers
    n_iterations: int
    # 6x6 marginal covariance of T_camA_camB in GTSAM's tangent order (rx, ry, rz [rad], tx, ty,
    # tz [m], in camera B's frame) at the solution; inf where the problem is singular
    covariance: np.ndarray

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def sigma_rot_deg(self) -> float:
        """Largest rotation standard deviation [deg] (worst-constrained axis); inf if singular."""
        return float(np.degrees(worst_sigma(self.covariance[:3, :3])))

    @property
    def sigma_trans_m(self) -> float:
        """Largest translation standard deviation [m] (worst direction); inf if singular."""
        return worst_sigma(self.covariance[3:, 3:])


def worst_sigma(cov: np.ndarray) -> float:
    """Standard deviation along the worst-constrained direction of a covariance block; inf when
    the problem is singular."""
    # A singular problem's covariance is inf, on which eigvalsh raises instead of answering.
    if not np.all(np.isfinite(cov)):
        return float("inf")
    return float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0)))


def reprojection_errors_both(T_camA_camB, points_camA, uv_px_a, uv_px_b, K_a, K_b):
    """((K,), (K,)) pixel errors of camera-A points in image A and image B (inf when behind)."""
    err_a = np.linalg.norm(project(points_camA, K_a) - uv_px_a, axis=1)
    points_camB = transform_points(invert(T_camA_camB), points_camA)
    err_b = np.linalg.norm(project(points_camB, K_b) - uv_px_b, axis=1)
    return np.nan_to_num(err_a, nan=np.inf), np.nan_to_num(err_b, nan=np.inf)


def rms_both(err_a: np.ndarray, err_b: np.ndarray, mask: np.ndarray) -> float:
    """RMS per-image reprojection error of the masked correspondences over both images."""
    if not mask.any():
        return np.nan
    return float(np.sqrt(0.5 * (err_a[mask] ** 2 + err_b[mask] ** 2).mean()))


def _pose_sigmas(prior_sigma) -> np.ndarray:
    """6 GTSAM tangent sigmas (rx, ry, rz [rad], tx, ty, tz [m]) from a 2- or 6-vector."""
    s = np.asarray(prior_sigma, dtype=float).reshape(-1)
    if len(s) == 2:
        s = np.repeat(s, 3)
    if len(s) != 6 or not np.all(np.isfinite(s)) or (s <= 0).any():
        raise RegistrationError(
            "prior_sigma must be (rot_rad, trans_m) or 6 tangent sigmas "
            "(rx, ry, rz [rad], tx, ty, tz [m]), all > 0"
        )
    return s


@dataclass
class _Problem:
    """Per-correspondence measurements of one solve (ranges 0 = no depth factor)."""

    uv_a: np.ndarray
    uv_b: np.ndarray
    range_a: np.ndarray
    range_sigma_a: np.ndarray
    range_b: np.ndarray
    range_sigma_b: np.ndarray

    def subset(self, mask: np.ndarray) -> _Problem:
        return _Problem(*(getattr(self, f.name)[mask] for f in fields(self)))


@dataclass
class _Settings:
    cal_a: gtsam.Cal3_S2
    cal_b: gtsam.Cal3_S2
    sigma_px: float
    huber_k: float
    T_prior: np.ndarray | None
    prior_sigmas: np.ndarray | None
    max_iterations: int
    relative_tol: float


def _solve(problem: _Problem, points0: np.ndarray, T0: np.ndarray, cfg: _Settings):
    """One LM solve -> (T_camA_camB, points_camA, iterations, covariance of camera B)."""
    n = len(problem.uv_a)
    graph = gtsam.NonlinearFactorGraph()
    # Huber's k is in whitened units, i.e. it bends at huber_k * sigma_px pixels.
    pixel_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_k),
        gtsam.noiseModel.Isotropic.Sigma(2, cfg.sigma_px),
    )
    point_keys = (KEY_POINT0 + np.arange(n)).astype(float)
    for cam_key, uv, cal in (
        (KEY_CAM_A, problem.uv_a, cfg.cal_a),
        (KEY_CAM_B, problem.uv_b, cfg.cal_b),
    ):
        gtsam.utilities.insertProjectionFactors(graph, cam_key, point_keys, uv.T, pixel_noise, cal)
    fix_noise = gtsam.noiseModel.Isotropic.Sigma(6, _FIX_SIGMA)
    graph.add(gtsam.PriorFactorPose3(KEY_CAM_A, gtsam.Pose3(), fix_noise))
    if cfg.T_prior is not None:
        prior_noise = gtsam.noiseModel.Diagonal.Sigmas(cfg.prior_sigmas)
        graph.add(gtsam.PriorFactorPose3(KEY_CAM_B, gtsam.Pose3(cfg.T_prior), prior_noise))
    huber_range = gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_k)
    for cam_key, ranges, sigmas in (
        (KEY_CAM_A, problem.range_a, problem.range_sigma_a),
        (KEY_CAM_B, problem.range_b, problem.range_sigma_b),
    ):
        for i in np.flatnonzero(ranges > 0):  # depth is a per-point measurement: one factor each
            noise = gtsam.noiseModel.Robust.Create(
                huber_range, gtsam.noiseModel.Isotropic.Sigma(1, float(sigmas[i]))
            )
            graph.add(gtsam.RangeFactor3D(cam_key, KEY_POINT0 + int(i), float(ranges[i]), noise))
    values = gtsam.Values()
    values.insert(KEY_CAM_A, gtsam.Pose3())
    values.insert(KEY_CAM_B, gtsam.Pose3(T0))
    for i in range(n):
        values.insert_point3(KEY_POINT0 + i, points0[i])
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(cfg.max_iterations))
    params.setRelativeErrorTol(cfg.relative_tol)
    params.setAbsoluteErrorTol(1e-9)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    # Express everything relative to the optimised camera A (it moves by ~_FIX_SIGMA at most).
    T_a_w = invert(result.atPose3(KEY_CAM_A).matrix())
    T_camA_camB = T_a_w @ result.atPose3(KEY_CAM_B).matrix()
    points = gtsam.utilities.extractPoint3(result)  # rows in key order = correspondence order
    try:
        # Camera A is pinned, so B's marginal is the covariance of the relative pose: it exposes
        # ill-conditioned solutions (all inliers on one small object) that residuals cannot.
        covariance = gtsam.Marginals(graph, result).marginalCovariance(KEY_CAM_B)
    except RuntimeError:  # indeterminant system
        covariance = np.full((6, 6), np.inf)
    return T_camA_camB, transform_points(T_a_w, points), optimizer.iterations(), covariance


def two_view_ba(
    uv_px_a: np.ndarray,
    uv_px_b: np.ndarray,
    K_a: np.ndarray,
    K_b: np.ndarray,
    points_camA_init: np.ndarray,
    T_camA_camB_init: np.ndarray,
    depths_a_m: np.ndarray | None = None,
    depth_sigma_a_m: np.ndarray | None = None,
    depths_b_m: np.ndarray | None = None,
    depth_sigma_b_m: np.ndarray | None = None,
    sigma_px: float = 1.0,
    huber_k: float = 1.345,
    inlier_px: float = 2.5,
    T_prior_camA_camB: np.ndarray | None = None,
    prior_sigma=None,
    max_iterations: int = 30,
    rounds: int = 2,
    relative_tol: float = 1e-3,
) -> BaResult:
    """Refine the relative pose from K correspondences (uv in A, uv in B, initial point in A).

    Depths (0 = none) add range factors with the given per-point depth sigmas. ``prior_sigma`` for
    ``T_prior_camA_camB`` is (rot_rad, trans_m) or 6 tangent sigmas; keep it weak (the prior must
    not replace feature evidence). LM stops at ``relative_tol`` relative cost decrease: the Huber
    cost creeps down for many more iterations without moving the pose noticeably.
    """
    uv_a = np.asarray(uv_px_a, dtype=float)
    uv_b = np.asarray(uv_px_b, dtype=float)
    n = len(uv_a)
    if uv_a.shape != (n, 2) or uv_b.shape != (n, 2):
        raise RegistrationError(
            f"uv_px_a/uv_px_b must both be (K, 2), got {uv_a.shape}, {uv_b.shape}"
        )
    if not (np.all(np.isfinite(uv_a)) and np.all(np.isfinite(uv_b))):
        raise RegistrationError("uv_px_a/uv_px_b contain NaN or inf")
    K_a, K_b = check_intrinsics(K_a, "K_a"), check_intrinsics(K_b, "K_b")
    points0 = check_points(points_camA_init, "points_camA_init", n)
    try:
        T0 = check_se3(T_camA_camB_init, "T_camA_camB_init")
        T_prior = None
        if T_prior_camA_camB is not None:
            T_prior = check_se3(T_prior_camA_camB, "T_prior_camA_camB")
    except GeometryError as exc:
        raise RegistrationError(str(exc)) from None
    if (T_prior is None) != (prior_sigma is None):
        raise RegistrationError("a pose prior needs both T_prior_camA_camB and prior_sigma")
    prior_sigmas = _pose_sigmas(prior_sigma) if T_prior is not None else None
    if sigma_px <= 0 or huber_k <= 0 or inlier_px <= 0 or rounds < 1:
        raise RegistrationError("sigma_px, huber_k, inlier_px must be > 0 and rounds >= 1")

    def ranges(depths, sigmas, uv, K, name):
        if depths is None:
            return np.zeros(n), np.ones(n)
        depths = np.asarray(depths, dtype=float).reshape(-1)
        sigmas = np.broadcast_to(np.asarray(sigmas, dtype=float), (n,))
        if len(depths) != n or not np.all(np.isfinite(depths)) or (depths < 0).any():
            raise RegistrationError(f"{name} must be {n} finite depths >= 0")
        if not np.all(sigmas[depths > 0] > 0):
            raise RegistrationError(f"depth sigmas for {name} must be > 0 where depth exists")
        norm = ray_norms(uv, K)  # range along the ray = depth * |K^-1 (u, v, 1)|
        return depths * norm, np.where(depths > 0, sigmas * norm, 1.0)

    problem = _Problem(
        uv_a,
        uv_b,
        *ranges(depths_a_m, depth_sigma_a_m, uv_a, K_a, "depths_a_m"),
        *ranges(depths_b_m, depth_sigma_b_m, uv_b, K_b, "depths_b_m"),
    )
    settings = _Settings(
        gtsam.Cal3_S2(K_a[0, 0], K_a[1, 1], K_a[0, 1], K_a[0, 2], K_a[1, 2]),
        gtsam.Cal3_S2(K_b[0, 0], K_b[1, 1], K_b[0, 1], K_b[0, 2], K_b[1, 2]),
        sigma_px,
        huber_k,
        T_prior,
        prior_sigmas,
        max_iterations,
        relative_tol,
    )

    err_a0, err_b0 = reprojection_errors_both(T0, points0, uv_a, uv_b, K_a, K_b)
    T, points = T0, points0.copy()
    active = np.ones(n, dtype=bool)
    iterations = 0
    covariance = np.full((6, 6), np.inf)
    for _ in range(rounds):
        if active.sum() < 3:
            break
        T, points[active], its, covariance = _solve(
            problem.subset(active), points[active], T, settings
        )
        iterations += its
        # Later rounds drop correspondences that are outliers in either image (kept out for good).
        err_a, err_b = reprojection_errors_both(T, points, uv_a, uv_b, K_a, K_b)
        inliers = active & (err_a < inlier_px) & (err_b < inlier_px)
        if np.array_equal(inliers, active):
            break
        active = inliers
    err_a, err_b = reprojection_errors_both(T, points, uv_a, uv_b, K_a, K_b)
    inliers = (err_a < inlier_px) & (err_b < inlier_px)
    return BaResult(
        T_camA_camB=T,
        points_camA=points,
        errors_a_px=err_a,
        errors_b_px=err_b,
        inliers=inliers,
        rms_px=rms_both(err_a, err_b, inliers),
        initial_rms_px=rms_both(err_a0, err_b0, inliers),
        n_iterations=iterations,
        covariance=covariance,
    )
