"""RANSAC over 3D-3D correspondences with 3-point minimal sets (rigid ``T_dst_src``).

Hypotheses are drawn and scored in batches (one stacked SVD, one (H, N) residual array per batch)
so there is no per-hypothesis Python work. Scoring is MSAC (truncated quadratic cost) with a
per-correspondence inlier threshold, since depth noise grows with range; the iteration count adapts
to the best inlier ratio found so far. The best hypothesis is refined by weighted Umeyama on its
inliers (a few local-optimisation rounds). Deterministic for a given seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import transform_points
from .camera import RegistrationError, check_points
from .umeyama import umeyama_batch


@dataclass
class RansacResult:
    """``T_dst_src`` is None when no non-degenerate hypothesis existed."""

    T_dst_src: np.ndarray | None
    inliers: np.ndarray  # (N,) bool
    n_iterations: int

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def required_iterations(inlier_ratio: float, confidence: float, sample_size: int = 3) -> float:
    """Draws needed to pick one all-inlier sample with probability ``confidence``."""
    p_good = inlier_ratio**sample_size
    if p_good <= 0:
        return np.inf
    if p_good >= 1:
        return 1.0
    return float(np.log(1.0 - confidence) / np.log(1.0 - p_good))


def _residuals(T_dst_src: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(H, N) distances of the transformed source points to their destinations."""
    moved = np.einsum("hij,nj->hni", T_dst_src[:, :3, :3], src) + T_dst_src[:, None, :3, 3]
    return np.linalg.norm(moved - dst[None], axis=2)


def ransac_rigid(
    points_src: np.ndarray,
    points_dst: np.ndarray,
    thresholds_m: np.ndarray | float,
    confidence: float = 0.999,
    max_iterations: int = 2000,
    batch_size: int = 64,
    seed: int = 0,
    extra_hypotheses: list[np.ndarray] | None = None,
    refine_rounds: int = 3,
    min_edge_factor: float = 2.0,
) -> RansacResult:
    """Robust rigid alignment of (N, 3) correspondences.

    ``thresholds_m``: inlier distance per correspondence (or one for all). ``extra_hypotheses``
    (e.g. a marker-based guess of ``T_dst_src``) are scored like drawn ones, so they win only if
    the data supports them better. Minimal samples whose edges are shorter than
    ``min_edge_factor`` x the summed thresholds of their ends are skipped: such a tight triangle
    fixes the rotation so poorly that a cluster of matches on one small object would support
    almost any rotation about it.
    """
    src = check_points(points_src, "points_src")
    dst = check_points(points_dst, "points_dst", len(src))
    n = len(src)
    thr = np.broadcast_to(np.asarray(thresholds_m, dtype=float), (n,)).copy()
    if not np.all(np.isfinite(thr)) or (thr <= 0).any():
        raise RegistrationError("RANSAC thresholds must be finite and > 0")
    if not 0 < confidence < 1 or max_iterations < 1 or batch_size < 1:
        raise RegistrationError("RANSAC needs 0 < confidence < 1 and positive iteration counts")
    inv_thr2 = 1.0 / thr**2

    best_T, best_cost, best_inliers = None, np.inf, np.zeros(n, dtype=bool)

    def consider(T_batch: np.ndarray) -> None:
        nonlocal best_T, best_cost, best_inliers
        res2 = _residuals(T_batch, src, dst) ** 2
        cost = np.minimum(res2 * inv_thr2, 1.0).sum(axis=1)
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost, best_T = cost[k], T_batch[k]
            best_inliers = res2[k] * inv_thr2 < 1.0

    if extra_hypotheses:
        consider(np.stack([np.asarray(T, dtype=float) for T in extra_hypotheses]))

    rng = np.random.default_rng(seed)
    iterations, needed = 0, float(max_iterations)
    while n >= 3 and iterations < min(needed, max_iterations):
        idx = rng.integers(0, n, size=(batch_size, 3))
        iterations += batch_size
        s, d = src[idx], dst[idx]
        # Reject samples with repeated indices, near-collinear or tiny triangles, or edge lengths
        # that differ between the two sides more than the noise allows (rigid motions keep them).
        distinct = (idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])
        area = np.linalg.norm(np.cross(s[:, 1] - s[:, 0], s[:, 2] - s[:, 0]), axis=1)
        edge_s = np.linalg.norm(s - np.roll(s, 1, axis=1), axis=2)
        edge_d = np.linalg.norm(d - np.roll(d, 1, axis=1), axis=2)
        edge_tol = thr[idx] + thr[np.roll(idx, 1, axis=1)]
        ok = distinct & (area > 1e-2 * np.max(edge_s, axis=1) ** 2 + 1e-12)
        ok &= np.all(np.abs(edge_s - edge_d) <= edge_tol, axis=1)
        ok &= np.all(np.minimum(edge_s, edge_d) >= min_edge_factor * edge_tol, axis=1)
        if not ok.any():
            continue
        T_batch, _ = umeyama_batch(s[ok], d[ok])
        consider(T_batch)
        if best_inliers.any():
            needed = required_iterations(best_inliers.mean(), confidence)

    if best_T is None:
        return RansacResult(None, best_inliers, iterations)
    for _ in range(refine_rounds):
        if best_inliers.sum() < 3:
            break
        T_ref, _ = umeyama_batch(
            src[best_inliers][None], dst[best_inliers][None], inv_thr2[best_inliers][None]
        )
        res = np.linalg.norm(transform_points(T_ref[0], src) - dst, axis=1)
        inliers = res < thr
        if inliers.sum() < best_inliers.sum():
            break
        best_T, best_inliers = T_ref[0], inliers
    return RansacResult(best_T, best_inliers, iterations)
