"""A keyframe's decimated depth image back-projected to 3D points in its camera's optical frame
(REP-103: z forward, x right, y down) -- what the dense cloud and the occupancy grid place by the
keyframe's pose."""

from __future__ import annotations

import numpy as np

from ..camera import CameraModel
from .depth_image import DepthImage, DepthImageError


def points_grid(image: DepthImage, camera: CameraModel, min_m: float, max_m: float) -> np.ndarray:
    """(h, w, 3) points of the image's pixels, NaN where the depth is outside [min_m, max_m]."""
    small = image.camera(camera)
    depth = image.depth_m
    if depth.shape != (small.height, small.width):
        raise DepthImageError(f"depth image {depth.shape} does not match its camera model")
    z = np.where((depth >= min_m) & (depth <= max_m), depth, np.nan).astype(np.float32)
    v, u = np.mgrid[0 : small.height, 0 : small.width].astype(np.float32)
    return np.stack(
        [
            (u - np.float32(small.cx)) * z / np.float32(small.fx),
            (v - np.float32(small.cy)) * z / np.float32(small.fy),
            z,
        ],
        axis=-1,
    )


def points_cam(image: DepthImage, camera: CameraModel, min_m: float, max_m: float) -> np.ndarray:
    """(N, 3) float32 points of the pixels with a depth in [min_m, max_m]; ``camera`` is the
    full-resolution model the image was decimated from."""
    grid = points_grid(image, camera, min_m, max_m)
    return grid[np.isfinite(grid[..., 2])]
