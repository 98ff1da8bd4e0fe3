"""Input type of relative-pose estimation: one keyframe's features, camera and 3D points.

A :class:`KeyframeView` holds keypoints ``uv_px`` (N, 2), ORB descriptors (N, 32) uint8, depths
``depths_m`` (N,) (0 = no depth), intrinsics ``K`` and ``points_cam`` (N, 3) in the keyframe's
camera optical frame. ``points_cam`` rows that are NaN mean "no 3D point"; when not given they are
back-projected from the depths. Input is validated once here, so the estimators can trust it.

The 3D noise model (:func:`point_sigma_m`) is shared by RANSAC, ICP and bundle adjustment: depth
noise of structured-light/ToF sensors grows with range squared, keypoint noise grows linearly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..descriptors import DescriptorError, as_descriptors
from ..errors import GeometryError
from ..geometry import check_se3, invert, transform_points
from .camera import RegistrationError, backproject, check_intrinsics, check_points


def point_sigma_m(
    z_m: np.ndarray, floor_m: float, depth_coeff_per_m: float, lateral_rad: float
) -> np.ndarray:
    """Standard deviation [m] of a depth-camera point at depth ``z_m``.

    sigma^2 = floor^2 + (depth_coeff * z^2)^2 + (z * lateral_rad)^2: the quadratic term is the
    Kinect axial disparity noise (Khoshelham & Elberink 2012: 1.425e-3 / m), the linear one the
    keypoint localisation error (pixel sigma / focal length), the floor covers calibration.
    """
    z = np.asarray(z_m, dtype=float)
    return np.sqrt(floor_m**2 + (depth_coeff_per_m * z**2) ** 2 + (z * lateral_rad) ** 2)


def sample_depth(
    depth_m: np.ndarray,
    uv_px: np.ndarray,
    window_px: int = 2,
    max_rel_spread: float = 0.05,
    min_valid_fraction: float = 0.5,
) -> np.ndarray:
    """Depth [m] at keypoints from a depth image; 0 where it is missing or unreliable.

    Takes the median over a (2w+1)^2 window and rejects windows whose valid depths spread more than
    ``max_rel_spread`` of the median: keypoints sit on corners, often depth edges, where a small
    colour/depth misregistration (unregistered Kinect data) would otherwise pick the wrong surface.
    """
    depth_m = np.asarray(depth_m, dtype=np.float32)
    if depth_m.ndim != 2:
        raise RegistrationError(f"depth image must be 2-D, got shape {depth_m.shape}")
    uv_px = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    if len(uv_px) == 0:
        return np.zeros(0)
    h, w = depth_m.shape
    offsets = np.arange(-window_px, window_px + 1)
    du, dv = np.meshgrid(offsets, offsets)
    u = np.clip(np.rint(uv_px[:, 0])[:, None] + du.ravel(), 0, w - 1).astype(int)
    v = np.clip(np.rint(uv_px[:, 1])[:, None] + dv.ravel(), 0, h - 1).astype(int)
    vals = depth_m[v, u].astype(float)
    valid = np.isfinite(vals) & (vals > 0)
    enough = valid.mean(axis=1) >= min_valid_fraction
    vals = np.where(valid, vals, np.nan)
    out = np.zeros(len(uv_px))
    if enough.any():
        sub = vals[enough]
        med = np.nanmedian(sub, axis=1)
        spread = (np.nanmax(sub, axis=1) - np.nanmin(sub, axis=1)) / med
        out[enough] = np.where(spread <= max_rel_spread, med, 0.0)
    return out


@dataclass(frozen=True, eq=False)
class KeyframeView:
    """Features of one keyframe in its camera optical frame (validated and normalised on creation).

    ``points_cam`` NaN rows mean "no 3D point"; if omitted it is back-projected from ``depths_m``.
    """

    uv_px: np.ndarray
    descriptors: np.ndarray
    depths_m: np.ndarray | None
    K: np.ndarray
    points_cam: np.ndarray | None = None

    def __post_init__(self):
        uv_px = np.asarray(self.uv_px, dtype=float)
        if uv_px.ndim != 2 or uv_px.shape[1] != 2:
            raise RegistrationError(f"uv_px has shape {uv_px.shape}, expected (N, 2)")
        if not np.all(np.isfinite(uv_px)):
            raise RegistrationError("uv_px contains NaN or inf")
        n = len(uv_px)
        try:
            descriptors = as_descriptors(self.descriptors)
        except DescriptorError as exc:
            raise RegistrationError(str(exc)) from None
        if len(descriptors) != n:
            raise RegistrationError(f"{len(descriptors)} descriptors for {n} keypoints")
        K = check_intrinsics(self.K)
        if self.depths_m is None:
            depths_m = np.zeros(n)
        else:
            depths_m = np.asarray(self.depths_m, dtype=float).reshape(-1)
            if len(depths_m) != n:
                raise RegistrationError(f"{len(depths_m)} depths for {n} keypoints")
            if not np.all(np.isfinite(depths_m)) or (depths_m < 0).any():
                raise RegistrationError("depths_m must be finite and >= 0 (0 = no depth)")
        if self.points_cam is None:
            points_cam = backproject(uv_px, depths_m, K)
        else:
            points_cam = check_points(self.points_cam, "points_cam", n, allow_nan_rows=True)
        for name, value in (
            ("uv_px", uv_px),
            ("descriptors", descriptors),
            ("depths_m", depths_m),
            ("K", K),
            ("points_cam", points_cam),
        ):
            # Own copies, read-only: a view is shared between estimators and must not change
            # under them, and freezing the caller's array in place would surprise the caller.
            value = np.array(value, copy=True)
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.uv_px)

    @property
    def has_point(self) -> np.ndarray:
        """(N,) bool: keypoints with a 3D point in front of the camera."""
        return np.isfinite(self.points_cam[:, 2]) & (np.nan_to_num(self.points_cam[:, 2]) > 0)

    @classmethod
    def from_map_points(
        cls, uv_px, descriptors, K, points_map, T_map_cam, depths_m=None
    ) -> KeyframeView:
        """View whose 3D points are map points (robot map frame, NaN rows = none) seen from
        a keyframe at ``T_map_cam``."""
        try:
            T_map_cam = check_se3(T_map_cam, "T_map_cam")
        except GeometryError as exc:
            raise RegistrationError(str(exc)) from None
        points_map = check_points(points_map, "points_map", len(np.asarray(uv_px)), True)
        return cls(uv_px, descriptors, depths_m, K, transform_points(invert(T_map_cam), points_map))

    @classmethod
    def from_image(
        cls, image, depth_m, K, detector, mask=None, depth_window_px: int = 2, **sample_kw
    ) -> KeyframeView:
        """Detect and describe features (e.g. ``cv2.ORB_create(1000)``) and sample their depth."""
        keypoints, descriptors = detector.detectAndCompute(image, mask)
        if descriptors is None or not keypoints:
            return cls(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0), K)
        uv_px = np.array([kp.pt for kp in keypoints], dtype=float)
        depths = (
            np.zeros(len(uv_px))
            if depth_m is None
            else sample_depth(depth_m, uv_px, depth_window_px, **sample_kw)
        )
        return cls(uv_px, descriptors, depths, K)
