"""Similarity (Sim(3)) registration of two keyframes' map points, for monocular maps.

A monocular robot's map has no metric scale, so a merge or loop closure involving one estimates a
similarity ``p_a = scale * R p_b + t`` instead of a rigid transform. It is kept here as
``(T_a_b, scale)``: ``T_a_b`` is the rigid part (a proper 4x4 holding R and t, so the rigid helpers
in :mod:`coop_slam.geometry` apply to it) and ``scale`` multiplies the rotated point before the
translation; :func:`sim3_matrix` gives the 4x4 ``[[scale R, t], [0, 1]]``.

* :func:`ransac_sim3`: RANSAC over 3-point minimal sets with Umeyama *with scale*, batched and
  seeded like :func:`~coop_slam.registration.ransac.ransac_rigid`. With pixels and intrinsics the
  inlier test is that of ORB-SLAM's Sim3Solver: each point, moved into the other keyframe, must
  reproject onto that keyframe's observation (a chi2 bound per image), except that the bound's
  sigma also counts the moved point's own noise; without pixels it is a 3D distance relative to
  depth, since the scale of either map is unknown.
* :func:`refine_sim3`: Huber-robust Levenberg-Marquardt on the 7 parameters (rotation, translation,
  log-scale) minimising both reprojection errors with the map points held fixed (as ORB-SLAM's
  OptimizeSim3), optionally with relative depth residuals, and the covariance of the similarity
  at the solution (calibrated: on the synthetic tests its NEES is close to the 7 expected).
* :func:`estimate_sim3`: both on two keyframes' matched map points plus an acceptance test,
  returning a :class:`Sim3Result` (rejection is a result, invalid input raises :class:`Sim3Error`).

GTSAM 4.2's ``gtsam.Similarity3(R, t, s)`` maps ``p -> s (R p + t)``: our ``(T, scale)`` is
``gtsam.Similarity3(R, t / scale, scale)``, and its ``matrix()`` is ``[[R, t], [0, 1/s]]``. The
Python wrapper has neither Lie-group operations nor factors or ``Values`` support for it, hence the
small numpy solver here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..config import require
from ..geometry import exp_so3, skew
from .ba import huber, rms_both, worst_sigma
from .camera import RegistrationError, check_intrinsics, check_points, projection_jacobian
from .ransac import required_iterations
from .umeyama import umeyama_batch

# 99 % quantile of chi2 with 2 dof: the per-image gate of ORB-SLAM's Sim3Solver (in sigma^2 units).
CHI2_2DOF_99 = 9.21
_MIN_DEPTH = 1e-9  # a moved point at or behind this depth cannot be projected
_BEHIND_WHITENED = 1e3  # robust-cost stand-in for the error of a point pushed behind a camera


class Sim3Error(RegistrationError):
    """Invalid input to similarity estimation (shapes, NaN, points behind a camera, too few)."""


# --- similarity helpers ---------------------------------------------------------------------------
def sim3_matrix(T_dst_src: np.ndarray, scale: float) -> np.ndarray:
    """4x4 ``[[scale R, t], [0, 1]]`` of a similarity given as rigid part and scale."""
    S = np.array(T_dst_src, dtype=float, copy=True)
    S[:3, :3] *= scale
    return S


def sim3_inverse(T_dst_src: np.ndarray, scale: float) -> tuple[np.ndarray, float]:
    """``(T_src_dst, 1 / scale)``: p_src = R^T (p_dst - t) / scale."""
    R, t = T_dst_src[:3, :3], T_dst_src[:3, 3]
    T_src_dst = np.eye(4)
    T_src_dst[:3, :3] = R.T
    T_src_dst[:3, 3] = -R.T @ t / scale
    return T_src_dst, 1.0 / scale


def sim3_transform_points(T_dst_src: np.ndarray, scale: float, points_src: np.ndarray):
    """(N, 3) points of frame src moved into frame dst: ``scale * R p + t``."""
    points_src = np.asarray(points_src, dtype=float).reshape(-1, 3)
    return scale * points_src @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]


# --- input checks ---------------------------------------------------------------------------------
def _points(points, name: str, n: int | None = None) -> np.ndarray:
    try:
        arr = check_points(points, name, n)
    except RegistrationError as exc:
        raise Sim3Error(str(exc)) from None
    behind = ~(arr[:, 2] > 0)
    if behind.any():
        raise Sim3Error(
            f"{name}: {int(behind.sum())} point(s) with depth z <= 0 (first: row "
            f"{int(np.argmax(behind))}); give each point in its keyframe's camera frame and drop "
            "points behind the camera"
        )
    return arr


def _pixels(uv_px, name: str, n: int) -> np.ndarray:
    arr = np.asarray(uv_px, dtype=float)
    if arr.shape != (n, 2):
        raise Sim3Error(f"{name} has shape {arr.shape}, expected ({n}, 2): one pixel per point")
    if not np.all(np.isfinite(arr)):
        raise Sim3Error(f"{name} contains NaN or inf")
    return arr


def _sigmas(sigma_px, name: str, n: int) -> np.ndarray:
    try:
        arr = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,)).copy()
    except ValueError:
        raise Sim3Error(f"{name} must be one value or one per point ({n})") from None
    if not np.all(np.isfinite(arr)) or (arr <= 0).any():
        raise Sim3Error(f"{name} must be finite and > 0")
    return arr


def _intrinsics(K, name: str) -> np.ndarray:
    try:
        return check_intrinsics(K, name)
    except RegistrationError as exc:
        raise Sim3Error(str(exc)) from None


def _require_three(n: int) -> None:
    if n < 3:
        raise Sim3Error(
            f"a similarity needs at least 3 correspondences, got {n}; match more map points "
            "(ORB-SLAM asks for 20) before estimating one"
        )


# --- batched residuals ----------------------------------------------------------------------------
def _project(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 2) pixels and (...,) bool in-front mask of (..., 3) camera-frame points."""
    z = points_cam[..., 2]
    valid = z > _MIN_DEPTH
    z_safe = np.where(valid, z, 1.0)
    x, y = points_cam[..., 0] / z_safe, points_cam[..., 1] / z_safe
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    return np.stack([u, v], axis=-1), valid


@dataclass
class _Data:
    """Correspondences and their noise; ``uv_src is None`` selects the 3D gate relative to depth."""

    src: np.ndarray  # (N, 3) points in the src camera frame
    dst: np.ndarray
    uv_src: np.ndarray | None  # (N, 2) observed pixels of the points in their own keyframe
    uv_dst: np.ndarray | None
    K_src: np.ndarray | None
    K_dst: np.ndarray | None
    sig_src: np.ndarray | None  # (N,) keypoint noise [px]
    sig_dst: np.ndarray | None
    chi2: float  # per-image gate in squared sigmas (pixel mode)
    rel_threshold: float  # 3D gate as a fraction of the depth (3D mode)
    thr3d_src: np.ndarray  # (N,) the gate as a 3D distance at the point's depth (sample checks)
    thr3d_dst: np.ndarray

    def subset(self, mask: np.ndarray) -> _Data:
        def pick(x):
            return None if x is None else x[mask]

        return _Data(
            self.src[mask],
            self.dst[mask],
            pick(self.uv_src),
            pick(self.uv_dst),
            self.K_src,
            self.K_dst,
            pick(self.sig_src),
            pick(self.sig_dst),
            self.chi2,
            self.rel_threshold,
            self.thr3d_src[mask],
            self.thr3d_dst[mask],
        )

    def residual_sigmas(self, scale) -> tuple[np.ndarray, np.ndarray]:
        """Sigmas [px] of the dst-image and src-image residuals at ``scale`` ((H,) or scalar).

        A moved point carries its own keyframe's keypoint noise along: a src point's lateral error
        of ``z_src sig_src / f_src`` becomes ``scale`` times that in dst units, i.e. ``rho`` dst
        pixels per src pixel at the point's depth in dst. Without it the gate (ORB-SLAM's, on the
        observing keypoint's sigma alone) rejects about a third of the true matches at equal noise
        in both keyframes, and the covariance comes out too small.
        """
        scale = np.asarray(scale, dtype=float)[..., None]
        f_src = 0.5 * (self.K_src[0, 0] + self.K_src[1, 1])
        f_dst = 0.5 * (self.K_dst[0, 0] + self.K_dst[1, 1])
        rho = scale * self.src[:, 2] * f_dst / (f_src * self.dst[:, 2])
        sig_dst = np.sqrt(self.sig_dst**2 + (self.sig_src * rho) ** 2)
        sig_src = np.sqrt(self.sig_src**2 + (self.sig_dst / rho) ** 2)
        return sig_dst, sig_src

    def normalized_errors(self, T: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """(H, N) worse of the two directions' squared errors over their gate (< 1: inlier)."""
        R, t = T[:, :3, :3], T[:, :3, 3]
        moved_dst = scale[:, None, None] * np.einsum("hij,nj->hni", R, self.src) + t[:, None]
        moved_src = np.einsum("hji,hnj->hni", R, self.dst[None] - t[:, None]) / scale[:, None, None]
        if self.uv_src is None:
            e2_dst = ((moved_dst - self.dst) ** 2).sum(axis=2)
            e2_src = ((moved_src - self.src) ** 2).sum(axis=2)
            return np.maximum(
                e2_dst / (self.rel_threshold * self.dst[:, 2]) ** 2,
                e2_src / (self.rel_threshold * self.src[:, 2]) ** 2,
            )
        uv_dst, ok_dst = _project(moved_dst, self.K_dst)
        uv_src, ok_src = _project(moved_src, self.K_src)
        e2_dst = np.where(ok_dst, ((uv_dst - self.uv_dst) ** 2).sum(axis=2), np.inf)
        e2_src = np.where(ok_src, ((uv_src - self.uv_src) ** 2).sum(axis=2), np.inf)
        sig_dst, sig_src = self.residual_sigmas(scale)
        return np.maximum(e2_dst / sig_dst**2, e2_src / sig_src**2) / self.chi2


def _make_data(
    points_src,
    points_dst,
    relative_threshold,
    uv_src_px,
    uv_dst_px,
    K_src,
    K_dst,
    sigma_src_px,
    sigma_dst_px,
    chi2_threshold,
) -> _Data:
    src = _points(points_src, "points_src")
    dst = _points(points_dst, "points_dst", len(src))
    n = len(src)
    _require_three(n)
    given = [x is not None for x in (uv_src_px, uv_dst_px, K_src, K_dst)]
    if any(given) and not all(given):
        raise Sim3Error(
            "the reprojection gate needs uv_src_px, uv_dst_px, K_src and K_dst together; "
            "give all four, or none for the 3D gate relative to depth"
        )
    if all(given):
        if not (np.isfinite(chi2_threshold) and chi2_threshold > 0):
            raise Sim3Error("chi2_threshold must be finite and > 0 (9.21: 2-dof 99 %)")
        K_src, K_dst = _intrinsics(K_src, "K_src"), _intrinsics(K_dst, "K_dst")
        sig_src = _sigmas(sigma_src_px, "sigma_src_px", n)
        sig_dst = _sigmas(sigma_dst_px, "sigma_dst_px", n)
        # A pixel gate g at depth z is a lateral distance g z / f.
        f_src, f_dst = 0.5 * (K_src[0, 0] + K_src[1, 1]), 0.5 * (K_dst[0, 0] + K_dst[1, 1])
        gate = np.sqrt(chi2_threshold)
        return _Data(
            src,
            dst,
            _pixels(uv_src_px, "uv_src_px", n),
            _pixels(uv_dst_px, "uv_dst_px", n),
            K_src,
            K_dst,
            sig_src,
            sig_dst,
            float(chi2_threshold),
            np.nan,
            gate * sig_src * src[:, 2] / f_src,
            gate * sig_dst * dst[:, 2] / f_dst,
        )
    if not (np.isfinite(relative_threshold) and relative_threshold > 0):
        raise Sim3Error("relative_threshold must be finite and > 0 (error / depth, e.g. 0.05)")
    return _Data(
        src,
        dst,
        None,
        None,
        None,
        None,
        None,
        None,
        np.nan,
        float(relative_threshold),
        relative_threshold * src[:, 2],
        relative_threshold * dst[:, 2],
    )


# --- RANSAC ---------------------------------------------------------------------------------------
@dataclass
class Sim3RansacResult:
    """``T_dst_src`` (rigid part) is None and ``scale`` NaN when no usable sample existed."""

    T_dst_src: np.ndarray | None
    scale: float
    inliers: np.ndarray  # (N,) bool
    n_iterations: int

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def ransac_sim3(
    points_src: np.ndarray,
    points_dst: np.ndarray,
    relative_threshold: float = 0.05,
    *,
    uv_src_px: np.ndarray | None = None,
    uv_dst_px: np.ndarray | None = None,
    K_src: np.ndarray | None = None,
    K_dst: np.ndarray | None = None,
    sigma_src_px: np.ndarray | float = 1.0,
    sigma_dst_px: np.ndarray | float = 1.0,
    chi2_threshold: float = CHI2_2DOF_99,
    fix_scale: bool = False,
    confidence: float = 0.999,
    max_iterations: int = 2000,
    batch_size: int = 64,
    seed: int = 0,
    refine_rounds: int = 3,
    min_edge_factor: float = 2.0,
) -> Sim3RansacResult:
    """Robust similarity ``p_dst = scale R p_src + t`` from (N, 3) correspondences.

    Points are in their keyframes' camera frames (z > 0). With ``uv_*_px`` (each point's observed
    pixel in its own keyframe) and ``K_*``, a correspondence is an inlier when its squared
    reprojection error in *both* images is below ``chi2_threshold * sigma^2``, sigma combining the
    observing keypoint's noise with the moved point's (``sigma_*_px`` per point, e.g. from the
    keypoint's pyramid level; see ``_Data.residual_sigmas``); otherwise when its 3D error in both
    frames is below ``relative_threshold`` x the point's depth. ``fix_scale``: scale held at 1
    (metric maps).

    Minimal samples whose edges are shorter than ``min_edge_factor`` x the summed gates of their
    ends (as 3D distances at the points' depths) are skipped, in both frames: such a tight or
    collinear triple fixes rotation and scale too poorly to be worth scoring. The best hypothesis
    is refined by weighted Umeyama on its inliers for ``refine_rounds``. Deterministic per seed.
    """
    data = _make_data(
        points_src,
        points_dst,
        relative_threshold,
        uv_src_px,
        uv_dst_px,
        K_src,
        K_dst,
        sigma_src_px,
        sigma_dst_px,
        chi2_threshold,
    )
    if not 0 < confidence < 1 or max_iterations < 1 or batch_size < 1 or refine_rounds < 0:
        raise Sim3Error("RANSAC needs 0 < confidence < 1 and positive iteration counts")
    if not min_edge_factor >= 0:
        raise Sim3Error("min_edge_factor must be >= 0")
    src, dst = data.src, data.dst
    n = len(src)
    # Umeyama's residual lives in dst: weight it by the inverse squared gate there so near points
    # (small gates) count as much as their tighter reprojection bound says.
    weights = 1.0 / data.thr3d_dst**2

    best_T, best_scale, best_cost = None, np.nan, np.inf
    best_inliers = np.zeros(n, dtype=bool)

    def consider(T_batch: np.ndarray, scale_batch: np.ndarray) -> None:
        nonlocal best_T, best_scale, best_cost, best_inliers
        err = data.normalized_errors(T_batch, scale_batch)
        cost = np.minimum(err, 1.0).sum(axis=1)
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost, best_T, best_scale = cost[k], T_batch[k], float(scale_batch[k])
            best_inliers = err[k] < 1.0

    rng = np.random.default_rng(seed)
    iterations, needed = 0, float(max_iterations)
    while iterations < min(needed, max_iterations):
        idx = rng.integers(0, n, size=(batch_size, 3))
        iterations += batch_size
        ok = (idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])
        for pts, thr in ((src[idx], data.thr3d_src), (dst[idx], data.thr3d_dst)):
            edges = np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2)
            area = np.linalg.norm(np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]), axis=1)
            ok &= area > 1e-2 * np.max(edges, axis=1) ** 2 + 1e-12
            edge_tol = thr[idx] + thr[np.roll(idx, 1, axis=1)]
            ok &= np.all(edges >= min_edge_factor * edge_tol, axis=1)
        if not ok.any():
            continue
        T_batch, scale_batch = umeyama_batch(src[idx[ok]], dst[idx[ok]], with_scale=not fix_scale)
        good = np.isfinite(scale_batch) & (scale_batch > 1e-12)
        if not good.any():
            continue
        consider(T_batch[good], scale_batch[good])
        if best_inliers.any():
            needed = required_iterations(best_inliers.mean(), confidence)

    if best_T is None:
        return Sim3RansacResult(None, np.nan, best_inliers, iterations)
    for _ in range(refine_rounds):
        if best_inliers.sum() < 3:
            break
        T_ref, scale_ref = umeyama_batch(
            src[best_inliers][None],
            dst[best_inliers][None],
            weights[best_inliers][None],
            with_scale=not fix_scale,
        )
        if not (np.isfinite(scale_ref[0]) and scale_ref[0] > 1e-12):
            break
        inliers = data.normalized_errors(T_ref, scale_ref)[0] < 1.0
        if inliers.sum() < best_inliers.sum():
            break
        best_T, best_scale, best_inliers = T_ref[0], float(scale_ref[0]), inliers
    return Sim3RansacResult(best_T, best_scale, best_inliers, iterations)


# --- refinement -----------------------------------------------------------------------------------
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

    def moved(self, data: _Data) -> tuple[np.ndarray, np.ndarray]:
        """(src points in dst, dst points in src)."""
        moved_dst = self.scale * data.src @ self.R.T + self.t
        moved_src = (data.dst - self.t) @ self.R / self.scale  # R^T (p - t) / s, row-wise
        return moved_dst, moved_src


def _pixel_errors(state: _Sim3, data: _Data) -> tuple[np.ndarray, np.ndarray]:
    """(N,) reprojection errors [px] in the src and the dst image (inf when behind)."""
    moved_dst, moved_src = state.moved(data)
    uv_dst, ok_dst = _project(moved_dst, data.K_dst)
    uv_src, ok_src = _project(moved_src, data.K_src)
    err_dst = np.where(ok_dst, np.linalg.norm(uv_dst - data.uv_dst, axis=1), np.inf)
    err_src = np.where(ok_src, np.linalg.norm(uv_src - data.uv_src, axis=1), np.inf)
    return err_src, err_dst


@dataclass
class _Problem:
    """One solve: correspondences, residual sigmas (held fixed while solving), depth term."""

    data: _Data
    sig_dst: np.ndarray  # (N,) sigma of the dst-image residual [px]
    sig_src: np.ndarray
    depth_sigma_rel: float  # 0: reprojection only

    def whitened(self, state: _Sim3, jacobians: bool):
        """Whitened residual blocks (M, N, 2), in-front mask (M, N) and, when asked, Jacobians
        (M, N, 2, 7) of the update (r, dt, log s). Blocks: src points in the dst image, dst points
        in the src image, then (with the depth term) their depth errors, padded with a zero."""
        d = self.data
        R, t, s = state.R, state.t, state.scale
        moved_dst, moved_src = state.moved(d)
        uv_dst, ok_dst = _project(moved_dst, d.K_dst)
        uv_src, ok_src = _project(moved_src, d.K_src)
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


def _solve(state: _Sim3, problem: _Problem, huber_k, n_params, max_it, rel_tol):
    """Levenberg-Marquardt -> (state, accepted steps)."""
    r, valid, J = problem.whitened(state, True)
    cost = _robust_cost(r, valid, huber_k)
    lam, iterations = 1e-4, 0
    for _ in range(max_it):
        H, g, _, _ = _normal_equations(r, valid, J, huber_k, n_params)
        improved = False
        while lam < 1e10:
            A = H + lam * np.diag(np.maximum(np.diag(H), 1e-12))
            try:
                delta = np.linalg.solve(A, -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            candidate = state.retract(delta)
            cost_c = _robust_cost(*problem.whitened(candidate, False)[:2], huber_k)
            if cost_c < cost:
                improved = True
                break
            lam *= 10
        if not improved:
            break
        decrease = cost - cost_c
        state, cost, iterations = candidate, cost_c, iterations + 1
        lam = max(lam / 10, 1e-12)
        r, valid, J = problem.whitened(state, True)
        if decrease <= rel_tol * cost:
            break
    return state, iterations


def _covariance(state: _Sim3, problem: _Problem, huber_k, n_params) -> tuple[np.ndarray, float]:
    """(7x7 covariance, variance factor) at the solution.

    The inverse information is doubled because the two directions observe the same noise (to
    first order the src-image residual is the dst-image one carried back), so counting both as
    independent halves the variance; and it is inflated by the a-posteriori variance factor when
    the residuals exceed their model (e.g. depth errors of the map points, which it omits).
    """
    r, valid, J = problem.whitened(state, True)
    H, _, chi2, dims = _normal_equations(r, valid, J, huber_k, n_params)
    factor = chi2 / max(dims - n_params, 1)
    cov = np.full((7, 7), np.inf)
    # A (near-)singular information matrix means some direction is unobservable: report inf.
    if np.all(np.isfinite(H)) and np.linalg.cond(H) < 1e12:
        cov = np.zeros((7, 7))
        cov[:n_params, :n_params] = 2.0 * max(factor, 1.0) * np.linalg.inv(H)
    return cov, factor


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
    ``sigma_*_px`` combined with the moved point's, as in :func:`ransac_sim3`) under a Huber loss
    (``huber_k`` in sigmas). With ``depth_sigma_rel`` > 0 each direction also gets a depth
    residual, the moved point's depth against its match's, with sigma ``depth_sigma_rel`` x that
    depth (the pair's combined relative depth noise); 0 is ORB-SLAM's reprojection-only cost. The
    map points stay fixed. ``active`` (e.g. the RANSAC inliers) selects the correspondences of the
    first round; later rounds drop those outside the chi2 gate in either image. Inliers and errors
    of the result cover all N correspondences. ``fix_scale`` needs ``scale`` 1 (metric maps).
    """
    data = _make_data(
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
    if not (huber_k > 0 and max_iterations >= 1 and rounds >= 1 and relative_tol > 0):
        raise Sim3Error("need huber_k > 0, max_iterations >= 1, rounds >= 1, relative_tol > 0")
    if not (np.isfinite(depth_sigma_rel) and depth_sigma_rel >= 0):
        raise Sim3Error("depth_sigma_rel must be finite and >= 0 (0: reprojection only)")
    active = np.ones(n, dtype=bool) if active is None else np.asarray(active, dtype=bool).copy()
    if active.shape != (n,):
        raise Sim3Error(f"active has shape {active.shape}, expected ({n},)")
    n_params = 6 if fix_scale else 7

    def gate(state: _Sim3) -> np.ndarray:
        err_src, err_dst = _pixel_errors(state, data)
        sig_dst, sig_src = data.residual_sigmas(state.scale)
        return (err_src < np.sqrt(data.chi2) * sig_src) & (err_dst < np.sqrt(data.chi2) * sig_dst)

    state0 = _Sim3(R0.copy(), T0[:3, 3].copy(), float(scale))
    state, iterations = state0, 0
    covariance, factor = np.full((7, 7), np.inf), np.nan
    for _ in range(rounds):
        if active.sum() < 3:
            break
        sub = data.subset(active)
        # Residual sigmas depend on the scale: fixed per round so each solve has one cost.
        problem = _Problem(sub, *sub.residual_sigmas(state.scale), float(depth_sigma_rel))
        state, its = _solve(state, problem, huber_k, n_params, max_iterations, relative_tol)
        iterations += its
        covariance, factor = _covariance(state, problem, huber_k, n_params)
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


# --- two-keyframe estimate ------------------------------------------------------------------------
@dataclass
class Sim3Config:
    """Parameters of :func:`estimate_sim3` (defaults follow ORB-SLAM's loop-closing Sim3)."""

    pixel_sigma_px: float = 1.0  # keypoint noise when no per-point sigmas are given
    chi2_threshold: float = CHI2_2DOF_99  # per-image gate in sigma^2 (RANSAC and refinement)
    fix_scale: bool = False  # True when both maps are metric (stereo / RGB-D): the rigid case
    # RANSAC
    ransac_confidence: float = 0.999
    ransac_max_iterations: int = 2000
    ransac_batch: int = 64
    ransac_refine_rounds: int = 3
    ransac_min_edge_factor: float = 2.0  # minimal-sample edges >= this x summed 3D gates
    seed: int = 0
    # refinement
    refine_huber_k: float = 1.345  # whitened units: bends at k * sigma
    # combined relative depth noise of a matched pair of map points for the refinement's depth
    # residuals; 0 leaves them out (ORB-SLAM: reprojection only)
    refine_depth_sigma_rel: float = 0.0
    refine_max_iterations: int = 20
    refine_rounds: int = 2
    refine_relative_tol: float = 1e-6
    # acceptance
    accept_min_inliers: int = 20
    # RMS per-image error of the inliers; the map points are held fixed, so each residual carries
    # both keyframes' noise: about 2 px (2D norm) at 1 px keypoint noise in each
    accept_max_residual_px: float = 3.0
    accept_min_inlier_ratio: float = 0.2  # final inliers / correspondences
    # marginal standard deviations (worst axis) of the refined similarity: reject solutions that
    # fit but are ill-conditioned. Translation is relative to the median inlier depth in A, since
    # A's units need not be metres.
    accept_max_sigma_rot_deg: float = 0.5
    accept_max_sigma_trans_rel: float = 0.02
    # 3 %, not 2: two ground robots' monocular maps of corridor walls (one depth, so scale and
    # translation along the view trade) had no candidate under 2 % (revisit world: 2.1-10 %),
    # and merged at 3 % as when their keyframes were denser
    accept_max_sigma_scale_rel: float = 0.03

    def validate(self) -> None:
        require(self.pixel_sigma_px > 0, "pixel_sigma_px must be > 0")
        require(self.chi2_threshold > 0, "chi2_threshold must be > 0 (9.21: 2-dof 99 %)")
        require(0 < self.ransac_confidence < 1, "ransac_confidence must be in (0, 1)")
        for name in (
            "ransac_max_iterations",
            "ransac_batch",
            "refine_max_iterations",
            "refine_rounds",
        ):
            require(getattr(self, name) >= 1, f"{name} must be >= 1")
        require(self.ransac_refine_rounds >= 0, "ransac_refine_rounds must be >= 0")
        require(self.ransac_min_edge_factor >= 0, "ransac_min_edge_factor must be >= 0")
        require(self.refine_huber_k > 0, "refine_huber_k must be > 0")
        require(self.refine_depth_sigma_rel >= 0, "refine_depth_sigma_rel must be >= 0 (0: off)")
        require(self.refine_relative_tol > 0, "refine_relative_tol must be > 0")
        require(self.accept_min_inliers >= 3, "accept_min_inliers must be >= 3")
        require(self.accept_max_residual_px > 0, "accept_max_residual_px must be > 0")
        require(0 <= self.accept_min_inlier_ratio <= 1, "accept_min_inlier_ratio must be in [0, 1]")
        require(self.accept_max_sigma_rot_deg > 0, "accept_max_sigma_rot_deg must be > 0")
        require(self.accept_max_sigma_trans_rel > 0, "accept_max_sigma_trans_rel must be > 0")
        require(self.accept_max_sigma_scale_rel > 0, "accept_max_sigma_scale_rel must be > 0")


@dataclass
class Sim3Result:
    """Outcome of :func:`estimate_sim3`: ``p_a = scale * R p_b + t`` with ``T_a_b`` = (R, t).

    ``T_a_b`` / ``scale`` are the best estimate even when rejected (None / NaN if there is none).
    """

    accepted: bool
    reason: str
    T_a_b: np.ndarray | None = None
    scale: float = np.nan
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (N,) bool
    residual_px: float = np.nan  # RMS per-image reprojection error of the inliers
    initial_residual_px: float = np.nan  # same at the RANSAC estimate
    sigma_rot_deg: float = np.inf  # marginal std of the rotation (worst axis)
    sigma_trans: float = np.inf  # marginal std of the translation, in A's length units
    sigma_scale_rel: float = np.inf  # marginal std of log(scale)
    covariance: np.ndarray = field(default_factory=lambda: np.full((7, 7), np.inf))
    n_correspondences: int = 0
    inlier_ratio: float = 0.0
    ransac_inliers: int = 0
    ransac_iterations: int = 0
    timings_ms: dict = field(default_factory=dict)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def sim3_a_b(self) -> np.ndarray | None:
        """4x4 ``[[scale R, t], [0, 1]]`` (None without an estimate)."""
        return None if self.T_a_b is None else sim3_matrix(self.T_a_b, self.scale)


def estimate_sim3(
    points_a_cam: np.ndarray,
    uv_a_px: np.ndarray,
    K_a: np.ndarray,
    points_b_cam: np.ndarray,
    uv_b_px: np.ndarray,
    K_b: np.ndarray,
    config: Sim3Config | None = None,
    *,
    sigma_a_px: np.ndarray | float | None = None,
    sigma_b_px: np.ndarray | float | None = None,
) -> Sim3Result:
    """Similarity ``T_a_b, scale`` between two keyframes from N matched map points.

    Row i is one correspondence: map point i in A's camera frame with its observed pixel in A, and
    its match in B's camera frame with its pixel in B. ``sigma_*_px`` (one or per point, e.g. the
    keypoint's pyramid scale) default to ``config.pixel_sigma_px``. Pipeline: RANSAC (reprojection
    gate in both images) -> robust refinement -> acceptance on inlier count, residual, inlier ratio
    and the marginal sigmas. Invalid input raises :class:`Sim3Error`.
    """
    cfg = config if config is not None else Sim3Config()
    if not isinstance(cfg, Sim3Config):
        raise Sim3Error(f"config must be a Sim3Config, got {type(cfg).__name__}")
    cfg.validate()
    t0 = time.perf_counter()
    timings: dict = {}
    points_a = _points(points_a_cam, "points_a_cam")
    n = len(points_a)
    points_b = _points(points_b_cam, "points_b_cam", n)
    uv_a, uv_b = _pixels(uv_a_px, "uv_a_px", n), _pixels(uv_b_px, "uv_b_px", n)
    K_a, K_b = _intrinsics(K_a, "K_a"), _intrinsics(K_b, "K_b")
    sig_a = _sigmas(cfg.pixel_sigma_px if sigma_a_px is None else sigma_a_px, "sigma_a_px", n)
    sig_b = _sigmas(cfg.pixel_sigma_px if sigma_b_px is None else sigma_b_px, "sigma_b_px", n)

    def finish(reason: str, **fields) -> Sim3Result:
        timings["total"] = 1e3 * (time.perf_counter() - t0)
        fields.setdefault("inliers", np.zeros(n, dtype=bool))
        return Sim3Result(
            reason == "accepted", reason, n_correspondences=n, timings_ms=timings, **fields
        )

    if n < cfg.accept_min_inliers:
        return finish(f"too few correspondences ({n} < {cfg.accept_min_inliers})")
    # B is the source: RANSAC's T_dst_src is then T_a_b.
    ransac = ransac_sim3(
        points_b,
        points_a,
        uv_src_px=uv_b,
        uv_dst_px=uv_a,
        K_src=K_b,
        K_dst=K_a,
        sigma_src_px=sig_b,
        sigma_dst_px=sig_a,
        chi2_threshold=cfg.chi2_threshold,
        fix_scale=cfg.fix_scale,
        confidence=cfg.ransac_confidence,
        max_iterations=cfg.ransac_max_iterations,
        batch_size=cfg.ransac_batch,
        seed=cfg.seed,
        refine_rounds=cfg.ransac_refine_rounds,
        min_edge_factor=cfg.ransac_min_edge_factor,
    )
    timings["ransac"] = 1e3 * (time.perf_counter() - t0)
    common = dict(ransac_inliers=ransac.n_inliers, ransac_iterations=ransac.n_iterations)
    if ransac.T_dst_src is None:
        return finish(
            "no usable minimal sample: the points are collinear, coincident or too close together",
            **common,
        )
    if ransac.n_inliers < cfg.accept_min_inliers:
        return finish(
            f"RANSAC found too few inliers ({ransac.n_inliers} < {cfg.accept_min_inliers})",
            T_a_b=ransac.T_dst_src,
            scale=ransac.scale,
            inliers=ransac.inliers,
            **common,
        )
    t1 = time.perf_counter()
    ref = refine_sim3(
        ransac.T_dst_src,
        ransac.scale,
        points_b,
        uv_b,
        K_b,
        points_a,
        uv_a,
        K_a,
        active=ransac.inliers,
        sigma_src_px=sig_b,
        sigma_dst_px=sig_a,
        chi2_threshold=cfg.chi2_threshold,
        depth_sigma_rel=cfg.refine_depth_sigma_rel,
        huber_k=cfg.refine_huber_k,
        fix_scale=cfg.fix_scale,
        max_iterations=cfg.refine_max_iterations,
        rounds=cfg.refine_rounds,
        relative_tol=cfg.refine_relative_tol,
    )
    timings["refine"] = 1e3 * (time.perf_counter() - t1)
    n_inl = ref.n_inliers
    ratio = n_inl / n
    depth_a = float(np.median(points_a[ref.inliers, 2])) if n_inl else np.nan
    sigma_trans_rel = ref.sigma_trans / depth_a if n_inl else np.inf
    if n_inl < cfg.accept_min_inliers:
        reason = f"too few inliers after refinement ({n_inl} < {cfg.accept_min_inliers})"
    elif not ref.rms_px <= cfg.accept_max_residual_px:
        reason = f"residual {ref.rms_px:.2f} px > {cfg.accept_max_residual_px} px"
    elif ratio < cfg.accept_min_inlier_ratio:
        reason = f"inlier ratio {ratio:.2f} < {cfg.accept_min_inlier_ratio}"
    elif not ref.sigma_rot_deg <= cfg.accept_max_sigma_rot_deg:
        reason = f"ill-conditioned: rotation sigma {ref.sigma_rot_deg:.2f} deg"
    elif not sigma_trans_rel <= cfg.accept_max_sigma_trans_rel:
        reason = f"ill-conditioned: translation sigma {sigma_trans_rel:.1%} of the median depth"
    elif not ref.sigma_scale_rel <= cfg.accept_max_sigma_scale_rel:
        reason = f"ill-conditioned: scale sigma {ref.sigma_scale_rel:.1%}"
    else:
        reason = "accepted"
    return finish(
        reason,
        T_a_b=ref.T_dst_src,
        scale=ref.scale,
        inliers=ref.inliers,
        residual_px=ref.rms_px,
        initial_residual_px=ref.initial_rms_px,
        sigma_rot_deg=ref.sigma_rot_deg,
        sigma_trans=ref.sigma_trans,
        sigma_scale_rel=ref.sigma_scale_rel,
        covariance=ref.covariance,
        inlier_ratio=ratio,
        **common,
    )
