"""Relative pose ``T_a_b`` (= ``T_camA_camB``) between two keyframes, with an acceptance test.

Two pipelines share one result type:

* :func:`estimate_pnp` (place recognition): match -> PnP RANSAC of B's keypoints against A's 3D
  points -> two-view BA -> acceptance. Needs depth (3D points) in A only.
* :func:`estimate_3d3d` (rendezvous): match -> 3D-3D RANSAC -> descriptor-gated ICP -> BA ->
  acceptance. Needs 3D points in both. A marker-based ``T_init`` is only an extra RANSAC hypothesis
  / ICP start and, with ``prior_sigma``, a weak BA prior: acceptance always counts feature inliers,
  so a marker sighting without feature support is rejected.
* :func:`estimate_similarity` (any pair with a monocular keyframe, whose points have no metric
  scale): match -> Sim(3) RANSAC + refinement over both reprojection errors
  (:func:`~coop_slam.registration.sim3.estimate_sim3`) -> acceptance; the result's ``scale``
  multiplies B's lengths into A's.

Rejection is a result (``accepted=False`` with a ``reason``); only invalid input raises
:class:`RegistrationError`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from ..config import require
from ..errors import GeometryError
from ..geometry import check_se3, transform_points
from .ba import BaResult, two_view_ba
from .camera import RegistrationError
from .icp import icp_descriptor
from .keyframe_view import KeyframeView, point_sigma_m
from .matching import match_descriptors
from .pnp import PNP_METHODS, pnp_ransac
from .ransac import ransac_rigid
from .sim3 import Sim3Config, estimate_sim3


@dataclass
class RegistrationConfig:
    """Parameters of both pipelines (defaults suit a Kinect-class RGB-D camera at VGA)."""

    # descriptor matching
    match_ratio: float = 0.8
    match_max_hamming: int = 64
    match_mutual: bool = True
    # 3D noise model: sigma^2 = floor^2 + (depth_sigma_per_m2 * z^2)^2 + (z * pixel_sigma / f)^2
    depth_min_m: float = 0.2
    depth_max_m: float = 8.0
    point_sigma_floor_m: float = 0.003
    depth_sigma_per_m2: float = 1.425e-3
    pixel_sigma_px: float = 1.0
    inlier_n_sigma: float = 3.0  # 3D inlier gate in sigmas of the pair (RANSAC, ICP)
    # 3D-3D RANSAC
    ransac_confidence: float = 0.999
    ransac_max_iterations: int = 2000
    ransac_batch: int = 64
    ransac_min_edge_factor: float = 2.0  # minimal-sample edges >= this x summed thresholds
    seed: int = 0
    # ICP
    icp_max_iterations: int = 30
    icp_start_factor: float = 4.0
    icp_decay: float = 0.5
    icp_max_hamming: int = 64
    icp_neighbours: int = 4
    # PnP
    pnp_method: str = "ap3p"
    pnp_reprojection_px: float = 5.0  # loose: A's depth errors show up here; BA re-gates at 2.5 px
    pnp_max_iterations: int = 500
    pnp_confidence: float = 0.999
    # bundle adjustment
    ba_huber_k: float = 1.345  # whitened units: bends at k * pixel_sigma_px
    ba_inlier_px: float = 2.5  # error gate applied in both images
    ba_use_depth: bool = True
    ba_depth_sigma_scale: float = 2.0  # >1: depth only weakly constrains the points
    ba_max_iterations: int = 30
    ba_rounds: int = 2
    ba_relative_tol: float = 1e-3  # Huber cost creeps on for many iterations; the pose does not
    # acceptance
    accept_min_inliers: int = 30
    accept_max_residual_px: float = 2.0
    accept_min_inlier_ratio: float = 0.2  # final inliers / descriptor matches
    # fraction of inliers with depth in both keyframes whose 3D points agree within the 3D gate
    # (checked when there are >= 3 such inliers): catches poses that fit pixels but not depth
    accept_min_3d_fraction: float = 0.5
    # BA marginal standard deviations of the relative pose (worst axis): rejects solutions that
    # fit the data but are ill-conditioned, e.g. all inliers clustered on one small object
    accept_max_sigma_rot_deg: float = 0.5
    accept_max_sigma_trans_m: float = 0.01
    # the similarity path (monocular keyframes); its inlier bar is accept_min_inliers above
    sim3: Sim3Config = field(default_factory=Sim3Config)

    def validate(self) -> None:
        require(0 < self.match_ratio <= 1, "match_ratio must be in (0, 1]")
        require(0 <= self.match_max_hamming <= 256, "match_max_hamming must be in [0, 256]")
        require(0 <= self.icp_max_hamming <= 256, "icp_max_hamming must be in [0, 256]")
        require(0 < self.depth_min_m < self.depth_max_m, "need 0 < depth_min_m < depth_max_m")
        require(self.point_sigma_floor_m > 0, "point_sigma_floor_m must be > 0")
        require(self.depth_sigma_per_m2 >= 0, "depth_sigma_per_m2 must be >= 0")
        require(self.pixel_sigma_px > 0, "pixel_sigma_px must be > 0")
        require(self.inlier_n_sigma > 0, "inlier_n_sigma must be > 0")
        require(0 < self.ransac_confidence < 1, "ransac_confidence must be in (0, 1)")
        require(0 < self.pnp_confidence < 1, "pnp_confidence must be in (0, 1)")
        for name in (
            "ransac_max_iterations",
            "ransac_batch",
            "icp_max_iterations",
            "icp_neighbours",
            "pnp_max_iterations",
            "ba_max_iterations",
            "ba_rounds",
        ):
            require(getattr(self, name) >= 1, f"{name} must be >= 1")
        require(self.icp_start_factor >= 1, "icp_start_factor must be >= 1")
        require(0 < self.icp_decay < 1, "icp_decay must be in (0, 1)")
        require(self.pnp_method in PNP_METHODS, f"pnp_method must be one of {sorted(PNP_METHODS)}")
        require(self.pnp_reprojection_px > 0, "pnp_reprojection_px must be > 0")
        require(self.ba_huber_k > 0, "ba_huber_k must be > 0")
        require(self.ba_inlier_px > 0, "ba_inlier_px must be > 0")
        require(self.ba_depth_sigma_scale > 0, "ba_depth_sigma_scale must be > 0")
        require(self.accept_min_inliers >= 4, "accept_min_inliers must be >= 4")
        require(self.accept_max_residual_px > 0, "accept_max_residual_px must be > 0")
        require(0 <= self.accept_min_inlier_ratio <= 1, "accept_min_inlier_ratio must be in [0, 1]")
        require(0 <= self.accept_min_3d_fraction <= 1, "accept_min_3d_fraction must be in [0, 1]")
        require(self.ba_relative_tol > 0, "ba_relative_tol must be > 0")
        require(self.accept_max_sigma_rot_deg > 0, "accept_max_sigma_rot_deg must be > 0")
        require(self.accept_max_sigma_trans_m > 0, "accept_max_sigma_trans_m must be > 0")
        require(self.ransac_min_edge_factor >= 0, "ransac_min_edge_factor must be >= 0")
        self.sim3.validate()


@dataclass
class RelativePoseResult:
    """Outcome of one estimate; ``T_a_b`` is the best estimate even when rejected (None if none)."""

    accepted: bool
    reason: str
    T_a_b: np.ndarray | None = None
    n_inliers: int = 0
    # (K, 2) feature indices (idx_a, idx_b) of the inlier correspondences
    inlier_idx: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=int))
    residual_px: float = np.nan  # RMS reprojection error of the inliers (both images)
    rmse_3d_m: float = np.nan  # RMS 3D distance of the 3D-consistent inliers (depth in both)
    fraction_3d: float = np.nan  # 3D-consistent share of the inliers with depth in both
    sigma_rot_deg: float = np.inf  # BA marginal std of the rotation (worst axis)
    sigma_trans_m: float = np.inf  # BA marginal std of the translation (worst direction)
    n_matches: int = 0  # descriptor correspondences
    # B's lengths in A's units: 1 for the rigid paths; a similarity (estimate_similarity) maps
    # p_a = scale * R p_b + t, with (R, t) = T_a_b and sigma_trans_m in A's units
    scale: float = 1.0
    sigma_log_scale: float = np.inf  # BA marginal std of log(scale) (similarity path only)
    inlier_ratio: float = 0.0
    timings_ms: dict = field(default_factory=dict)


def _check_inputs(kf_a, kf_b, cfg) -> RegistrationConfig:
    for name, kf in (("kf_a", kf_a), ("kf_b", kf_b)):
        if not isinstance(kf, KeyframeView):
            raise RegistrationError(f"{name} must be a KeyframeView, got {type(kf).__name__}")
    cfg = cfg if cfg is not None else RegistrationConfig()
    cfg.validate()
    return cfg


def _points_with_depth(kf: KeyframeView, cfg: RegistrationConfig) -> np.ndarray:
    """(N,) bool: 3D points within the trusted depth range."""
    z = np.nan_to_num(kf.points_cam[:, 2], nan=-1.0)
    return kf.has_point & (z >= cfg.depth_min_m) & (z <= cfg.depth_max_m)


def _sigma(kf: KeyframeView, cfg: RegistrationConfig) -> np.ndarray:
    """(N,) point noise sigma [m] (NaN where there is no point)."""
    f = 0.5 * (kf.K[0, 0] + kf.K[1, 1])
    return point_sigma_m(
        kf.points_cam[:, 2], cfg.point_sigma_floor_m, cfg.depth_sigma_per_m2, cfg.pixel_sigma_px / f
    )


def _depth_for_ba(kf: KeyframeView, idx: np.ndarray, cfg: RegistrationConfig):
    """(depths, sigmas) of the selected keypoints for BA range factors (0 = none)."""
    if not cfg.ba_use_depth:
        return None, None
    ok = _points_with_depth(kf, cfg)[idx]
    depth = np.where(ok, np.nan_to_num(kf.points_cam[idx, 2]), 0.0)
    sigma = cfg.ba_depth_sigma_scale * np.nan_to_num(_sigma(kf, cfg)[idx], nan=1.0)
    return depth, sigma


def _match(kf_a, kf_b, cfg, groups) -> np.ndarray:
    return match_descriptors(
        kf_a.descriptors,
        kf_b.descriptors,
        ratio=cfg.match_ratio,
        max_distance=cfg.match_max_hamming,
        mutual=cfg.match_mutual,
        groups=groups,
    )


def _run_ba(kf_a, kf_b, pairs, T0, cfg, T_prior=None, prior_sigma=None) -> BaResult:
    ia, ib = pairs[:, 0], pairs[:, 1]
    depth_a, sig_a = _depth_for_ba(kf_a, ia, cfg)
    depth_b, sig_b = _depth_for_ba(kf_b, ib, cfg)
    points0 = kf_a.points_cam[ia].copy()
    # Points without depth in A start from B's depth (moved into A) or, failing that, at the
    # median depth of the others along A's ray; BA then places them by reprojection.
    missing = ~np.isfinite(points0[:, 2])
    from_b = missing & np.isfinite(kf_b.points_cam[ib, 2])
    points0[from_b] = transform_points(T0, kf_b.points_cam[ib[from_b]])
    rest = ~np.isfinite(points0[:, 2])
    if rest.any():
        z = np.nanmedian(points0[:, 2]) if (~rest).any() else 2.0
        rays = np.c_[kf_a.uv_px[ia[rest]], np.ones(rest.sum())] @ np.linalg.inv(kf_a.K).T
        points0[rest] = rays * z
    return two_view_ba(
        kf_a.uv_px[ia],
        kf_b.uv_px[ib],
        kf_a.K,
        kf_b.K,
        points0,
        T0,
        depth_a,
        sig_a,
        depth_b,
        sig_b,
        sigma_px=cfg.pixel_sigma_px,
        huber_k=cfg.ba_huber_k,
        inlier_px=cfg.ba_inlier_px,
        T_prior_camA_camB=T_prior,
        prior_sigma=prior_sigma,
        max_iterations=cfg.ba_max_iterations,
        rounds=cfg.ba_rounds,
        relative_tol=cfg.ba_relative_tol,
    )


def _finish(kf_a, kf_b, pairs, ba: BaResult, n_matches, cfg, timings, t0) -> RelativePoseResult:
    """Acceptance test on the BA outcome."""
    inlier_idx = pairs[ba.inliers]
    n_inl = len(inlier_idx)
    ia, ib = inlier_idx[:, 0], inlier_idx[:, 1]
    both = _points_with_depth(kf_a, cfg)[ia] & _points_with_depth(kf_b, cfg)[ib]
    rmse_3d, fraction_3d = np.nan, np.nan
    if both.sum() >= 3:
        # Depth is checked robustly (share within the noise gate) because single keypoints on
        # depth edges or with misregistered depth are common and say little about the pose.
        dist = np.linalg.norm(
            kf_a.points_cam[ia[both]] - transform_points(ba.T_camA_camB, kf_b.points_cam[ib[both]]),
            axis=1,
        )
        gate = cfg.inlier_n_sigma * np.hypot(
            _sigma(kf_a, cfg)[ia[both]], _sigma(kf_b, cfg)[ib[both]]
        )
        consistent = dist < gate
        fraction_3d = float(consistent.mean())
        if consistent.any():
            rmse_3d = float(np.sqrt((dist[consistent] ** 2).mean()))
    ratio = min(1.0, n_inl / max(n_matches, 1))
    if n_inl < cfg.accept_min_inliers:
        reason = f"too few inliers ({n_inl} < {cfg.accept_min_inliers})"
    elif not ba.rms_px <= cfg.accept_max_residual_px:
        reason = f"residual {ba.rms_px:.2f} px > {cfg.accept_max_residual_px} px"
    elif ratio < cfg.accept_min_inlier_ratio:
        reason = f"inlier ratio {ratio:.2f} < {cfg.accept_min_inlier_ratio}"
    elif np.isfinite(fraction_3d) and fraction_3d < cfg.accept_min_3d_fraction:
        reason = (
            f"only {fraction_3d:.0%} of inliers agree in depth (< {cfg.accept_min_3d_fraction:.0%})"
        )
    elif not ba.sigma_rot_deg <= cfg.accept_max_sigma_rot_deg:
        reason = f"ill-conditioned: rotation sigma {ba.sigma_rot_deg:.2f} deg"
    elif not ba.sigma_trans_m <= cfg.accept_max_sigma_trans_m:
        reason = f"ill-conditioned: translation sigma {ba.sigma_trans_m:.3f} m"
    else:
        reason = "accepted"
    timings["total"] = 1e3 * (time.perf_counter() - t0)
    return RelativePoseResult(
        accepted=reason == "accepted",
        reason=reason,
        T_a_b=ba.T_camA_camB,
        n_inliers=n_inl,
        inlier_idx=inlier_idx,
        residual_px=ba.rms_px,
        rmse_3d_m=rmse_3d,
        fraction_3d=fraction_3d,
        sigma_rot_deg=ba.sigma_rot_deg,
        sigma_trans_m=ba.sigma_trans_m,
        n_matches=n_matches,
        inlier_ratio=ratio,
        timings_ms=timings,
    )


def _reject(reason, t0, timings, n_matches=0, T_a_b=None) -> RelativePoseResult:
    timings["total"] = 1e3 * (time.perf_counter() - t0)
    return RelativePoseResult(False, reason, T_a_b, n_matches=n_matches, timings_ms=timings)


class _Timer:
    """Accumulates stage durations [ms] into a dict."""

    def __init__(self, timings: dict):
        self.timings, self.last = timings, time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = 1e3 * (now - self.last)
        self.last = now


def estimate_pnp(
    kf_a: KeyframeView, kf_b: KeyframeView, cfg: RegistrationConfig | None = None, groups=None
) -> RelativePoseResult:
    """Place-recognition path: B's keypoints against A's 3D points (``groups``: BoW candidates)."""
    cfg = _check_inputs(kf_a, kf_b, cfg)
    t0 = time.perf_counter()
    timings: dict = {}
    timer = _Timer(timings)
    pairs = _match(kf_a, kf_b, cfg, groups)
    n_matches = len(pairs)
    pairs = pairs[_points_with_depth(kf_a, cfg)[pairs[:, 0]]]
    timer.lap("match")
    if len(pairs) < cfg.accept_min_inliers:
        return _reject(
            f"too few matches with 3D points ({len(pairs)} < {cfg.accept_min_inliers})",
            t0,
            timings,
            n_matches,
        )
    pnp = pnp_ransac(
        kf_a.points_cam[pairs[:, 0]],
        kf_b.uv_px[pairs[:, 1]],
        kf_b.K,
        reprojection_px=cfg.pnp_reprojection_px,
        max_iterations=cfg.pnp_max_iterations,
        confidence=cfg.pnp_confidence,
        method=cfg.pnp_method,
        min_inliers=4,
    )
    timer.lap("pnp")
    if pnp.T_camA_camB is None or pnp.n_inliers < cfg.accept_min_inliers:
        return _reject(
            f"PnP RANSAC found too few inliers ({pnp.n_inliers} < {cfg.accept_min_inliers})",
            t0,
            timings,
            n_matches,
            pnp.T_camA_camB,
        )
    pairs = pairs[pnp.inliers]
    ba = _run_ba(kf_a, kf_b, pairs, pnp.T_camA_camB, cfg)
    timer.lap("ba")
    return _finish(kf_a, kf_b, pairs, ba, n_matches, cfg, timings, t0)


def estimate_3d3d(
    kf_a: KeyframeView,
    kf_b: KeyframeView,
    cfg: RegistrationConfig | None = None,
    T_init: np.ndarray | None = None,
    prior_sigma=None,
    groups=None,
) -> RelativePoseResult:
    """Rendezvous path: 3D-3D RANSAC -> ICP -> BA.

    ``T_init`` (``T_camA_camB``, e.g. from a marker) is scored as one more RANSAC hypothesis and
    used as the ICP start when matches are too few for RANSAC; with ``prior_sigma``
    ((rot_rad, trans_m) or 6 tangent sigmas) it is also a weak BA prior.
    """
    cfg = _check_inputs(kf_a, kf_b, cfg)
    if T_init is not None:
        try:
            T_init = check_se3(T_init, "T_init")
        except GeometryError as exc:
            raise RegistrationError(str(exc)) from None
    elif prior_sigma is not None:
        raise RegistrationError("prior_sigma given without T_init")
    t0 = time.perf_counter()
    timings: dict = {}
    timer = _Timer(timings)
    valid_a, valid_b = _points_with_depth(kf_a, cfg), _points_with_depth(kf_b, cfg)
    sigma_a, sigma_b = _sigma(kf_a, cfg), _sigma(kf_b, cfg)
    pairs = _match(kf_a, kf_b, cfg, groups)
    n_matches = len(pairs)
    pairs = pairs[valid_a[pairs[:, 0]] & valid_b[pairs[:, 1]]]
    timer.lap("match")

    T0 = None
    if len(pairs) >= 3:
        thr = cfg.inlier_n_sigma * np.hypot(sigma_a[pairs[:, 0]], sigma_b[pairs[:, 1]])
        ransac = ransac_rigid(
            kf_b.points_cam[pairs[:, 1]],
            kf_a.points_cam[pairs[:, 0]],
            thr,
            confidence=cfg.ransac_confidence,
            max_iterations=cfg.ransac_max_iterations,
            batch_size=cfg.ransac_batch,
            seed=cfg.seed,
            min_edge_factor=cfg.ransac_min_edge_factor,
            extra_hypotheses=None if T_init is None else [T_init],
        )
        T0 = ransac.T_dst_src
    timer.lap("ransac")
    if T0 is None:
        T0 = T_init
    if T0 is None:
        return _reject(f"too few 3D-3D matches for RANSAC ({len(pairs)})", t0, timings, n_matches)

    points_a = np.where(valid_a[:, None], kf_a.points_cam, np.nan)
    points_b = np.where(valid_b[:, None], kf_b.points_cam, np.nan)
    icp = icp_descriptor(
        points_a,
        kf_a.descriptors,
        sigma_a,
        points_b,
        kf_b.descriptors,
        sigma_b,
        T0,
        gate_n_sigma=cfg.inlier_n_sigma,
        start_factor=cfg.icp_start_factor,
        decay=cfg.icp_decay,
        max_hamming=cfg.icp_max_hamming,
        k_neighbours=cfg.icp_neighbours,
        max_iterations=cfg.icp_max_iterations,
    )
    timer.lap("icp")
    if len(icp.pairs) < cfg.accept_min_inliers:
        return _reject(
            f"ICP found too few consistent pairs ({len(icp.pairs)} < {cfg.accept_min_inliers})",
            t0,
            timings,
            n_matches,
            icp.T_i_j,
        )
    ba = _run_ba(
        kf_a,
        kf_b,
        icp.pairs,
        icp.T_i_j,
        cfg,
        T_init if prior_sigma is not None else None,
        prior_sigma,
    )
    timer.lap("ba")
    return _finish(kf_a, kf_b, icp.pairs, ba, n_matches, cfg, timings, t0)


def estimate_similarity(
    kf_a: KeyframeView, kf_b: KeyframeView, cfg: RegistrationConfig | None = None, groups=None
) -> RelativePoseResult:
    """Similarity path: descriptor matches with a 3D point in both keyframes (any units: a
    monocular keyframe's are its map's) -> :func:`~coop_slam.registration.sim3.estimate_sim3`.
    Acceptance is Sim(3)'s (residual with the points held fixed, marginal sigmas relative to depth)
    with the rigid paths' inlier count and ratio."""
    cfg = _check_inputs(kf_a, kf_b, cfg)
    t0 = time.perf_counter()
    timings: dict = {}
    pairs = _match(kf_a, kf_b, cfg, groups)
    n_matches = len(pairs)
    pairs = pairs[kf_a.has_point[pairs[:, 0]] & kf_b.has_point[pairs[:, 1]]]
    timings["match"] = 1e3 * (time.perf_counter() - t0)
    if len(pairs) < cfg.accept_min_inliers:
        return _reject(
            f"too few matches with 3D points in both ({len(pairs)} < {cfg.accept_min_inliers})",
            t0,
            timings,
            n_matches,
        )
    sim_cfg = dataclasses.replace(
        cfg.sim3,
        accept_min_inliers=max(cfg.sim3.accept_min_inliers, cfg.accept_min_inliers),
        accept_min_inlier_ratio=max(cfg.sim3.accept_min_inlier_ratio, cfg.accept_min_inlier_ratio),
    )
    ia, ib = pairs[:, 0], pairs[:, 1]
    sim = estimate_sim3(
        kf_a.points_cam[ia],
        kf_a.uv_px[ia],
        kf_a.K,
        kf_b.points_cam[ib],
        kf_b.uv_px[ib],
        kf_b.K,
        sim_cfg,
    )
    timings.update({f"sim3_{k}": v for k, v in sim.timings_ms.items()})
    timings["total"] = 1e3 * (time.perf_counter() - t0)
    inlier_idx = pairs[sim.inliers] if len(sim.inliers) == len(pairs) else pairs[:0]
    return RelativePoseResult(
        accepted=sim.accepted,
        reason=sim.reason,
        T_a_b=sim.T_a_b,
        n_inliers=len(inlier_idx),
        inlier_idx=inlier_idx,
        residual_px=sim.residual_px,
        sigma_rot_deg=sim.sigma_rot_deg,
        sigma_trans_m=sim.sigma_trans,
        n_matches=n_matches,
        inlier_ratio=min(1.0, len(inlier_idx) / max(n_matches, 1)),
        timings_ms=timings,
        scale=float(sim.scale),
        sigma_log_scale=sim.sigma_scale_rel,
    )
