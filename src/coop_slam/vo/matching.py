"""Projection matching of map points to keypoints, and the pose-independent helpers it needs.

The search (:func:`search_by_projection`) is one compiled loop over the projected points that
visits a grid of the keypoints within each point's radius and applies the gates (radius scaled by
the predicted octave, octave window, Hamming distance, ratio test, depth consistency, one point per
keypoint) as it goes; the rotation histogram is numpy on the matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..descriptors import as_descriptors, hamming
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
    keypoint used at most once (in keypoint order). ``exclude_kp`` marks keypoints that must not
    be matched; ``chi2_gate`` rejects pairs whose (u, v[, u_right]) reprojection error, weighted by
    the keypoint's octave, exceeds it (a depth-consistency test used when fusing points).

    A point's candidates are the keypoints within ``radius_px`` times its predicted octave's
    scale, at that octave or one next to it; the nearest descriptor wins (ties: the lower
    keypoint index) if within ``max_distance`` and, against the second nearest at the same
    level, the ratio test; of the points that chose one keypoint, the nearest descriptor (ties:
    the lower point). Compiled (:func:`_search`): a loop over the points and a grid of the
    keypoints, where numpy's candidate pairs and sorts cost 2 ms a call (issue #50).
    """
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros(0, np.int32))
    if len(proj.index) == 0 or len(frame) == 0:
        return empty
    chi2 = -1.0 if chi2_gate is None else float(chi2_gate)
    pi, kj, dist = _search(
        np.ascontiguousarray(proj.uv_px, dtype=float),
        np.ascontiguousarray(proj.u_right_px, dtype=float),
        np.ascontiguousarray(proj.pred_octave, dtype=np.int64),
        as_descriptors(point_desc[proj.index], "points").view(np.uint64),
        np.ascontiguousarray(frame.uv_px, dtype=float),
        np.ascontiguousarray(frame.u_right_px, dtype=float),
        np.ascontiguousarray(frame.octaves, dtype=np.int64),
        as_descriptors(frame.descriptors, "keypoints").view(np.uint64),
        np.zeros(len(frame), np.bool_) if exclude_kp is None else np.asarray(exclude_kp, bool),
        float(radius_px),
        np.ascontiguousarray(scales, dtype=float),
        int(max_distance),
        float(ratio),
        chi2,
    )
    if check_orientation and point_angle_deg is not None and len(pi) > 10:
        keep = rotation_consistent(point_angle_deg[proj.index[pi]], frame.angle_deg[kj])
        pi, kj, dist = pi[keep], kj[keep], dist[keep]
    return pi, kj, dist


_GRID_PX = 16.0  # cell of the keypoint grid the search visits [px]


@njit(cache=True, nogil=True)
def _search(
    uv, u_right, octave, desc, kp_uv, kp_u_right, kp_octave, kp_desc, exclude, radius_px,
    scales, max_distance, ratio, chi2,
):  # fmt: skip
    """:func:`search_by_projection`'s matches (chi2 < 0: no reprojection gate)."""
    n_kp = kp_uv.shape[0]
    # The keypoints by grid cell (a counting sort): cell c holds order[start[c]:start[c + 1]].
    cols = int(kp_uv[:, 0].max() / _GRID_PX) + 1
    rows = int(kp_uv[:, 1].max() / _GRID_PX) + 1
    cell = np.empty(n_kp, np.int64)
    start = np.zeros(rows * cols + 1, np.int64)
    for k in range(n_kp):
        cu = min(max(int(kp_uv[k, 0] / _GRID_PX), 0), cols - 1)
        cv = min(max(int(kp_uv[k, 1] / _GRID_PX), 0), rows - 1)
        cell[k] = cv * cols + cu
        start[cell[k] + 1] += 1
    for c in range(rows * cols):
        start[c + 1] += start[c]
    order = np.empty(n_kp, np.int64)
    fill = start[:-1].copy()
    for k in range(n_kp):
        order[fill[cell[k]]] = k
        fill[cell[k]] += 1
    big = 1 << 30
    owner = np.full(n_kp, -1, np.int64)  # the point each keypoint went to, and its distance
    owner_d = np.full(n_kp, big, np.int64)
    for m in range(uv.shape[0]):
        o = octave[m]
        r = radius_px * scales[o]
        u, v = uv[m, 0], uv[m, 1]
        best_d, best_k, second_d, second_k = big, -1, big, -1
        for cv in range(
            max(int((v - r) / _GRID_PX), 0), min(int((v + r) / _GRID_PX), rows - 1) + 1
        ):
            for cu in range(
                max(int((u - r) / _GRID_PX), 0), min(int((u + r) / _GRID_PX), cols - 1) + 1
            ):
                for idx in range(start[cv * cols + cu], start[cv * cols + cu + 1]):
                    k = order[idx]
                    du, dv = kp_uv[k, 0] - u, kp_uv[k, 1] - v
                    d2 = du * du + dv * dv
                    if d2 > r * r or kp_octave[k] < o - 1 or kp_octave[k] > o + 1 or exclude[k]:
                        continue
                    if chi2 >= 0.0:
                        gate = chi2
                        if np.isfinite(kp_u_right[k]):
                            dr = u_right[m] - kp_u_right[k]
                            d2 += dr * dr
                            gate = chi2 * 7.815 / 5.991
                        if d2 / scales[kp_octave[k]] ** 2 > gate:
                            continue
                    d = hamming(desc[m], kp_desc[k])
                    if d < best_d or (d == best_d and k < best_k):
                        second_d, second_k = best_d, best_k
                        best_d, best_k = d, k
                    elif d < second_d or (d == second_d and k < second_k):
                        second_d, second_k = d, k
        if best_k < 0 or best_d > max_distance:
            continue
        # Ratio test only against a keypoint of the same level, as ORB-SLAM (other levels are
        # other scales).
        if second_k >= 0 and kp_octave[second_k] == kp_octave[best_k] and best_d > ratio * second_d:
            continue
        if best_d < owner_d[best_k]:  # one point per keypoint: the nearest descriptor
            owner[best_k], owner_d[best_k] = m, best_d
    count = 0
    for k in range(n_kp):
        count += owner[k] >= 0
    pi, kj = np.empty(count, np.int64), np.empty(count, np.int64)
    dist = np.empty(count, np.int32)
    count = 0
    for k in range(n_kp):
        if owner[k] >= 0:
            pi[count], kj[count], dist[count] = owner[k], k, owner_d[k]
            count += 1
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
