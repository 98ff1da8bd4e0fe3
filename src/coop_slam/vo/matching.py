"""Vectorized projection matching of map points to keypoints, and the pose-independent helpers it
needs.

All candidate (point, keypoint) pairs within the search radius come from one KD-tree query
(``sparse_distance_matrix``); the gates (radius scaled by the predicted octave, octave window,
Hamming distance, ratio test, depth consistency, one point per keypoint, rotation histogram) are
numpy array operations on those pairs, so there is no per-point Python loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..descriptors import hamming_rows
from ..geometry import transform_points
from .features import FrameFeatures


@dataclass
class Projection:
    """Map points projected into a camera: which are in the frustum, where, at which level."""

    index: np.ndarray  # (M,) indices into the projected point array of the points in view
    uv_px: np.ndarray  # (M, 2)
    u_right_px: np.ndarray  # (M,)
    depth_m: np.ndarray  # (M,)
    pred_octave: np.ndarray  # (M,) int


def project_points(
    T_cam_map: np.ndarray,
    points_map: np.ndarray,
    K: np.ndarray,
    bf: float,
    size_wh: tuple[int, int],
    scales: np.ndarray,
    max_dist_m: np.ndarray | None = None,
    normals_map: np.ndarray | None = None,
    min_view_cos: float = 0.5,
) -> Projection:
    """Frustum test and projection, as ORB-SLAM's ``isInFrustum``.

    ``max_dist_m`` (the distance at which a point was seen at level 0 times scale**octave) gives the
    predicted pyramid level and the scale-invariance range; ``normals_map`` the viewing-angle test.
    """
    points_cam = transform_points(T_cam_map, points_map)
    z = points_cam[:, 2]
    ok = z > 1e-3
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * points_cam[:, 0] / z + K[0, 2]
        v = K[1, 1] * points_cam[:, 1] / z + K[1, 2]
    w, h = size_wh
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    n_levels = len(scales)
    pred = np.zeros(len(points_map), dtype=int)
    if max_dist_m is not None:
        # Camera centre in the map frame: -R^T t of T_cam_map.
        center_map = -T_cam_map[:3, :3].T @ T_cam_map[:3, 3]
        ray = points_map - center_map
        dist = np.linalg.norm(ray, axis=1)
        min_dist = max_dist_m / scales[-1]
        ok &= (dist >= 0.8 * min_dist) & (dist <= 1.2 * max_dist_m)
        if normals_map is not None:
            with np.errstate(invalid="ignore", divide="ignore"):
                cos = np.einsum("ij,ij->i", ray, normals_map) / dist
            ok &= cos >= min_view_cos
        with np.errstate(divide="ignore", invalid="ignore"):
            level = np.ceil(
                np.log(max_dist_m / np.maximum(dist, 1e-6))
                / np.log(scales[1] if n_levels > 1 else 2.0)
            )
        pred = np.clip(np.nan_to_num(level, nan=0.0), 0, n_levels - 1).astype(int)
    idx = np.flatnonzero(ok)
    return Projection(
        index=idx,
        uv_px=np.stack([u[idx], v[idx]], axis=1),
        u_right_px=u[idx] - bf / z[idx],
        depth_m=z[idx],
        pred_octave=pred[idx],
    )


def search_by_projection(
    proj: Projection,
    point_desc: np.ndarray,
    frame: FrameFeatures,
    radius_px: float,
    scales: np.ndarray,
    max_distance: int,
    ratio: float,
    exclude_kp: np.ndarray | None = None,
    point_angle_deg: np.ndarray | None = None,
    check_orientation: bool = False,
    chi2_gate: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match projected points to frame keypoints.

    ``point_desc`` (P, 32) and ``point_angle_deg`` (P,) are indexed like the projected points (use
    ``proj.index``). Returns (proj_idx, kp_idx, hamming) with proj_idx indexing ``proj`` rows, each
    keypoint used at most once. ``exclude_kp`` marks keypoints that must not be matched;
    ``chi2_gate`` rejects pairs whose (u, v[, u_right]) reprojection error, weighted by the
    keypoint's octave, exceeds it (a depth-consistency test used when fusing points).
    """
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros(0, np.int32))
    m = len(proj.index)
    if m == 0 or len(frame) == 0:
        return empty
    radius = radius_px * scales[proj.pred_octave]
    pairs = cKDTree(proj.uv_px).sparse_distance_matrix(
        frame.tree(), float(radius.max()), output_type="ndarray"
    )
    if len(pairs) == 0:
        return empty
    pi = pairs["i"].astype(int)
    kj = pairs["j"].astype(int)
    keep = pairs["v"] <= radius[pi]
    kp_oct = frame.octaves[kj].astype(int)
    keep &= (kp_oct >= proj.pred_octave[pi] - 1) & (kp_oct <= proj.pred_octave[pi] + 1)
    if exclude_kp is not None:
        keep &= ~exclude_kp[kj]
    pi, kj = pi[keep], kj[keep]
    if chi2_gate is not None and len(pi):
        inv_s2 = 1.0 / scales[frame.octaves[kj].astype(int)] ** 2
        err2 = ((proj.uv_px[pi] - frame.uv_px[kj]) ** 2).sum(1)
        ur_kp = frame.u_right_px[kj]
        stereo = np.isfinite(ur_kp)
        err2 = err2 + np.where(stereo, (proj.u_right_px[pi] - np.nan_to_num(ur_kp)) ** 2, 0.0)
        gate = np.where(stereo, chi2_gate * 7.815 / 5.991, chi2_gate)
        ok = err2 * inv_s2 <= gate
        pi, kj = pi[ok], kj[ok]
    if len(pi) == 0:
        return empty
    dist = hamming_rows(point_desc[proj.index[pi]], frame.descriptors[kj])
    # Best and second best keypoint of each point: pairs by point, then distance (a stable sort of
    # one integer key: the same order as lexsort((dist, pi)), twice as fast).
    order = np.argsort(pi * 1024 + dist, kind="stable")
    pi, kj, dist = pi[order], kj[order], dist[order]
    first = np.r_[True, pi[1:] != pi[:-1]]
    has_second = np.r_[~first[1:], False]  # the next pair belongs to the same point
    best = np.flatnonzero(first)
    second_dist = np.where(has_second[best], dist[np.minimum(best + 1, len(dist) - 1)], 10**6)
    second_oct = np.where(
        has_second[best], frame.octaves[kj[np.minimum(best + 1, len(kj) - 1)]], 255
    )
    best_oct = frame.octaves[kj[best]]
    ok = dist[best] <= max_distance
    # Ratio test only between keypoints of the same level, as ORB-SLAM (other levels are other
    # scales).
    ok &= ~((second_oct == best_oct) & (dist[best] > ratio * second_dist))
    best = best[ok]
    if len(best) == 0:
        return empty
    pi, kj, dist = pi[best], kj[best], dist[best]
    # One point per keypoint: the closest descriptor wins.
    order = np.lexsort((dist, kj))
    pi, kj, dist = pi[order], kj[order], dist[order]
    first = np.r_[True, kj[1:] != kj[:-1]]
    pi, kj, dist = pi[first], kj[first], dist[first]
    if check_orientation and point_angle_deg is not None and len(pi) > 10:
        keep = rotation_consistent(point_angle_deg[proj.index[pi]], frame.angle_deg[kj])
        pi, kj, dist = pi[keep], kj[keep], dist[keep]
    return pi, kj, dist


def rotation_consistent(
    angle_a_deg: np.ndarray, angle_b_deg: np.ndarray, bins: int = 30
) -> np.ndarray:
    """Mask of matches whose keypoint rotation change lies in the 3 most common histogram bins.

    Bins holding less than 10 % of the fullest one are not kept (ORB-SLAM's ComputeThreeMaxima).
    Matches without an angle (-1) are kept.
    """
    valid = (angle_a_deg >= 0) & (angle_b_deg >= 0)
    diff = np.mod(angle_b_deg - angle_a_deg, 360.0)
    b = np.minimum((diff * bins / 360.0).astype(int), bins - 1)
    hist = np.bincount(b[valid], minlength=bins)
    if hist.max() == 0:
        return np.ones(len(b), bool)
    top = np.argsort(hist)[::-1][:3]
    top = top[hist[top] >= 0.1 * hist.max()]
    return ~valid | np.isin(b, top)
