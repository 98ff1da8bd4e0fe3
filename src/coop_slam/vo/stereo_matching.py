"""Matching the ORB keypoints of a rectified stereo pair, as ORB-SLAM2's ComputeStereoMatches does:

1. candidates: a right keypoint within ``stereo_row_tolerance_px`` x its level scale of the left
   keypoint's row, on the same or a neighbouring pyramid level, with a disparity in
   [0, fx] (depth at least one baseline); the one with the smallest descriptor distance, if below
   ``stereo_max_descriptor_distance``;
2. subpixel refinement: the zero-mean sum of squared differences of a (2r+1)^2 patch around the
   keypoint on its pyramid level, slid along the right row +- ``stereo_search_px`` columns, and a
   parabola through the best three costs (a minimum at the end of the search, or a parabola moving
   it by more than a pixel, is no match). ORB-SLAM2 subtracts the centre pixel and sums absolute
   differences; at corners, where keypoints sit, the centre pixel is on an edge: on rendered pairs
   with known disparity that doubled the median error;
3. matches whose best patch cost exceeds 1.5 x 1.4 x the median cost are outliers.

Steps 1 and 2 are compiled loops (:func:`_best_in_band`: each left keypoint against the right
keypoints in its row band, sorted by row; :func:`_slide_patches`: each pair's patches).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..descriptors import as_descriptors, hamming
from .config import VoConfig
from .features import OrbKeypoints


def match_stereo(
    left: OrbKeypoints,
    right: OrbKeypoints,
    left_levels: list[np.ndarray],
    right_levels: list[np.ndarray],
    scales: np.ndarray,
    fx: float,
    config: VoConfig,
) -> np.ndarray:
    """Right-image u [px] of every left keypoint (NaN: no match)."""
    n = len(left)
    u_right = np.full(n, np.nan)
    if n == 0 or len(right) == 0:
        return u_right
    pairs = _candidate_matches(left, right, scales, fx, config)
    if len(pairs) == 0:
        return u_right
    refined, cost = _refine(pairs, left, right, left_levels, right_levels, scales, config)
    ok = np.isfinite(refined)
    if not ok.any():
        return u_right
    # Patch-cost outliers (ORB-SLAM2: 1.5 x 1.4 x the median).
    ok &= cost <= 1.5 * 1.4 * np.median(cost[ok])
    i = pairs[ok, 0]
    uL = left.uv_px[:, 0]
    d = uL[i] - refined[ok]
    good = (d >= 0) & (d < fx)
    d = np.maximum(d[good], 0.01)  # a zero disparity is a point at infinity: keep it finite
    u_right[i[good]] = uL[i[good]] - d
    return u_right


def _candidate_matches(
    left: OrbKeypoints, right: OrbKeypoints, scales: np.ndarray, fx: float, config: VoConfig
) -> np.ndarray:
    """(K, 2) (left, right) index pairs: each left keypoint with its best right candidate (step 1
    of the module docstring; ties: the right keypoint higher in the image)."""
    by_row = np.argsort(right.uv_px[:, 1], kind="stable")
    li, ri = _best_in_band(
        np.ascontiguousarray(left.uv_px, dtype=float),
        np.ascontiguousarray(left.octaves, dtype=np.int64),
        as_descriptors(left.descriptors, "left").view(np.uint64),
        np.ascontiguousarray(right.uv_px[by_row], dtype=float),
        np.ascontiguousarray(right.octaves[by_row], dtype=np.int64),
        as_descriptors(right.descriptors[by_row], "right").view(np.uint64),
        np.ascontiguousarray(scales, dtype=float),
        float(fx),
        float(config.stereo.row_tolerance_px),
        int(config.stereo.max_descriptor_distance),
    )
    return np.column_stack([li, by_row[ri]]).astype(np.int64)


@njit(cache=True, nogil=True)
def _best_in_band(uv_l, oct_l, desc_l, uv_r, oct_r, desc_r, scales, fx, row_tol, max_distance):
    """Per left keypoint, the right keypoint (they are sorted by row) of a neighbouring level in
    its row band with a disparity in [0, fx) and the least descriptor distance, if below
    ``max_distance``: (left indices, right indices)."""
    n_levels = len(scales)
    li = np.empty(len(uv_l), np.int64)
    ri = np.empty(len(uv_l), np.int64)
    count = 0
    for i in range(len(uv_l)):
        o = oct_l[i]
        band = row_tol * scales[min(o + 1, n_levels - 1)]
        lo = np.searchsorted(uv_r[:, 1], uv_l[i, 1] - band, side="left")
        hi = np.searchsorted(uv_r[:, 1], uv_l[i, 1] + band, side="right")
        best_d, best_j = max_distance, -1
        for j in range(lo, hi):
            if abs(oct_r[j] - o) > 1 or abs(uv_l[i, 1] - uv_r[j, 1]) > row_tol * scales[oct_r[j]]:
                continue
            disparity = uv_l[i, 0] - uv_r[j, 0]
            if disparity < 0 or disparity >= fx:
                continue
            d = hamming(desc_l[i], desc_r[j])
            if d < best_d:
                best_d, best_j = d, j
        if best_j >= 0:
            li[count], ri[count] = i, best_j
            count += 1
    return li[:count], ri[:count]


def _refine(pairs, left, right, left_levels, right_levels, scales, config):
    """(refined right u [px] at level 0, best patch cost) per pair; NaN where refinement fails."""
    r, search = config.stereo.patch_radius_px, config.stereo.search_px
    refined = np.full(len(pairs), np.nan)
    cost = np.full(len(pairs), np.inf)
    octave = left.octaves[pairs[:, 0]].astype(int)
    for level in np.unique(octave):
        sel = np.flatnonzero(octave == level)
        s = scales[level]
        img_l, img_r = left_levels[level], right_levels[level]
        h, w = img_l.shape
        # Level-l pixel x_l of a level-0 position u = (x_l + 0.5) s - 0.5 (features.orb_level0_uv).
        ul = np.rint((left.uv_px[pairs[sel, 0], 0] + 0.5) / s - 0.5).astype(int)
        vl = np.rint((left.uv_px[pairs[sel, 0], 1] + 0.5) / s - 0.5).astype(int)
        ur0 = np.rint((right.uv_px[pairs[sel, 1], 0] + 0.5) / s - 0.5).astype(int)
        inside = (
            (vl - r >= 0)
            & (vl + r < h)
            & (ul - r >= 0)
            & (ul + r < w)
            & (ur0 - search - r >= 0)
            & (ur0 + search + r < w)
        )
        sel, ul, vl, ur0 = sel[inside], ul[inside], vl[inside], ur0[inside]
        if len(sel) == 0:
            continue
        at, best_cost = _slide_patches(img_l, img_r, ul, vl, ur0, r, search)
        ok = np.isfinite(at)
        refined[sel[ok]] = (at[ok] + 0.5) * s - 0.5
        cost[sel[ok]] = best_cost[ok]
    return refined, cost


@njit(cache=True, nogil=True)
def _slide_patches(img_l, img_r, ul, vl, ur0, r, search):
    """Per pair (left pixel (ul, vl), right column ur0 on one level; all patches inside): the
    subpixel right column where the zero-mean patch difference is least (NaN: at the end of the
    search, or the parabola moves it by more than a pixel) and that least cost's square root.

    With n pixels a patch, left patch L and right patch R, the zero-mean SSD is
    (n SR2 - SR^2 - 2 (n SLR - SL SR) + n SL2 - SL^2) / n (S: sums over the patch): integer sums,
    exact. The right band's column sums give SR and SR2 of every position at once; only SLR is
    per position."""
    n, side = len(ul), 2 * r + 1
    n_px = side * side
    width = side + 2 * search
    at = np.full(n, np.nan)
    best_cost = np.full(n, np.inf)
    costs = np.empty(2 * search + 1)
    col_sum = np.empty(width, np.int64)
    col_sq = np.empty(width, np.int64)
    # (int32 pixels load faster than int64 ones; numba sums their products in int64)
    patch = np.empty((side, side), np.int32)
    band = np.empty((side, width), np.int32)
    for i in range(n):
        sl = 0
        sl2 = 0
        for a in range(side):
            for b in range(side):
                v = np.int64(img_l[vl[i] - r + a, ul[i] - r + b])
                patch[a, b] = v
                sl += v
                sl2 += v * v
        c_first = ur0[i] - search - r
        for c in range(width):
            col_sum[c] = 0
            col_sq[c] = 0
        for a in range(side):
            for c in range(width):
                v = np.int64(img_r[vl[i] - r + a, c_first + c])
                band[a, c] = v
                col_sum[c] += v
                col_sq[c] += v * v
        sr = 0
        sr2 = 0
        for c in range(side):
            sr += col_sum[c]
            sr2 += col_sq[c]
        left_term = n_px * sl2 - sl * sl
        for k in range(2 * search + 1):
            if k > 0:
                sr += col_sum[k + side - 1] - col_sum[k - 1]
                sr2 += col_sq[k + side - 1] - col_sq[k - 1]
            slr = 0
            for a in range(side):
                for b in range(side):
                    slr += patch[a, b] * band[a, k + b]
            costs[k] = (n_px * sr2 - sr * sr - 2 * (n_px * slr - sl * sr) + left_term) / n_px
        best = np.argmin(costs)
        if best == 0 or best == 2 * search:
            continue
        d1, d2, d3 = costs[best - 1], costs[best], costs[best + 1]
        denom = 2.0 * (d1 + d3 - 2.0 * d2)
        delta = (d1 - d3) / denom if denom != 0 else 0.0
        if abs(delta) <= 1.0:
            at[i] = ur0[i] + best - search + delta
            best_cost[i] = np.sqrt(d2)  # an RMS-like difference, as ORB-SLAM2's SAD
    return at, best_cost
