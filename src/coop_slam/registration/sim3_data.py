"""The correspondences of a similarity (Sim(3)) estimate between two keyframes' map points --
points, pixels, intrinsics and keypoint noise -- with their input checks and the batched inlier
test that RANSAC (:mod:`.sim3_ransac`), the refinement (:mod:`.sim3_refine`) and the estimate
(:mod:`.sim3`) share. Invalid input raises :class:`Sim3Error`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import RegistrationError, check_intrinsics, check_points

# 99 % quantile of chi2 with 2 dof: the per-image gate of ORB-SLAM's Sim3Solver (in sigma^2 units).
CHI2_2DOF_99 = 9.21
_MIN_DEPTH = 1e-9  # a moved point at or behind this depth cannot be projected


class Sim3Error(RegistrationError):
    """Invalid input to similarity estimation (shapes, NaN, points behind a camera, too few)."""


# --- input checks ---------------------------------------------------------------------------------
def check_points_in_front(points, name: str, n: int | None = None) -> np.ndarray:
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


def check_pixels(uv_px, name: str, n: int) -> np.ndarray:
    arr = np.asarray(uv_px, dtype=float)
    if arr.shape != (n, 2):
        raise Sim3Error(f"{name} has shape {arr.shape}, expected ({n}, 2): one pixel per point")
    if not np.all(np.isfinite(arr)):
        raise Sim3Error(f"{name} contains NaN or inf")
    return arr


def check_sigmas(sigma_px, name: str, n: int) -> np.ndarray:
    try:
        arr = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,)).copy()
    except ValueError:
        raise Sim3Error(f"{name} must be one value or one per point ({n})") from None
    if not np.all(np.isfinite(arr)) or (arr <= 0).any():
        raise Sim3Error(f"{name} must be finite and > 0")
    return arr


def check_intrinsics_sim3(K, name: str) -> np.ndarray:
    try:
        return check_intrinsics(K, name)
    except RegistrationError as exc:
        raise Sim3Error(str(exc)) from None


def require_three(n: int) -> None:
    if n < 3:
        raise Sim3Error(
            f"a similarity needs at least 3 correspondences, got {n}; match more map points "
            "(ORB-SLAM asks for 20) before estimating one"
        )


# --- batched residuals ----------------------------------------------------------------------------
def project_in_front(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 2) pixels and (...,) bool in-front mask of (..., 3) camera-frame points."""
    z = points_cam[..., 2]
    valid = z > _MIN_DEPTH
    z_safe = np.where(valid, z, 1.0)
    x, y = points_cam[..., 0] / z_safe, points_cam[..., 1] / z_safe
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    return np.stack([u, v], axis=-1), valid


@dataclass
class Correspondences:
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

    def subset(self, mask: np.ndarray) -> Correspondences:
        def pick(x):
            return None if x is None else x[mask]

        return Correspondences(
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
        uv_dst, ok_dst = project_in_front(moved_dst, self.K_dst)
        uv_src, ok_src = project_in_front(moved_src, self.K_src)
        e2_dst = np.where(ok_dst, ((uv_dst - self.uv_dst) ** 2).sum(axis=2), np.inf)
        e2_src = np.where(ok_src, ((uv_src - self.uv_src) ** 2).sum(axis=2), np.inf)
        sig_dst, sig_src = self.residual_sigmas(scale)
        return np.maximum(e2_dst / sig_dst**2, e2_src / sig_src**2) / self.chi2


def make_correspondences(
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
) -> Correspondences:
    src = check_points_in_front(points_src, "points_src")
    dst = check_points_in_front(points_dst, "points_dst", len(src))
    n = len(src)
    require_three(n)
    given = [x is not None for x in (uv_src_px, uv_dst_px, K_src, K_dst)]
    if any(given) and not all(given):
        raise Sim3Error(
            "the reprojection gate needs uv_src_px, uv_dst_px, K_src and K_dst together; "
            "give all four, or none for the 3D gate relative to depth"
        )
    if all(given):
        if not (np.isfinite(chi2_threshold) and chi2_threshold > 0):
            raise Sim3Error("chi2_threshold must be finite and > 0 (9.21: 2-dof 99 %)")
        K_src, K_dst = check_intrinsics_sim3(K_src, "K_src"), check_intrinsics_sim3(K_dst, "K_dst")
        sig_src = check_sigmas(sigma_src_px, "sigma_src_px", n)
        sig_dst = check_sigmas(sigma_dst_px, "sigma_dst_px", n)
        # A pixel gate g at depth z is a lateral distance g z / f.
        f_src, f_dst = 0.5 * (K_src[0, 0] + K_src[1, 1]), 0.5 * (K_dst[0, 0] + K_dst[1, 1])
        gate = np.sqrt(chi2_threshold)
        return Correspondences(
            src,
            dst,
            check_pixels(uv_src_px, "uv_src_px", n),
            check_pixels(uv_dst_px, "uv_dst_px", n),
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
    return Correspondences(
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
