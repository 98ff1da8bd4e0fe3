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

Vectorised: OpenCV's brute-force matcher with a candidate mask does step 1; step 2 gathers every
patch of one pyramid level at once.
"""

from __future__ import annotations

import cv2
import numpy as np

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
    uL, vL = left.uv_px[:, 0], left.uv_px[:, 1]
    uR, vR = right.uv_px[:, 0], right.uv_px[:, 1]
    oL, oR = left.octaves.astype(int), right.octaves.astype(int)
    row_tol = config.stereo_row_tolerance_px * scales[oR]
    disparity = uL[:, None] - uR[None, :]
    mask = (
        (np.abs(vL[:, None] - vR[None, :]) <= row_tol[None, :])
        & (np.abs(oL[:, None] - oR[None, :]) <= 1)
        & (disparity >= 0)
        & (disparity < fx)
    )
    if not mask.any():
        return u_right
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    matches = matcher.match(left.descriptors, right.descriptors, mask.astype(np.uint8))
    pairs = np.array(
        [
            (m.queryIdx, m.trainIdx)
            for m in matches
            if m.distance < config.stereo_max_descriptor_distance and mask[m.queryIdx, m.trainIdx]
        ],
        dtype=np.int64,
    ).reshape(-1, 2)
    if len(pairs) == 0:
        return u_right
    refined, cost = _refine(pairs, left, right, left_levels, right_levels, scales, config)
    ok = np.isfinite(refined)
    if not ok.any():
        return u_right
    # Patch-cost outliers (ORB-SLAM2: 1.5 x 1.4 x the median).
    ok &= cost <= 1.5 * 1.4 * np.median(cost[ok])
    i = pairs[ok, 0]
    d = uL[i] - refined[ok]
    good = (d >= 0) & (d < fx)
    d = np.maximum(d[good], 0.01)  # a zero disparity is a point at infinity: keep it finite
    u_right[i[good]] = uL[i[good]] - d
    return u_right


def _refine(pairs, left, right, left_levels, right_levels, scales, config):
    """(refined right u [px] at level 0, best patch cost) per pair; NaN where refinement fails."""
    r, search = config.stereo_patch_radius_px, config.stereo_search_px
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
        patch_l = img_l[rows, ul[:, None, None] + offsets[None, None, :]].astype(float)  # (n, P, P)
        patch_l -= patch_l.mean(axis=(1, 2), keepdims=True)
        cols = ur0[:, None, None, None] + shifts[None, :, None, None] + offsets[None, None, None, :]
        patch_r = img_r[rows[:, None, :, :], cols].astype(float)  # (n, S, P, P)
        patch_r -= patch_r.mean(axis=(2, 3), keepdims=True)
        costs = ((patch_r - patch_l[:, None]) ** 2).sum(axis=(2, 3))  # (n, S)
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
