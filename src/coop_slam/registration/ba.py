"""Two-view bundle adjustment (Levenberg-Marquardt, Schur complement) refining ``T_camA_camB``.

Variables: the pose of camera B in camera A's frame (= ``T_camA_camB``; camera A is the frame of
the problem and fixed) and one 3D point per correspondence. Cost: the sum over both images of
``||u - pi(K, T, X)||^2`` under a Huber m-estimator, plus, where a keypoint has depth, a weak range
residual from that camera (its sigma grows with depth^2) that fixes the scale and keeps points
near their measured depth, plus an optional weak prior on ``T_camA_camB`` (e.g. from a marker
sighting). Correspondences whose error exceeds the inlier threshold in either image after a round
are dropped and the problem re-solved.

The solver is numpy, not GTSAM: with two cameras every point is independent given camera B, so
each step eliminates the points (3x3 blocks) and solves one 6x6 system. The cost is that of
GTSAM's factor graph (projection, range and prior factors, which this solver replaced: the same
inliers and covariances on recorded server problems) without building thousands of factors in
Python for each verification; the iteration is :func:`coop_slam.optim.lm.least_squares`'s (its
rules, Marquardt's damping and the gain ratio, are the Sim(3) refinement's too). The covariance
of camera B is GTSAM's tangent of Pose3 (rotation first, in B's frame).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import cv2
import numpy as np

from ..errors import GeometryError
from ..geometry import check_se3, exp_so3, invert, skew, transform_points
from ..optim.lm import LmRules, damp, least_squares
from .camera import (
    RegistrationError,
    check_intrinsics,
    check_points,
    project,
    projection_jacobian,
    ray_norms,
)


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
    K_a: np.ndarray
    K_b: np.ndarray
    sigma_px: float
    huber_k: float
    T_prior: np.ndarray | None
    prior_sigmas: np.ndarray | None
    max_iterations: int
    relative_tol: float


def huber(e: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """(cost, IRLS weight) of whitened error norms under Huber's m-estimator."""
    cost = np.where(e <= k, 0.5 * e**2, k * e - 0.5 * k**2)
    weight = np.where(e <= k, 1.0, k / np.maximum(e, 1e-300))
    return cost, weight


@dataclass
class _Block:
    """One kind of residual for every point: whitened residuals (n, d), which points have it
    (n,), and, for the normal equations, whitened Jacobians by the pose of B (n, d, 6; None for
    terms of camera A alone) and by the point (n, d, 3)."""

    r: np.ndarray
    has: np.ndarray
    J_pose: np.ndarray | None = None
    J_point: np.ndarray | None = None


def _projection_block(points_cam, uv, K, sigma_px, dcam_dpoint, dcam_dpose, jacobians) -> _Block:
    """Pixel residuals of camera-frame points. A point behind the camera gets GTSAM's answer for
    it: a constant error of 2 fx per coordinate and no gradient, so a step there is refused."""
    n = len(points_cam)
    front = points_cam[:, 2] > 1e-9
    uv_hat = project(points_cam, K)  # NaN behind the camera, replaced here
    r = np.where(front[:, None], (uv_hat - uv) / sigma_px, 2.0 * K[0, 0] / sigma_px)
    if not jacobians:
        return _Block(r, np.ones(n, dtype=bool))
    P = projection_jacobian(points_cam, K) * (front / sigma_px)[:, None, None]
    J_pose = None if dcam_dpose is None else np.einsum("nij,njk->nik", P, dcam_dpose)
    J_point = P if dcam_dpoint is None else P @ dcam_dpoint
    return _Block(r, np.ones(n, dtype=bool), J_pose, J_point)


def _range_block(points_cam, ranges, sigmas, dcam_dpoint, dcam_dpose, jacobians) -> _Block:
    """Range residuals ``|point| - range`` of the points that have a range (0: none)."""
    has = ranges > 0
    norm = np.linalg.norm(points_cam, axis=1)
    r = np.where(has, (norm - ranges) / sigmas, 0.0)[:, None]
    if not jacobians:
        return _Block(r, has)
    d = (points_cam / np.maximum(norm, 1e-12)[:, None] * (has / sigmas)[:, None])[:, None, :]
    J_pose = None if dcam_dpose is None else np.einsum("nij,njk->nik", d, dcam_dpose)
    J_point = d if dcam_dpoint is None else d @ dcam_dpoint
    return _Block(r, has, J_pose, J_point)


def _blocks(problem: _Problem, R, t, points, cfg: _Settings, jacobians: bool) -> list[_Block]:
    """Every residual at pose (R, t) of camera B in A and points in A."""
    points_b = (points - t) @ R  # R^T (X - t), row-wise
    # Camera B moves as T exp(xi), xi = (w, v): d points_b = [points_b]x w - v, d points_b / d X
    # = R^T, so the covariance is in GTSAM's tangent of Pose3 (rotation first, in B's frame).
    dpose = dpoint_b = None
    if jacobians:
        dpose = np.concatenate(
            [skew(points_b), np.broadcast_to(-np.eye(3), (len(points), 3, 3))], axis=2
        )
        dpoint_b = R.T
    return [
        _projection_block(points, problem.uv_a, cfg.K_a, cfg.sigma_px, None, None, jacobians),
        _projection_block(
            points_b, problem.uv_b, cfg.K_b, cfg.sigma_px, dpoint_b, dpose, jacobians
        ),
        _range_block(points, problem.range_a, problem.range_sigma_a, None, None, jacobians),
        _range_block(points_b, problem.range_b, problem.range_sigma_b, dpoint_b, dpose, jacobians),
    ]


def _prior_residual(R, t, cfg: _Settings) -> np.ndarray:
    """Whitened error of camera B against the pose prior: Pose3's logarithm of the prior's
    inverse times the pose, as GTSAM's prior factor has it."""
    dR = cfg.T_prior[:3, :3].T @ R
    dt = cfg.T_prior[:3, :3].T @ (t - cfg.T_prior[:3, 3])
    w = cv2.Rodrigues(dR)[0].ravel()
    theta = float(np.linalg.norm(w))
    W = skew(w)
    # the translation part of SE(3)'s log: V(w)^-1 dt
    c = 1.0 / 12.0 if theta < 1e-6 else (1.0 - theta / (2.0 * np.tan(theta / 2.0))) / theta**2
    v = dt - 0.5 * W @ dt + c * W @ (W @ dt)
    return np.r_[w, v] / cfg.prior_sigmas


def _cost(blocks: list[_Block], prior_r: np.ndarray | None, huber_k: float) -> float:
    total = 0.0
    for b in blocks:
        total += float(huber(np.linalg.norm(b.r, axis=1), huber_k)[0][b.has].sum())
    if prior_r is not None:
        total += 0.5 * float(prior_r @ prior_r)
    return total


@dataclass
class _Normal:
    """The normal equations of the IRLS-weighted problem, points apart (Schur form)."""

    H_cc: np.ndarray  # (6, 6) pose of B
    H_cp: np.ndarray  # (n, 6, 3)
    H_pp: np.ndarray  # (n, 3, 3)
    g_c: np.ndarray  # (6,)
    g_p: np.ndarray  # (n, 3)

    def _schur(self, lam: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(H_pp^-1, H_cp H_pp^-1, Schur complement of the pose) of the system damped by
        ``lam`` (None: undamped): the points eliminated, their blocks being independent given
        the pose. Damping the whole system's diagonal is damping each diagonal block's."""
        H_pp, H_cc = self.H_pp, self.H_cc
        if lam is not None:
            H_pp, H_cc = damp(H_pp, lam), damp(H_cc, lam)
        H_pp_inv = np.linalg.inv(H_pp)
        HcpHinv = self.H_cp @ H_pp_inv  # (n, 6, 3)
        S = H_cc - np.einsum("nij,nkj->ik", HcpHinv, self.H_cp)
        return H_pp_inv, HcpHinv, S

    def step(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """(pose step, point steps) of the system damped by ``lam`` (Marquardt's damping)."""
        H_pp_inv, HcpHinv, S = self._schur(lam)
        b = self.g_c - np.einsum("nij,nj->i", HcpHinv, self.g_p)
        d_pose = np.linalg.solve(S, -b)
        rhs = -self.g_p - np.einsum("nji,j->ni", self.H_cp, d_pose)
        return d_pose, np.einsum("nij,nj->ni", H_pp_inv, rhs)

    def pose_covariance(self) -> np.ndarray:
        """Marginal covariance of B's pose (the inverse Schur complement), inf if singular."""
        try:
            S = self._schur(None)[2]
            if not np.all(np.isfinite(S)) or np.linalg.cond(S) > 1e14:
                return np.full((6, 6), np.inf)
            return np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return np.full((6, 6), np.inf)


def _normal(blocks: list[_Block], prior_r, cfg: _Settings, n: int) -> _Normal:
    # All residual rows of a point side by side, IRLS-weighted per block, camera A's with a zero
    # pose Jacobian: one batched product per block of the normal equations.
    w_rows, J_point, J_pose, r = [], [], [], []
    for b in blocks:
        w = np.where(b.has, huber(np.linalg.norm(b.r, axis=1), cfg.huber_k)[1], 0.0)
        d = b.r.shape[1]
        w_rows.append(np.repeat(w[:, None], d, axis=1))
        J_point.append(b.J_point)
        J_pose.append(np.zeros((n, d, 6)) if b.J_pose is None else b.J_pose)
        r.append(b.r)
    w_rows, r = np.concatenate(w_rows, axis=1), np.concatenate(r, axis=1)
    J_point, J_pose = np.concatenate(J_point, axis=1), np.concatenate(J_pose, axis=1)
    Jp_w = J_point.transpose(0, 2, 1) * w_rows[:, None, :]  # (n, 3, rows)
    Jc_w = J_pose.transpose(0, 2, 1) * w_rows[:, None, :]  # (n, 6, rows)
    wr = (w_rows * r)[:, :, None]
    H_cc = Jc_w.transpose(1, 0, 2).reshape(6, -1) @ J_pose.reshape(-1, 6)
    g_c = (J_pose * wr).sum(axis=(0, 1))
    if prior_r is not None:  # d residual / d xi is ~identity / sigma for a small error
        H_cc += np.diag(cfg.prior_sigmas**-2.0)
        g_c += prior_r / cfg.prior_sigmas
    return _Normal(H_cc, Jc_w @ J_point, Jp_w @ J_point, g_c, (J_point * wr).sum(axis=1))


class _BaSolve:
    """One solve of ``problem`` as a problem for :func:`~coop_slam.optim.lm.least_squares`: the
    state is (R, t, points) -- camera B's pose in A and the points in A -- and a step is
    (pose step, point steps) in one vector; camera B moves as T exp(xi), xi = (w, v)."""

    def __init__(self, problem: _Problem, cfg: _Settings):
        self.problem, self.cfg = problem, cfg

    def residuals(self, state, jacobians: bool):
        R, t, points = state
        blocks = _blocks(self.problem, R, t, points, self.cfg, jacobians)
        return blocks, None if self.cfg.T_prior is None else _prior_residual(R, t, self.cfg)

    def cost(self, state) -> float:
        return _cost(*self.residuals(state, False), self.cfg.huber_k)

    def linearize(self, state) -> _Normal:
        return _normal(*self.residuals(state, True), self.cfg, len(state[2]))

    @staticmethod
    def solve(normal: _Normal, lam: float) -> np.ndarray:
        d_pose, d_points = normal.step(lam)
        return np.concatenate([d_pose, d_points.ravel()])

    @staticmethod
    def predicted_decrease(normal: _Normal, step: np.ndarray) -> float:
        d_pose, d_points = step[:6], step[6:].reshape(-1, 3)
        return -(
            normal.g_c @ d_pose
            + np.einsum("ni,ni->", normal.g_p, d_points)
            + 0.5 * _quadratic(normal, d_pose, d_points)
        )

    @staticmethod
    def retract(state, step: np.ndarray):
        R, t, points = state
        return R @ exp_so3(step[:3]), t + R @ step[3:6], points + step[6:].reshape(-1, 3)


def _solve(problem: _Problem, points0: np.ndarray, T0: np.ndarray, cfg: _Settings):
    """One LM solve -> (T_camA_camB, points_camA, iterations, covariance of camera B).

    Camera A is the frame of the problem and stays fixed; camera B's pose and the points are the
    variables. The points are eliminated from each step's normal equations (Schur complement), so
    a step costs a few numpy products over the points and one 6x6 solve.
    """
    solve = _BaSolve(problem, cfg)
    rules = LmRules(max_iterations=cfg.max_iterations, relative_tol=cfg.relative_tol)
    state = (T0[:3, :3].copy(), T0[:3, 3].copy(), points0.copy())
    outcome = least_squares(solve, state, rules)
    R, t, points = outcome.state
    covariance = solve.linearize(outcome.state).pose_covariance()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T, points, outcome.iterations, covariance


def _quadratic(normal: _Normal, d_pose: np.ndarray, d_points: np.ndarray) -> float:
    """d^T H d of the undamped normal equations."""
    return float(
        d_pose @ normal.H_cc @ d_pose
        + 2.0 * np.einsum("i,nij,nj->", d_pose, normal.H_cp, d_points)
        + np.einsum("ni,nij,nj->", d_points, normal.H_pp, d_points)
    )


def _checked_problem(
    uv_px_a,
    uv_px_b,
    K_a,
    K_b,
    points_camA_init,
    T_camA_camB_init,
    depths,
    sigma_px,
    huber_k,
    T_prior_camA_camB,
    prior_sigma,
    max_iterations,
    relative_tol,
) -> tuple[_Problem, _Settings, np.ndarray, np.ndarray]:
    """two_view_ba's input, checked: (measurements, settings, initial pose, initial points).
    ``depths`` is (depths in A, their sigmas, depths in B, their sigmas)."""
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
    if sigma_px <= 0 or huber_k <= 0:
        raise RegistrationError("sigma_px and huber_k must be > 0")

    def ranges(depths, sigmas, uv, K, name):
        """(range along the ray, its sigma) per correspondence, range 0 where no depth."""
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
        *ranges(depths[0], depths[1], uv_a, K_a, "depths_a_m"),
        *ranges(depths[2], depths[3], uv_b, K_b, "depths_b_m"),
    )
    settings = _Settings(
        K_a, K_b, sigma_px, huber_k, T_prior, prior_sigmas, max_iterations, relative_tol
    )
    return problem, settings, T0, points0


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
    if inlier_px <= 0 or rounds < 1:
        raise RegistrationError("inlier_px must be > 0 and rounds >= 1")
    problem, settings, T0, points0 = _checked_problem(
        uv_px_a,
        uv_px_b,
        K_a,
        K_b,
        points_camA_init,
        T_camA_camB_init,
        (depths_a_m, depth_sigma_a_m, depths_b_m, depth_sigma_b_m),
        sigma_px,
        huber_k,
        T_prior_camA_camB,
        prior_sigma,
        max_iterations,
        relative_tol,
    )
    uv_a, uv_b, K_a, K_b, n = problem.uv_a, problem.uv_b, settings.K_a, settings.K_b, len(points0)
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
