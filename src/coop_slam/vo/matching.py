"""Projection matching of map points to keypoints, and the pose-independent helpers it needs.

The search (:func:`search_by_projection`): the candidate (point, keypoint) pairs within each
point's search radius from a compiled grid of the keypoints (:func:`candidate_pairs`, in the
frame's KD-tree order); the gates (octave window, Hamming distance, ratio test, depth consistency,
one point per keypoint) in one compiled loop over those pairs; the rotation histogram in numpy on
the matches.
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
    scale (:func:`candidate_pairs`), at that octave or one next to it; the nearest descriptor wins
    (ties: the first candidate in the tree's order) if within ``max_distance`` and, against the
    second nearest at the same level, the ratio test; of the points that chose one keypoint, the
    nearest descriptor (ties: the lower point). The gates are compiled (:func:`_gated_best`),
    where numpy's sorts and masks cost 1 ms a call (issue #50).
    """
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros(0, np.int32))
    if len(proj.index) == 0 or len(frame) == 0:
        return empty
    radius = radius_px * scales[proj.pred_octave]
    pair_i, pair_k, _ = candidate_pairs(proj.uv_px, radius, frame)
    if len(pair_i) == 0:
        return empty
    chi2 = -1.0 if chi2_gate is None else float(chi2_gate)
    pi, kj, dist = _gated_best(
        pair_i,
        pair_k,
        np.ascontiguousarray(proj.uv_px, dtype=float),
        np.ascontiguousarray(proj.u_right_px, dtype=float),
        np.ascontiguousarray(proj.pred_octave, dtype=np.int64),
        as_descriptors(point_desc[proj.index], "points").view(np.uint64),
        np.ascontiguousarray(frame.uv_px, dtype=float),
        np.ascontiguousarray(frame.u_right_px, dtype=float),
        np.ascontiguousarray(frame.octaves, dtype=np.int64),
        as_descriptors(frame.descriptors, "keypoints").view(np.uint64),
        np.zeros(len(frame), np.bool_) if exclude_kp is None else np.asarray(exclude_kp, bool),
        np.ascontiguousarray(scales, dtype=float),
        int(max_distance),
        float(ratio),
        chi2,
    )
    if check_orientation and point_angle_deg is not None and len(pi) > 10:
        keep = rotation_consistent(point_angle_deg[proj.index[pi]], frame.angle_deg[kj])
        pi, kj, dist = pi[keep], kj[keep], dist[keep]
    return pi, kj, dist


def candidate_pairs(
    uv_px: np.ndarray, radius_px: np.ndarray, frame: FrameFeatures
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(point, keypoint, image distance) for every keypoint within each point's own radius: a
    point's keypoints in the order of the frame's KD tree (``frame.tree().indices``), which is
    the order a KD-tree pair search (``sparse_distance_matrix`` against that tree) gives them and
    the order :func:`_gated_best` breaks descriptor ties by. From a grid of the keypoints,
    compiled: the tree search ran at the largest radius of all (a top-octave point's, ~5x a
    level-0 point's) and took a sixth of a frame's tracking (issue #50)."""
    n_kp = len(frame)
    rank = np.empty(n_kp, np.int64)
    rank[frame.tree().indices] = np.arange(n_kp)
    return _grid_pairs(
        np.ascontiguousarray(uv_px, dtype=float),
        np.ascontiguousarray(radius_px, dtype=float),
        np.ascontiguousarray(frame.uv_px, dtype=float),
        rank,
    )


@njit(cache=True, nogil=True)
def _grid_pairs(uv, radius, kp_uv, kp_rank):  # fmt: skip
    """:func:`candidate_pairs`' pairs: keypoints bucketed on a square grid (cells of the median
    radius), each point's cells scanned, its keypoints ordered by ``kp_rank``."""
    n_pt, n_kp = uv.shape[0], kp_uv.shape[0]
    if n_pt == 0 or n_kp == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    u0, v0 = kp_uv[:, 0].min(), kp_uv[:, 1].min()
    span_u, span_v = kp_uv[:, 0].max() - u0, kp_uv[:, 1].max() - v0
    # Cells of the median radius, but never more cells than ~4 per keypoint (tiny radii).
    cell = max(np.median(radius), 1.0, np.sqrt((span_u + 1.0) * (span_v + 1.0) / (4.0 * n_kp)))
    nu = int(span_u / cell) + 1
    nv = int(span_v / cell) + 1
    cell_of = np.empty(n_kp, np.int64)
    for k in range(n_kp):
        cell_of[k] = int((kp_uv[k, 1] - v0) / cell) * nu + int((kp_uv[k, 0] - u0) / cell)
    start = np.zeros(nu * nv + 1, np.int64)
    for k in range(n_kp):
        start[cell_of[k] + 1] += 1
    for c in range(nu * nv):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    items = np.empty(n_kp, np.int64)
    for k in range(n_kp):
        items[fill[cell_of[k]]] = k
        fill[cell_of[k]] += 1
    cap = 4 * n_kp + 64
    out_i = np.empty(cap, np.int64)
    out_k = np.empty(cap, np.int64)
    out_d = np.empty(cap)
    n = 0
    found_k = np.empty(n_kp, np.int64)
    found_d = np.empty(n_kp)
    for m in range(n_pt):
        r = radius[m]
        cu0 = max(int(np.floor((uv[m, 0] - r - u0) / cell)), 0)
        cu1 = min(int(np.floor((uv[m, 0] + r - u0) / cell)), nu - 1)
        cv0 = max(int(np.floor((uv[m, 1] - r - v0) / cell)), 0)
        cv1 = min(int(np.floor((uv[m, 1] + r - v0) / cell)), nv - 1)
        f = 0
        for cv in range(cv0, cv1 + 1):
            for cu in range(cu0, cu1 + 1):
                c = cv * nu + cu
                for q in range(start[c], start[c + 1]):
                    k = items[q]
                    du, dv = uv[m, 0] - kp_uv[k, 0], uv[m, 1] - kp_uv[k, 1]
                    d = np.sqrt(du * du + dv * dv)
                    if d <= r:
                        # insertion by rank: a point has a few to a few dozen keypoints
                        j = f
                        while j > 0 and kp_rank[found_k[j - 1]] > kp_rank[k]:
                            found_k[j], found_d[j] = found_k[j - 1], found_d[j - 1]
                            j -= 1
                        found_k[j], found_d[j] = k, d
                        f += 1
        if n + f > cap:
            cap = 2 * (n + f)
            out_i = _grown(out_i, cap)
            out_k = _grown(out_k, cap)
            out_d = _grown(out_d, cap)
        for j in range(f):
            out_i[n], out_k[n], out_d[n] = m, found_k[j], found_d[j]
            n += 1
    return out_i[:n], out_k[:n], out_d[:n]


@njit(cache=True, nogil=True)
def _grown(a, cap):
    b = np.empty(cap, a.dtype)
    b[: len(a)] = a
    return b


@njit(cache=True, nogil=True)
def _gated_best(
    pair_i, pair_k, uv, u_right, octave, desc, kp_uv, kp_u_right, kp_octave, kp_desc, exclude,
    scales, max_distance, ratio, chi2,
):  # fmt: skip
    """:func:`search_by_projection`'s matches from the candidate pairs (point, keypoint; each
    within the point's radius), taken in the tree's order: a point's best and second best are
    the first pairs of least descriptor distance, as numpy's stable sort kept them (on rendered
    worlds many keypoints tie, and which of them a monocular map takes changed its scale by
    5 %). chi2 < 0: no reprojection gate."""
    n_pt, n_kp = uv.shape[0], kp_uv.shape[0]
    big = 1 << 30
    best_d = np.full(n_pt, big, np.int64)
    best_k = np.full(n_pt, -1, np.int64)
    second_d = np.full(n_pt, big, np.int64)
    second_k = np.full(n_pt, -1, np.int64)
    for q in range(len(pair_i)):
        m, k = pair_i[q], pair_k[q]
        o = octave[m]
        if kp_octave[k] < o - 1 or kp_octave[k] > o + 1 or exclude[k]:
            continue
        if chi2 >= 0.0:
            du, dv = uv[m, 0] - kp_uv[k, 0], uv[m, 1] - kp_uv[k, 1]
            err2, gate = du * du + dv * dv, chi2
            if np.isfinite(kp_u_right[k]):
                dr = u_right[m] - kp_u_right[k]
                err2 += dr * dr
                gate = chi2 * 7.815 / 5.991
            if err2 / scales[kp_octave[k]] ** 2 > gate:
                continue
        d = hamming(desc[m], kp_desc[k])
        if d < best_d[m]:
            second_d[m], second_k[m] = best_d[m], best_k[m]
            best_d[m], best_k[m] = d, k
        elif d < second_d[m]:
            second_d[m], second_k[m] = d, k
    owner = np.full(n_kp, -1, np.int64)  # the point each keypoint went to, and its distance
    owner_d = np.full(n_kp, big, np.int64)
    for m in range(n_pt):
        k = best_k[m]
        if k < 0 or best_d[m] > max_distance:
            continue
        # Ratio test only against a keypoint of the same level, as ORB-SLAM (other levels are
        # other scales).
        s = second_k[m]
        if s >= 0 and kp_octave[s] == kp_octave[k] and best_d[m] > ratio * second_d[m]:
            continue
        if best_d[m] < owner_d[k]:  # one point per keypoint: the nearest descriptor
            owner[k], owner_d[k] = m, best_d[m]
    kj = np.flatnonzero(owner >= 0)
    return owner[kj], kj, owner_d[kj].astype(np.int32)


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
