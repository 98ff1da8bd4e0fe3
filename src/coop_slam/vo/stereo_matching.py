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

Steps 1 and 2 are one compiled call for a range of left keypoints (:func:`_match_range`: each
against the right keypoints in its row band, sorted by row; then each pair's patches on its level)
that runs without Python's lock: given a worker thread, the two halves of the left keypoints are
matched side by side (the result does not depend on it).
"""

from __future__ import annotations

from concurrent.futures import Executor

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
    worker: Executor | None = None,
) -> np.ndarray:
    """Right-image u [px] of every left keypoint (NaN: no match). ``worker``: a thread that
    matches the first half of the left keypoints while the caller's matches the second."""
    n = len(left)
    u_right = np.full(n, np.nan)
    if n == 0 or len(right) == 0:
        return u_right
    pair = _Pair(left, right, left_levels, right_levels, scales, fx, config)
    if worker is None or n < _MIN_SPLIT:
        pairs, refined, cost = pair.match(0, n)
    else:
        first_half = worker.submit(pair.match, 0, n // 2)
        try:
            second = pair.match(n // 2, n)
        finally:
            first = first_half.result()
        pairs, refined, cost = (np.concatenate(parts) for parts in zip(first, second))
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


# Fewer left keypoints are matched on the calling thread alone (a hand-over costs ~0.05 ms).
_MIN_SPLIT = 200


class _Pair:
    """A pair's keypoints and pyramids as the compiled loops take them (right ones sorted by
    row), and the matching of a range of left keypoints."""

    def __init__(self, left, right, left_levels, right_levels, scales, fx, config: VoConfig):
        # tuples of C-ordered images: a compiled loop indexes them by level
        self.left_levels = tuple(np.ascontiguousarray(img) for img in left_levels)
        self.right_levels = tuple(np.ascontiguousarray(img) for img in right_levels)
        self.scales = np.ascontiguousarray(scales, dtype=float)
        self.fx = float(fx)
        self.config = config
        self.uv_l = np.ascontiguousarray(left.uv_px, dtype=float)
        self.oct_l = np.ascontiguousarray(left.octaves, dtype=np.int64)
        self.desc_l = as_descriptors(left.descriptors, "left").view(np.uint64)
        self.by_row = np.argsort(right.uv_px[:, 1], kind="stable")
        self.uv_r = np.ascontiguousarray(right.uv_px[self.by_row], dtype=float)
        self.oct_r = np.ascontiguousarray(right.octaves[self.by_row], dtype=np.int64)
        self.desc_r = as_descriptors(right.descriptors[self.by_row], "right").view(np.uint64)

    def match(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Left keypoints lo..hi-1: (K, 2) (left, right) index pairs (step 1 of the module
        docstring; ties: the right keypoint higher in the image), and per pair the refined
        right u [px] at level 0 (NaN: refinement failed) and the best patch cost."""
        stereo = self.config.stereo
        r = stereo.patch_radius_px
        li, ri, refined, cost = _match_range(
            self.uv_l[lo:hi],
            self.oct_l[lo:hi],
            self.desc_l[lo:hi],
            self.uv_r,
            self.oct_r,
            self.desc_r,
            self.scales,
            self.fx,
            float(stereo.row_tolerance_px),
            int(stereo.max_descriptor_distance),
            self.left_levels,
            self.right_levels,
            r,
            stereo.search_px,
            _sum_type(r),
        )
        return np.column_stack([li + lo, self.by_row[ri]]).astype(np.int64), refined, cost


def _sum_type(r: int):
    """Zero of the type that sums a (2r+1)^2 patch's products exactly: float32 while they stay
    below 2^24 (its sums vectorise twice as wide as int64's), else int64."""
    return np.float32(0) if (2 * r + 1) ** 2 * 255 * 255 < 2**24 else np.int64(0)


@njit(cache=True, nogil=True)
def _match_range(
    uv_l,
    oct_l,
    desc_l,
    uv_r,
    oct_r,
    desc_r,
    scales,
    fx,
    row_tol,
    max_distance,
    levels_l,
    levels_r,
    r,
    search,
    zero,
):
    """Steps 1 and 2 for some left keypoints against all the right ones (sorted by row): left
    and (sorted) right indices of each candidate pair, its refined right u [px] at level 0 (NaN:
    refinement failed or a patch leaves the image) and its best patch cost."""
    li, ri = _best_in_band(
        uv_l, oct_l, desc_l, uv_r, oct_r, desc_r, scales, fx, row_tol, max_distance
    )
    refined = np.full(len(li), np.nan)
    cost = np.full(len(li), np.inf)
    costs, sums, columns = _work_arrays(r, search, zero)
    for m in range(len(li)):
        level = oct_l[li[m]]
        s = scales[level]
        img_l, img_r = levels_l[level], levels_r[level]
        h, w = img_l.shape
        # Level-l pixel x_l of a level-0 position u = (x_l + 0.5) s - 0.5 (features.orb_level0_uv).
        u = int(np.rint((uv_l[li[m], 0] + 0.5) / s - 0.5))
        v = int(np.rint((uv_l[li[m], 1] + 0.5) / s - 0.5))
        u_right = int(np.rint((uv_r[ri[m], 0] + 0.5) / s - 0.5))
        if v - r < 0 or v + r >= h or u - r < 0 or u + r >= w:
            continue
        if u_right - search - r < 0 or u_right + search + r >= w:
            continue
        at, best = _slide_patch(img_l, img_r, u, v, u_right, r, search, costs, sums, columns)
        if np.isfinite(at):
            refined[m] = (at + 0.5) * s - 0.5
            cost[m] = best
    return li, ri, refined, cost


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


@njit(cache=True, nogil=True)
def _work_arrays(r, search, zero):
    """:func:`_slide_patch`'s work arrays: the costs per position, and the patch sums (left row,
    right row, SLR per position; the right band's column sums and squares) in the type of
    ``zero`` (see :func:`_sum_type`)."""
    width = 2 * r + 1 + 2 * search
    return np.empty(2 * search + 1), np.full((3, width), zero), np.full((2, width), zero)


@njit(cache=True, nogil=True)
def _slide_patch(img_l, img_r, u, v, u_right, r, search, costs, sums, columns):
    """One pair (left pixel (u, v), right column u_right of one level; all patches inside): the
    subpixel right column where the zero-mean patch difference is least (NaN: at the end of the
    search, or the parabola moves it by more than a pixel) and that least cost's square root.

    With n pixels a patch, left patch L and right patch R, the zero-mean SSD is
    (n SR2 - SR^2 - 2 (n SLR - SL SR) + n SL2 - SL^2) / n (S: sums over the patch): integer sums,
    exact. The right band's column sums give SR and SR2 of every position at once; only SLR is
    per position."""
    side = 2 * r + 1
    n_px = side * side
    sl, sl2 = _patch_sums(img_l, img_r, u, v, u_right, r, search, sums, columns)
    col_sum, col_sq = columns[0], columns[1]
    sr = 0
    sr2 = 0
    for c in range(side):
        sr += np.int64(col_sum[c])
        sr2 += np.int64(col_sq[c])
    left_term = n_px * sl2 - sl * sl
    for k in range(2 * search + 1):
        if k > 0:
            sr += np.int64(col_sum[k + side - 1]) - np.int64(col_sum[k - 1])
            sr2 += np.int64(col_sq[k + side - 1]) - np.int64(col_sq[k - 1])
        slr = np.int64(sums[2, k])
        costs[k] = (n_px * sr2 - sr * sr - 2 * (n_px * slr - sl * sr) + left_term) / n_px
    best = np.argmin(costs)
    if best == 0 or best == 2 * search:
        return np.nan, np.inf
    d1, d2, d3 = costs[best - 1], costs[best], costs[best + 1]
    denom = 2.0 * (d1 + d3 - 2.0 * d2)
    delta = (d1 - d3) / denom if denom != 0 else 0.0
    if abs(delta) > 1.0:
        return np.nan, np.inf
    # the cost: an RMS-like difference, as ORB-SLAM2's SAD
    return u_right + best - search + delta, np.sqrt(d2)


@njit(cache=True, nogil=True, fastmath=True)
def _patch_sums(img_l, img_r, u, v, u_right, r, search, sums, columns):
    """One pair's integer patch sums, in the type of ``sums``, which holds them exactly (so the
    reordering that fastmath allows changes nothing): (SL, SL2) returned; SLR per position in
    ``sums[2]``, the right band's column sums and squares in ``columns``."""
    side = 2 * r + 1
    n_pos = 2 * search + 1
    width = side + 2 * search
    left_row, right_row, slr = sums[0], sums[1], sums[2]
    col_sum, col_sq = columns[0], columns[1]
    slr[:] = 0
    col_sum[:] = 0
    col_sq[:] = 0
    sl = left_row[0] * 0
    sl2 = left_row[0] * 0
    for a in range(side):
        for b in range(side):
            left_row[b] = img_l[v - r + a, u - r + b]
        for c in range(width):
            right_row[c] = img_r[v - r + a, u_right - search - r + c]
        for b in range(side):
            sl += left_row[b]
            sl2 += left_row[b] * left_row[b]
        for c in range(width):
            col_sum[c] += right_row[c]
            col_sq[c] += right_row[c] * right_row[c]
        for b in range(side):
            for k in range(n_pos):
                slr[k] += left_row[b] * right_row[k + b]
    return np.int64(sl), np.int64(sl2)
