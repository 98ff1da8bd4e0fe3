"""Pinhole camera helpers of the registration stage, and its input checks and error type.

``project`` / ``backproject`` map between camera-frame points [m] and pixels; the checks turn
malformed input (shapes, NaN, intrinsics) into a :class:`RegistrationError` naming what is wrong.
"""

from __future__ import annotations

import numpy as np

from ..errors import CoopSlamError


class RegistrationError(CoopSlamError):
    """Invalid input to relative-pose estimation (shapes, NaN, dtypes, intrinsics)."""


def check_intrinsics(K, name: str = "K") -> np.ndarray:
    """Return ``K`` as a float 3x3 pinhole matrix or raise RegistrationError."""
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise RegistrationError(f"{name} must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9 or K[1, 0] != 0:
        raise RegistrationError(f"{name} is not a pinhole matrix [[fx,s,cx],[0,fy,cy],[0,0,1]]")
    return K


def check_points(
    points, name: str, n: int | None = None, allow_nan_rows: bool = False
) -> np.ndarray:
    """Return ``points`` as float (N, 3); NaN rows only where ``allow_nan_rows`` (= no point)."""
    arr = np.asarray(points, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise RegistrationError(f"{name} has shape {arr.shape}, expected (N, 3)")
    if n is not None and len(arr) != n:
        raise RegistrationError(f"{name} has {len(arr)} rows, expected {n} (one per keypoint)")
    finite = np.isfinite(arr)
    if allow_nan_rows:
        partial = finite.any(axis=1) & ~finite.all(axis=1)
        if partial.any() or np.isinf(arr).any():
            raise RegistrationError(f"{name}: rows must be all finite or all NaN (no point)")
    elif not finite.all():
        raise RegistrationError(f"{name} contains NaN or inf")
    return arr


def backproject(uv_px: np.ndarray, depths_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame points of pixels with depth (z = depth); NaN rows where depth <= 0."""
    uv_px = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    depths_m = np.asarray(depths_m, dtype=float).reshape(-1)
    x = (uv_px[:, 0] - K[0, 2] - K[0, 1] * (uv_px[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (uv_px[:, 1] - K[1, 2]) / K[1, 1]
    points = np.stack([x, y, np.ones_like(x)], axis=1) * depths_m[:, None]
    points[depths_m <= 0] = np.nan
    return points


def project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of camera-frame points; NaN for points not in front of the camera."""
    points_cam = np.asarray(points_cam, dtype=float).reshape(-1, 3)
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = points_cam @ K.T
        uv = uvw[:, :2] / z[:, None]
    uv[~(z > 1e-9)] = np.nan
    return uv


def ray_norms(uv_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Length of the viewing ray per unit depth: range = depth * ray_norm (for range factors)."""
    rays = backproject(uv_px, np.ones(len(uv_px)), K)
    return np.linalg.norm(rays, axis=1)


def projection_jacobian(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2, 3) d(pixel)/d(point) of the pinhole projection."""
    x, y, z = points_cam[:, 0], points_cam[:, 1], points_cam[:, 2]
    z = np.where(z > 1e-9, z, 1.0)  # rows behind the camera get zero weight anyway
    J = np.zeros((len(points_cam), 2, 3))
    J[:, 0, 0] = K[0, 0] / z
    J[:, 0, 1] = K[0, 1] / z
    J[:, 0, 2] = -(K[0, 0] * x + K[0, 1] * y) / z**2
    J[:, 1, 1] = K[1, 1] / z
    J[:, 1, 2] = -K[1, 1] * y / z**2
    return J
