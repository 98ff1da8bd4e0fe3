"""Keyframes' points placed by their current poses in one frame (a merged group's root) and
thinned on a voxel grid: the dense team cloud. It is rebuilt from the per-keyframe points on every
call, so it follows the graph wherever a merge, loop closure or global BA moves a keyframe."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ..errors import CoopSlamError

# Voxel indices are packed into one int64 key: 21 bits per axis (+-1e6 voxels: +-50 km at 5 cm).
_BITS = 21
_OFFSET = 1 << (_BITS - 1)


class DenseCloudError(CoopSlamError):
    """Invalid input to the dense cloud (voxel size, poses, point arrays)."""


def place(views: Iterable[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(N, 3) float32 points in the frame of the poses, from (T_frame_cam, points_cam) pairs."""
    placed = [
        (pts @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32))
        for T, pts in views
        if len(pts)
    ]
    return np.concatenate(placed) if placed else np.zeros((0, 3), np.float32)


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 key per point naming its voxel of edge ``voxel_m``."""
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise DenseCloudError(f"voxel size must be > 0 m, got {voxel_m}")
    # float32 as the points are: its step at 1 km is 0.06 mm, far inside a voxel.
    idx = np.floor(np.asarray(points, np.float32) / np.float32(voxel_m)).astype(np.int64) + _OFFSET
    if len(idx) and (idx.min() < 0 or idx.max() >= (1 << _BITS)):
        raise DenseCloudError(
            f"points span more than {(1 << _BITS) * voxel_m:.0f} m at {voxel_m} m voxels"
        )
    return (idx[:, 0] << (2 * _BITS)) | (idx[:, 1] << _BITS) | idx[:, 2]


def voxel_centroids(
    points: np.ndarray, voxel_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centroids (M, 3) float32, the index of one point of each voxel (M,), point counts (M,)),
    voxels in the order of their keys."""
    points = np.asarray(points, np.float32)
    if len(points) == 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64)
    keys = voxel_keys(points, voxel_m)
    # One unstable sort (np.unique's return_index would sort stably: half again the time).
    order = np.argsort(keys)
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_keys[1:] != sorted_keys[:-1]]))
    counts = np.diff(np.append(starts, len(keys)))
    sums = np.add.reduceat(points[order], starts, axis=0, dtype=np.float64)
    return (sums / counts[:, None]).astype(np.float32), order[starts], counts


def voxel_filter(points: np.ndarray, voxel_m: float, min_points: int = 1) -> np.ndarray:
    """The centroid of each voxel holding at least ``min_points`` points (float32 (M, 3))."""
    centroids, _, counts = voxel_centroids(points, voxel_m)
    return centroids[counts >= max(1, int(min_points))]
