"""Projection matching of map points to keypoints, and the pose-independent helpers it needs.

The search (:func:`search_by_projection`): one compiled pass over a grid of the keypoints finds
each point's candidates within its search radius and applies the gates (octave window, Hamming
distance, ratio test, depth consistency, one point per keypoint), ties broken in the frame's
KD-tree order; the rotation histogram in numpy on the matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..descriptors import as_descriptors, hamming
from .features import FrameFeatures
from .types import VoError


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
    points_map = np.ascontiguousarray(points_map, dtype=float).reshape(-1, 3)
    n = len(points_map)
    with_dist = max_dist_m is not None
    with_normals = with_dist and normals_map is not None
    # The kernel reads them point by point, unchecked: a shorter array would be read past its end.
    if (with_dist and len(max_dist_m) != n) or (with_normals and len(normals_map) != n):
        raise VoError(
            f"project_points: {n} points but max_dist_m / normals_map of "
            f"{len(max_dist_m) if with_dist else '-'} / {len(normals_map) if with_normals else '-'}"
        )
    idx, uv, u_right, depth, pred = _project(
        np.ascontiguousarray(T_cam_map, dtype=float),
        points_map,
        float(K[0, 0]),
        float(K[1, 1]),
        float(K[0, 2]),
        float(K[1, 2]),
        float(bf),
        float(size_wh[0]),
        float(size_wh[1]),
        np.ascontiguousarray(scales, dtype=float),
        np.ascontiguousarray(max_dist_m if with_dist else np.zeros(n), dtype=float),
        np.ascontiguousarray(normals_map if with_normals else np.zeros((n, 3)), dtype=float),
        float(min_view_cos),
        with_dist,
        with_normals,
    )
    return Projection(idx, uv, u_right, depth, pred)


@njit(cache=True, nogil=True, error_model="numpy")
def _project(
    T, points, fx, fy, cx, cy, bf, w, h, scales, max_dist, normals, min_view_cos, with_dist,
    with_normals,
):  # fmt: skip
    """:func:`project_points` point by point (its dozen numpy passes over the local map's
    thousands of points took ~0.3 ms a call, issue #50)."""
    n, n_levels = points.shape[0], scales.shape[0]
    log_step = np.log(scales[1] if n_levels > 1 else 2.0)
    # Camera centre in the map frame: -R^T t of T_cam_map.
    c = np.empty(3)
    for j in range(3):
        c[j] = -(T[0, j] * T[0, 3] + T[1, j] * T[1, 3] + T[2, j] * T[2, 3])
    idx = np.empty(n, np.int64)
    uv = np.empty((n, 2))
    u_right = np.empty(n)
    depth = np.empty(n)
    pred = np.zeros(n, np.int64)
    m = 0
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        x = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
        y = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
        z = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
        if not z > 1e-3:
            continue
        u = fx * x / z + cx
        v = fy * y / z + cy
        if not (u >= 0.0 and u < w and v >= 0.0 and v < h):
            continue
        level = 0
        if with_dist:
            rx, ry, rz = px - c[0], py - c[1], pz - c[2]
            dist = np.sqrt(rx * rx + ry * ry + rz * rz)
            if not (
                dist >= 0.8 * (max_dist[i] / scales[n_levels - 1]) and dist <= 1.2 * max_dist[i]
            ):
                continue
            if with_normals:
                cos = (rx * normals[i, 0] + ry * normals[i, 1] + rz * normals[i, 2]) / dist
                if not cos >= min_view_cos:
                    continue
            f = np.ceil(np.log(max_dist[i] / max(dist, 1e-6)) / log_step)
            if f != f:
                f = 0.0
            level = int(min(max(f, 0.0), n_levels - 1.0))
        idx[m] = i
        uv[m, 0], uv[m, 1] = u, v
        u_right[m] = u - bf / z
        depth[m] = z
        pred[m] = level
        m += 1
    return idx[:m], uv[:m], u_right[:m], depth[:m], pred[:m]


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
    scale, at that octave or one next to it; the nearest descriptor wins (ties: the first
    candidate in the tree's order, :func:`tree_rank`) if within ``max_distance`` and, against the
    second nearest at the same level, the ratio test; of the points that chose one keypoint, the
    nearest descriptor (ties: the lower point). Compiled (:func:`_search`): numpy's sorts and
    masks cost 1 ms a call (issue #50).
    """
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros(0, np.int32))
    if len(proj.index) == 0 or len(frame) == 0:
        return empty
    radius = radius_px * scales[proj.pred_octave]
    chi2 = -1.0 if chi2_gate is None else float(chi2_gate)
    pi, kj, dist = _search(
        np.ascontiguousarray(proj.uv_px, dtype=float),
        np.ascontiguousarray(radius, dtype=float),
        np.ascontiguousarray(proj.u_right_px, dtype=float),
        np.ascontiguousarray(proj.pred_octave, dtype=np.int64),
        as_descriptors(point_desc[proj.index], "points").view(np.uint64),
        np.ascontiguousarray(frame.uv_px, dtype=float),
        np.ascontiguousarray(frame.u_right_px, dtype=float),
        np.ascontiguousarray(frame.octaves, dtype=np.int64),
        as_descriptors(frame.descriptors, "keypoints").view(np.uint64),
        tree_rank(frame),
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


def tree_rank(frame: FrameFeatures) -> np.ndarray:
    """Each keypoint's place in the frame's KD-tree order (``frame.tree().indices``): the order a
    KD-tree pair search gave a point's candidates, by which the search breaks descriptor ties."""
    rank = np.empty(len(frame), np.int64)
    rank[frame.tree().indices] = np.arange(len(frame))
    return rank


@njit(cache=True, nogil=True)
def _search(
    uv, radius, u_right, octave, desc, kp_uv, kp_u_right, kp_octave, kp_desc, kp_rank, exclude,
    scales, max_distance, ratio, chi2,
):  # fmt: skip
    """:func:`search_by_projection`'s matches. Keypoints bucketed on a square grid (cells of the
    median radius); each point scans its cells for the keypoints within its radius that pass the
    gates, keeping the two of least (descriptor distance, tree rank): the best and second best of
    its candidates taken in the tree's order with ties to the first (on rendered worlds many
    keypoints tie, and which of them a monocular map takes changed its scale by 5 %). One pass, no
    candidate list: listing and ordering the candidates took a sixth of a frame's tracking (issue
    #50). chi2 < 0: no reprojection gate."""
    n_pt, n_kp = uv.shape[0], kp_uv.shape[0]
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
    big = 1 << 30
    owner = np.full(n_kp, -1, np.int64)  # the point each keypoint went to, and its distance
    owner_d = np.full(n_kp, big, np.int64)
    for m in range(n_pt):
        r, o = radius[m], octave[m]
        best_d, best_k, second_d, second_k = big, -1, big, -1
        cu0 = max(int(np.floor((uv[m, 0] - r - u0) / cell)), 0)
        cu1 = min(int(np.floor((uv[m, 0] + r - u0) / cell)), nu - 1)
        cv0 = max(int(np.floor((uv[m, 1] - r - v0) / cell)), 0)
        cv1 = min(int(np.floor((uv[m, 1] + r - v0) / cell)), nv - 1)
        for cv in range(cv0, cv1 + 1):
            for cu in range(cu0, cu1 + 1):
                c = cv * nu + cu
                for q in range(start[c], start[c + 1]):
                    k = items[q]
                    if kp_octave[k] < o - 1 or kp_octave[k] > o + 1 or exclude[k]:
                        continue
                    du, dv = uv[m, 0] - kp_uv[k, 0], uv[m, 1] - kp_uv[k, 1]
                    if np.sqrt(du * du + dv * dv) > r:
                        continue
                    if chi2 >= 0.0:
                        err2, gate = du * du + dv * dv, chi2
                        if np.isfinite(kp_u_right[k]):
                            dr = u_right[m] - kp_u_right[k]
                            err2 += dr * dr
                            gate = chi2 * 7.815 / 5.991
                        if err2 / scales[kp_octave[k]] ** 2 > gate:
                            continue
                    d = hamming(desc[m], kp_desc[k])
                    if d < best_d or (d == best_d and kp_rank[k] < kp_rank[best_k]):
                        second_d, second_k = best_d, best_k
                        best_d, best_k = d, k
                    elif d < second_d or (d == second_d and kp_rank[k] < kp_rank[second_k]):
                        second_d, second_k = d, k
        k = best_k
        if k < 0 or best_d > max_distance:
            continue
        # Ratio test only against a keypoint of the same level, as ORB-SLAM (other levels are
        # other scales).
        s = second_k
        if s >= 0 and kp_octave[s] == kp_octave[k] and best_d > ratio * second_d:
            continue
        if best_d < owner_d[k]:  # one point per keypoint: the nearest descriptor
            owner[k], owner_d[k] = m, best_d
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
