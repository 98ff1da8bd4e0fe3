"""RANSAC for a similarity ``p_dst = scale R p_src + t`` (Sim(3)) between two keyframes' map
points: 3-point minimal sets solved by Umeyama *with scale*, batched and seeded like
:func:`~coop_slam.registration.ransac.ransac_rigid`, scored by the reprojection gate of ORB-SLAM's
Sim3Solver in both images (or a 3D gate relative to depth without pixels), the best hypothesis
refined by weighted Umeyama on its inliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ransac import required_iterations
from .sim3_data import CHI2_2DOF_99, Correspondences, Sim3Error, make_correspondences
from .umeyama import umeyama_batch


@dataclass
class Sim3RansacResult:
    """``T_dst_src`` (rigid part) is None and ``scale`` NaN when no usable sample existed."""

    T_dst_src: np.ndarray | None
    scale: float
    inliers: np.ndarray  # (N,) bool
    n_iterations: int

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def ransac_sim3(
    points_src: np.ndarray,
    points_dst: np.ndarray,
    relative_threshold: float = 0.05,
    *,
    uv_src_px: np.ndarray | None = None,
    uv_dst_px: np.ndarray | None = None,
    K_src: np.ndarray | None = None,
    K_dst: np.ndarray | None = None,
    sigma_src_px: np.ndarray | float = 1.0,
    sigma_dst_px: np.ndarray | float = 1.0,
    chi2_threshold: float = CHI2_2DOF_99,
    fix_scale: bool = False,
    confidence: float = 0.999,
    max_iterations: int = 2000,
    batch_size: int = 64,
    seed: int = 0,
    refine_rounds: int = 3,
    min_edge_factor: float = 2.0,
) -> Sim3RansacResult:
    """Robust similarity ``p_dst = scale R p_src + t`` from (N, 3) correspondences.

    Points are in their keyframes' camera frames (z > 0). With ``uv_*_px`` (each point's observed
    pixel in its own keyframe) and ``K_*``, a correspondence is an inlier when its squared
    reprojection error in *both* images is below ``chi2_threshold * sigma^2``, sigma combining the
    observing keypoint's noise with the moved point's (``sigma_*_px`` per point, e.g. from the
    keypoint's pyramid level; see ``Correspondences.residual_sigmas``); otherwise when its 3D error
    in both frames is below ``relative_threshold`` x the point's depth. ``fix_scale``: scale held
    at 1 (metric maps).

    Minimal samples whose edges are shorter than ``min_edge_factor`` x the summed gates of their
    ends (as 3D distances at the points' depths) are skipped, in both frames: such a tight or
    collinear triple fixes rotation and scale too poorly to be worth scoring. The best hypothesis
    is refined by weighted Umeyama on its inliers for ``refine_rounds``. Deterministic per seed.
    """
    data = make_correspondences(
        points_src,
        points_dst,
        relative_threshold,
        uv_src_px,
        uv_dst_px,
        K_src,
        K_dst,
        sigma_src_px,
        sigma_dst_px,
        chi2_threshold,
    )
    if not 0 < confidence < 1 or max_iterations < 1 or batch_size < 1 or refine_rounds < 0:
        raise Sim3Error("RANSAC needs 0 < confidence < 1 and positive iteration counts")
    if not min_edge_factor >= 0:
        raise Sim3Error("min_edge_factor must be >= 0")
    rng = np.random.default_rng(seed)
    best = _Hypothesis(None, np.nan, np.inf, np.zeros(len(data.src), dtype=bool))
    iterations, needed = 0, float(max_iterations)
    while iterations < min(needed, max_iterations):
        idx = rng.integers(0, len(data.src), size=(batch_size, 3))
        iterations += batch_size
        ok = _usable_samples(data, idx, min_edge_factor)
        if not ok.any():
            continue
        T_batch, scale_batch = umeyama_batch(
            data.src[idx[ok]], data.dst[idx[ok]], with_scale=not fix_scale
        )
        good = np.isfinite(scale_batch) & (scale_batch > 1e-12)
        if not good.any():
            continue
        best.consider(data, T_batch[good], scale_batch[good])
        if best.inliers.any():
            needed = required_iterations(best.inliers.mean(), confidence)
    if best.T is None:
        return Sim3RansacResult(None, np.nan, best.inliers, iterations)
    _refine_hypothesis(data, best, refine_rounds, fix_scale)
    return Sim3RansacResult(best.T, best.scale, best.inliers, iterations)


@dataclass
class _Hypothesis:
    """The best similarity so far: its truncated cost (gate-normalised errors capped at 1)."""

    T: np.ndarray | None
    scale: float
    cost: float
    inliers: np.ndarray

    def consider(self, data: Correspondences, T_batch: np.ndarray, scale_batch: np.ndarray):
        """Keep the batch's best hypothesis if it beats this one."""
        err = data.normalized_errors(T_batch, scale_batch)
        cost = np.minimum(err, 1.0).sum(axis=1)
        k = int(np.argmin(cost))
        if cost[k] < self.cost:
            self.cost, self.T, self.scale = cost[k], T_batch[k], float(scale_batch[k])
            self.inliers = err[k] < 1.0


def _usable_samples(data: Correspondences, idx: np.ndarray, min_edge_factor: float) -> np.ndarray:
    """(B,) bool: the minimal samples (B, 3) of three distinct points that are neither collinear
    nor tighter than ``min_edge_factor`` x their gates, in both frames."""
    ok = (idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])
    for pts, thr in ((data.src[idx], data.thr3d_src), (data.dst[idx], data.thr3d_dst)):
        edges = np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2)
        area = np.linalg.norm(np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]), axis=1)
        ok &= area > 1e-2 * np.max(edges, axis=1) ** 2 + 1e-12
        edge_tol = thr[idx] + thr[np.roll(idx, 1, axis=1)]
        ok &= np.all(edges >= min_edge_factor * edge_tol, axis=1)
    return ok


def _refine_hypothesis(data: Correspondences, best: _Hypothesis, rounds: int, fix_scale: bool):
    """Weighted Umeyama on ``best``'s inliers, in place, while the inliers do not shrink."""
    # Umeyama's residual lives in dst: weight it by the inverse squared gate there so near points
    # (small gates) count as much as their tighter reprojection bound says.
    weights = 1.0 / data.thr3d_dst**2
    for _ in range(rounds):
        if best.inliers.sum() < 3:
            break
        T_ref, scale_ref = umeyama_batch(
            data.src[best.inliers][None],
            data.dst[best.inliers][None],
            weights[best.inliers][None],
            with_scale=not fix_scale,
        )
        if not (np.isfinite(scale_ref[0]) and scale_ref[0] > 1e-12):
            break
        inliers = data.normalized_errors(T_ref, scale_ref)[0] < 1.0
        if inliers.sum() < best.inliers.sum():
            break
        best.T, best.scale, best.inliers = T_ref[0], float(scale_ref[0]), inliers
