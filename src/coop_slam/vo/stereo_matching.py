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

Vectorised: step 1 lists, per left pyramid level, the candidate pairs from the right keypoints of
the neighbouring levels sorted by row (a few dozen per left keypoint rather than all of them) and
takes descriptor distances of those pairs only;
step 2 gathers every patch of one pyramid level at once.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..descriptors import hamming_rows
from .config import VoConfig
from .features import OrbKeypoints


def level_images(gray: np.ndarray, scales: np.ndarray) -> list[np.ndarray]:
    """The image at each pyramid level (level 0 = gray), resized as OpenCV's ORB does."""
    h, w = gray.shape
    levels = [gray]
    for s in scales[1:]:
        size = (max(1, round(w / s)), max(1, round(h / s)))
        levels.append(cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR_EXACT))
    return levels


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
    of the module docstring)."""
    uR, vR, oR = right.uv_px[:, 0], right.uv_px[:, 1], right.octaves.astype(int)
    oL = left.octaves.astype(int)
    li_parts, ri_parts = [], []
    # Per left level, the right keypoints of its neighbouring levels only, in a band as wide as
    # the widest of them allows: a fraction of all row-band pairs.
    for level in np.unique(oL):
        lefts = np.flatnonzero(oL == level)
        rights = np.flatnonzero(np.abs(oR - level) <= 1)
        if len(rights) == 0:
            continue
        order = rights[np.argsort(vR[rights], kind="stable")]
        v_sorted = vR[order]
        band = config.stereo.row_tolerance_px * scales[min(level + 1, len(scales) - 1)]
        lo = np.searchsorted(v_sorted, left.uv_px[lefts, 1] - band, side="left")
        hi = np.searchsorted(v_sorted, left.uv_px[lefts, 1] + band, side="right")
        counts = hi - lo
        total = int(counts.sum())
        if total == 0:
            continue
        li_parts.append(np.repeat(lefts, counts))
        starts = np.repeat(lo - np.r_[0, np.cumsum(counts)[:-1]], counts)
        ri_parts.append(order[np.arange(total) + starts])
    if not li_parts:
        return np.zeros((0, 2), np.int64)
    li, ri = np.concatenate(li_parts), np.concatenate(ri_parts)
    disparity = left.uv_px[li, 0] - uR[ri]
    ok = (
        (np.abs(left.uv_px[li, 1] - vR[ri]) <= config.stereo.row_tolerance_px * scales[oR[ri]])
        & (disparity >= 0)
        & (disparity < fx)
    )
    li, ri = li[ok], ri[ok]
    if len(li) == 0:
        return np.zeros((0, 2), np.int64)
    dist = hamming_rows(left.descriptors[li], right.descriptors[ri])
    # The best candidate of each left keypoint (ties: the first right keypoint by row).
    best = np.lexsort((dist, li))
    first = np.r_[True, li[best][1:] != li[best][:-1]]
    best = best[first]
    keep = dist[best] < config.stereo.max_descriptor_distance
    return np.column_stack([li[best][keep], ri[best][keep]]).astype(np.int64)


def _refine(pairs, left, right, left_levels, right_levels, scales, config):
    """(refined right u [px] at level 0, best patch cost) per pair; NaN where refinement fails."""
    r, search = config.stereo.patch_radius_px, config.stereo.search_px
    refined = np.full(len(pairs), np.nan)
    cost = np.full(len(pairs), np.inf)
    octave = left.octaves[pairs[:, 0]].astype(int)
    offsets = np.arange(-r, r + 1)
    shifts = np.arange(-search, search + 1)
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
        rows = vl[:, None, None] + offsets[None, :, None]  # (n, P, 1)
        patch_l = img_l[rows, ul[:, None, None] + offsets[None, None, :]].astype(np.float32)
        patch_l -= patch_l.mean(axis=(1, 2), keepdims=True)
        cols = ur0[:, None, None, None] + shifts[None, :, None, None] + offsets[None, None, None, :]
        patch_r = img_r[rows[:, None, :, :], cols].astype(np.float32)  # (n, S, P, P)
        patch_r -= patch_r.mean(axis=(2, 3), keepdims=True)
        costs = ((patch_r - patch_l[:, None]) ** 2).sum(axis=(2, 3), dtype=np.float64)  # (n, S)
        best = np.argmin(costs, axis=1)
        interior = (best > 0) & (best < len(shifts) - 1)
        k = np.flatnonzero(interior)
        d1, d2, d3 = costs[k, best[k] - 1], costs[k, best[k]], costs[k, best[k] + 1]
        denom = 2.0 * (d1 + d3 - 2.0 * d2)
        with np.errstate(divide="ignore", invalid="ignore"):
            delta = np.where(denom != 0, (d1 - d3) / denom, 0.0)
        fine = np.abs(delta) <= 1.0
        k = k[fine]
        refined[sel[k]] = (ur0[k] + shifts[best[k]] + delta[fine] + 0.5) * s - 0.5
        cost[sel[k]] = np.sqrt(costs[k, best[k]])  # an RMS-like difference, as ORB-SLAM2's SAD
    return refined, cost
