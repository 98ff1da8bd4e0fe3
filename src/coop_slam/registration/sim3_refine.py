"""Refinement of a similarity ``p_dst = scale R p_src + t`` (Sim(3)) between two keyframes on
both reprojection errors, with the map points held fixed (as ORB-SLAM's OptimizeSim3): Huber-robust
:func:`coop_slam.optim.lm.least_squares` on the 7 parameters (rotation, translation, log-scale),
optionally with relative depth residuals, and the covariance of the similarity at the solution
(calibrated: on the synthetic tests its NEES is close to the 7 expected).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import exp_so3, skew
from ..optim.lm import LmRules, damp, least_squares
from .ba import huber, rms_both, worst_sigma
from .camera import projection_jacobian
from .sim3_data import (
    CHI2_2DOF_99,
    Correspondences,
    Sim3Error,
    make_correspondences,
    project_in_front,
)

_BEHIND_WHITENED = 1e3  # robust-cost stand-in for the error of a point pushed behind a camera


@dataclass
class Sim3RefineResult:
    T_dst_src: np.ndarray  # rigid part of the similarity
    scale: float
    errors_src_px: np.ndarray  # (N,) dst points moved into src, error in the src image (inf behind)
    errors_dst_px: np.ndarray  # (N,) src points moved into dst, error in the dst image
    inliers: np.ndarray  # (N,) bool: within the chi2 gate in both images at the solution
    rms_px: float  # RMS per-image reprojection error over the inliers
    initial_rms_px: float  # same measure at the initial guess, over the same inliers
    n_iterations: int
    # 7x7 covariance of the update (rx, ry, rz [rad], tx, ty, tz [dst units], log scale) applied as
    # R <- Exp(r) R, t <- t + dt, scale <- scale exp(ds) (rotation in dst's frame); inf if singular,
    # scale row/column 0 when the scale was fixed
    covariance: np.ndarray
    variance_factor: float  # a-posteriori residual variance / model's (>= 1 applied to covariance)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def sigma_rot_deg(self) -> float:
        """Largest rotation standard deviation [deg] (worst-constrained axis); inf if singular."""
        return float(np.degrees(worst_sigma(self.covariance[:3, :3])))

    @property
    def sigma_trans(self) -> float:
        """Largest translation standard deviation in dst's length units (worst direction)."""
        return worst_sigma(self.covariance[3:6, 3:6])

    @property
    def sigma_scale_rel(self) -> float:
        """Standard deviation of log(scale), i.e. the relative scale uncertainty."""
        var = self.covariance[6, 6]
        return float(np.sqrt(var)) if np.isfinite(var) else float("inf")


@dataclass
class _Sim3:
    R: np.ndarray
    t: np.ndarray
    scale: float

    def T(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T

    def retract(self, delta: np.ndarray) -> _Sim3:
        log_s = delta[6] if len(delta) == 7 else 0.0
        return _Sim3(exp_so3(delta[:3]) @ self.R, self.t + delta[3:6], self.scale * np.exp(log_s))

    def moved(self, data: Correspondences) -> tuple[np.ndarray, np.ndarray]:
        """(src points in dst, dst points in src)."""
        moved_dst = self.scale * data.src @ self.R.T + self.t
        moved_src = (data.dst - self.t) @ self.R / self.scale  # R^T (p - t) / s, row-wise
        return moved_dst, moved_src


def _pixel_errors(state: _Sim3, data: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """(N,) reprojection errors [px] in the src and the dst image (inf when behind)."""
    moved_dst, moved_src = state.moved(data)
    uv_dst, ok_dst = project_in_front(moved_dst, data.K_dst)
    uv_src, ok_src = project_in_front(moved_src, data.K_src)
    err_dst = np.where(ok_dst, np.linalg.norm(uv_dst - data.uv_dst, axis=1), np.inf)
    err_src = np.where(ok_src, np.linalg.norm(uv_src - data.uv_src, axis=1), np.inf)
    return err_src, err_dst


@dataclass
class _Problem:
    """One solve as a problem for :func:`~coop_slam.optim.lm.least_squares`: correspondences,
    residual sigmas (held fixed while solving), depth term, robust kernel. The state is a
    :class:`_Sim3`, a step the update (r, dt, log s), without log s when the scale is fixed."""

    data: Correspondences
    sig_dst: np.ndarray  # (N,) sigma of the dst-image residual [px]
    sig_src: np.ndarray
    depth_sigma_rel: float  # 0: reprojection only
    huber_k: float
    n_params: int  # 6 with the scale fixed, else 7

    def cost(self, state: _Sim3) -> float:
        return _robust_cost(*self.whitened(state, False)[:2], self.huber_k)

    def linearize(self, state: _Sim3) -> tuple[np.ndarray, np.ndarray]:
        """(H, g) of the IRLS-weighted normal equations at ``state``."""
        return _normal_equations(*self.whitened(state, True), self.huber_k, self.n_params)[:2]

    @staticmethod
    def solve(linearization, lam: float) -> np.ndarray:
        H, g = linearization
        return np.linalg.solve(damp(H, lam), -g)

    @staticmethod
    def predicted_decrease(linearization, step: np.ndarray) -> float:
        H, g = linearization
        return -float(g @ step + 0.5 * step @ H @ step)

    @staticmethod
    def retract(state: _Sim3, step: np.ndarray) -> _Sim3:
        return state.retract(step)

    def whitened(self, state: _Sim3, jacobians: bool):
        """Whitened residual blocks (M, N, 2), in-front mask (M, N) and, when asked, Jacobians
        (M, N, 2, 7) of the update (r, dt, log s). Blocks: src points in the dst image, dst points
        in the src image, then (with the depth term) their depth errors, padded with a zero."""
        d = self.data
        R, t, s = state.R, state.t, state.scale
        moved_dst, moved_src = state.moved(d)
        uv_dst, ok_dst = project_in_front(moved_dst, d.K_dst)
        uv_src, ok_src = project_in_front(moved_src, d.K_src)
        blocks = [(uv_dst - d.uv_dst) / self.sig_dst[:, None]]
        blocks.append((uv_src - d.uv_src) / self.sig_src[:, None])
        valid = [ok_dst, ok_src]
        if self.depth_sigma_rel > 0:
            # Relative depth errors: how far a moved point lands in front of or behind its match,
            # which reprojection sees only through the (often small) parallax.
            sig_z_dst = self.depth_sigma_rel * d.dst[:, 2]
            sig_z_src = self.depth_sigma_rel * d.src[:, 2]
            zero = np.zeros(len(d.src))
            blocks.append(np.stack([(moved_dst[:, 2] - d.dst[:, 2]) / sig_z_dst, zero], axis=1))
            blocks.append(np.stack([(moved_src[:, 2] - d.src[:, 2]) / sig_z_src, zero], axis=1))
            valid += [ok_dst, ok_src]
        r, valid = np.stack(blocks), np.stack(valid)
        if not jacobians:
            return r, valid, None
        n = len(d.src)
        q = moved_dst - t  # s R p_src
        a = d.dst - t
        # d moved_dst / d(r, dt, ds) = (-[q]x, I, q); d moved_src = (R^T [a]x / s, -R^T / s, -p)
        dp_dst = np.zeros((n, 3, 7))
        dp_dst[:, :, :3] = -skew(q)
        dp_dst[:, :, 3:6] = np.eye(3)
        dp_dst[:, :, 6] = q
        dp_src = np.zeros((n, 3, 7))
        dp_src[:, :, :3] = np.einsum("ji,njk->nik", R, skew(a)) / s
        dp_src[:, :, 3:6] = -R.T / s
        dp_src[:, :, 6] = -moved_src
        J_dst = np.einsum("nij,njk->nik", projection_jacobian(moved_dst, d.K_dst), dp_dst)
        J_src = np.einsum("nij,njk->nik", projection_jacobian(moved_src, d.K_src), dp_src)
        J = [J_dst / self.sig_dst[:, None, None], J_src / self.sig_src[:, None, None]]
        if self.depth_sigma_rel > 0:
            for dp, sig_z in ((dp_dst, sig_z_dst), (dp_src, sig_z_src)):
                Jz = np.zeros((n, 2, 7))
                Jz[:, 0] = dp[:, 2] / sig_z[:, None]
                J.append(Jz)
        return r, valid, np.stack(J)


def _robust_cost(r: np.ndarray, valid: np.ndarray, huber_k: float) -> float:
    # A point pushed behind a camera costs like a huge error, so such steps are refused.
    e = np.where(valid, np.linalg.norm(r, axis=2), _BEHIND_WHITENED)
    return float(huber(e, huber_k)[0].sum())


def _normal_equations(r, valid, J, huber_k, n_params):
    """(H, g, weighted squared error sum, residual dimensions) of the IRLS-weighted problem."""
    e = np.linalg.norm(r, axis=2)
    w = np.where(valid, huber(e, huber_k)[1], 0.0)
    # one (rows, params) matrix product instead of a 4-index einsum
    J = J[..., :n_params].reshape(-1, n_params)
    w_rows = np.repeat(w.reshape(-1), 2)
    r_rows = np.where(valid[..., None], r, 0.0).reshape(-1)
    H = (J * w_rows[:, None]).T @ J
    g = J.T @ (w_rows * r_rows)
    # pixel blocks have 2 dimensions, the zero-padded depth blocks 1
    dims = 2 * valid[:2].sum() + valid[2:].sum()
    return H, g, float((w * np.where(valid, e, 0.0) ** 2).sum()), int(dims)


def _covariance(state: _Sim3, problem: _Problem) -> tuple[np.ndarray, float]:
    """(7x7 covariance, variance factor) at the solution.

    The inverse information is doubled because the two directions observe the same noise (to
    first order the src-image residual is the dst-image one carried back), so counting both as
    independent halves the variance; and it is inflated by the a-posteriori variance factor when
    the residuals exceed their model (e.g. depth errors of the map points, which it omits).
    """
    n_params = problem.n_params
    r, valid, J = problem.whitened(state, True)
    H, _, chi2, dims = _normal_equations(r, valid, J, problem.huber_k, n_params)
    factor = chi2 / max(dims - n_params, 1)
    cov = np.full((7, 7), np.inf)
    # A (near-)singular information matrix means some direction is unobservable: report inf.
    if np.all(np.isfinite(H)) and np.linalg.cond(H) < 1e12:
        cov = np.zeros((7, 7))
        cov[:n_params, :n_params] = 2.0 * max(factor, 1.0) * np.linalg.inv(H)
    return cov, factor


def _initial_state(T_dst_src, scale, fix_scale: bool) -> _Sim3:
    """The similarity to start from, checked: a rigid 4x4 and a positive scale (1 if fixed)."""
    T0 = np.asarray(T_dst_src, dtype=float)
    if T0.shape != (4, 4) or not np.all(np.isfinite(T0)):
        raise Sim3Error(f"T_dst_src must be a finite 4x4 rigid transform, got shape {T0.shape}")
    R0 = T0[:3, :3]
    if np.abs(R0 @ R0.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(R0) - 1) > 1e-4:
        raise Sim3Error("T_dst_src must hold a rotation: pass the rigid part and the scale apart")
    if not (np.isfinite(scale) and scale > 0):
        raise Sim3Error(f"scale must be finite and > 0, got {scale}")
    if fix_scale and abs(scale - 1.0) > 1e-9:
        raise Sim3Error(f"fix_scale keeps the initial scale, which must then be 1 (got {scale})")
    return _Sim3(R0.copy(), T0[:3, 3].copy(), float(scale))


def refine_sim3(
    T_dst_src: np.ndarray,
    scale: float,
    points_src: np.ndarray,
    uv_src_px: np.ndarray,
    K_src: np.ndarray,
    points_dst: np.ndarray,
    uv_dst_px: np.ndarray,
    K_dst: np.ndarray,
    *,
    active: np.ndarray | None = None,
    sigma_src_px: np.ndarray | float = 1.0,
    sigma_dst_px: np.ndarray | float = 1.0,
    chi2_threshold: float = CHI2_2DOF_99,
    depth_sigma_rel: float = 0.0,
    huber_k: float = 1.345,
    fix_scale: bool = False,
    max_iterations: int = 20,
    rounds: int = 2,
    relative_tol: float = 1e-6,
) -> Sim3RefineResult:
    """Refine ``p_dst = scale R p_src + t`` on both keyframes' reprojection errors.

    Residuals: src points moved into dst against ``uv_dst_px``, dst points moved into src by the
    inverse similarity against ``uv_src_px``, each whitened by its sigma (the observing keypoint's
    ``sigma_*_px`` combined with the moved point's, as in
    :func:`~coop_slam.registration.sim3_ransac.ransac_sim3`) under a Huber loss (``huber_k`` in
    sigmas). With ``depth_sigma_rel`` > 0 each direction also gets a depth
    residual, the moved point's depth against its match's, with sigma ``depth_sigma_rel`` x that
    depth (the pair's combined relative depth noise); 0 is ORB-SLAM's reprojection-only cost. The
    map points stay fixed. ``active`` (e.g. the RANSAC inliers) selects the correspondences of the
    first round; later rounds drop those outside the chi2 gate in either image. Inliers and errors
    of the result cover all N correspondences. ``fix_scale`` needs ``scale`` 1 (metric maps).
    """
    data = make_correspondences(
        points_src,
        points_dst,
        1.0,
        uv_src_px,
        uv_dst_px,
        K_src,
        K_dst,
        sigma_src_px,
        sigma_dst_px,
        chi2_threshold,
    )
    n = len(data.src)
    state0 = _initial_state(T_dst_src, scale, fix_scale)
    if not (huber_k > 0 and max_iterations >= 1 and rounds >= 1 and relative_tol > 0):
        raise Sim3Error("need huber_k > 0, max_iterations >= 1, rounds >= 1, relative_tol > 0")
    if not (np.isfinite(depth_sigma_rel) and depth_sigma_rel >= 0):
        raise Sim3Error("depth_sigma_rel must be finite and >= 0 (0: reprojection only)")
    active = np.ones(n, dtype=bool) if active is None else np.asarray(active, dtype=bool).copy()
    if active.shape != (n,):
        raise Sim3Error(f"active has shape {active.shape}, expected ({n},)")
    n_params = 6 if fix_scale else 7
    rules = LmRules(max_iterations=max_iterations, relative_tol=relative_tol)

    def gate(state: _Sim3) -> np.ndarray:
        err_src, err_dst = _pixel_errors(state, data)
        sig_dst, sig_src = data.residual_sigmas(state.scale)
        return (err_src < np.sqrt(data.chi2) * sig_src) & (err_dst < np.sqrt(data.chi2) * sig_dst)

    state, iterations = state0, 0
    covariance, factor = np.full((7, 7), np.inf), np.nan
    for _ in range(rounds):
        if active.sum() < 3:
            break
        sub = data.subset(active)
        # Residual sigmas depend on the scale: fixed per round so each solve has one cost.
        problem = _Problem(
            sub, *sub.residual_sigmas(state.scale), float(depth_sigma_rel), huber_k, n_params
        )
        outcome = least_squares(problem, state, rules)
        state, iterations = outcome.state, iterations + outcome.iterations
        covariance, factor = _covariance(state, problem)
        inliers = active & gate(state)
        if np.array_equal(inliers, active):
            break
        active = inliers
    err_src, err_dst = _pixel_errors(state, data)
    err_src0, err_dst0 = _pixel_errors(state0, data)
    inliers = gate(state)
    return Sim3RefineResult(
        T_dst_src=state.T(),
        scale=state.scale,
        errors_src_px=err_src,
        errors_dst_px=err_dst,
        inliers=inliers,
        rms_px=rms_both(err_src, err_dst, inliers),
        initial_rms_px=rms_both(err_src0, err_dst0, inliers),
        n_iterations=iterations,
        covariance=covariance,
        variance_factor=factor,
    )
