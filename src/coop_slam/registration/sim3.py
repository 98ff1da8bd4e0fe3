"""Similarity (Sim(3)) registration of two keyframes' map points, for monocular maps.

A monocular robot's map has no metric scale, so a merge or loop closure involving one estimates a
similarity ``p_a = scale * R p_b + t`` instead of a rigid transform. It is kept here as
``(T_a_b, scale)``: ``T_a_b`` is the rigid part (a proper 4x4 holding R and t, so the rigid helpers
in :mod:`coop_slam.geometry` apply to it) and ``scale`` multiplies the rotated point before the
translation; :func:`sim3_matrix` gives the 4x4 ``[[scale R, t], [0, 1]]``.

The estimate between two keyframes (:func:`estimate_sim3`) and the similarity helpers are here;
its steps have their modules:

* :func:`~.sim3_ransac.ransac_sim3`: RANSAC over 3-point minimal sets with Umeyama *with scale*,
  batched and seeded like :func:`~coop_slam.registration.ransac.ransac_rigid`. With pixels and
  intrinsics the inlier test is that of ORB-SLAM's Sim3Solver: each point, moved into the other
  keyframe, must reproject onto that keyframe's observation (a chi2 bound per image), except that
  the bound's sigma also counts the moved point's own noise; without pixels it is a 3D distance
  relative to depth, since the scale of either map is unknown.
* :func:`~.sim3_refine.refine_sim3`: Huber-robust Levenberg-Marquardt
  (:func:`coop_slam.optim.lm.least_squares`) on the 7 parameters (rotation, translation,
  log-scale) minimising both reprojection errors with the map points held fixed (as ORB-SLAM's
  OptimizeSim3), optionally with relative depth residuals, and the covariance of the similarity
  at the solution (calibrated: on the synthetic tests its NEES is close to the 7 expected).
* :func:`estimate_sim3`: both on two keyframes' matched map points plus an acceptance test,
  returning a :class:`Sim3Result` (rejection is a result, invalid input raises
  :class:`~.sim3_data.Sim3Error`, :mod:`.sim3_data` holding the correspondences and their checks).

GTSAM 4.2's ``gtsam.Similarity3(R, t, s)`` maps ``p -> s (R p + t)``: our ``(T, scale)`` is
``gtsam.Similarity3(R, t / scale, scale)``, and its ``matrix()`` is ``[[R, t], [0, 1/s]]``. The
Python wrapper has neither Lie-group operations nor factors or ``Values`` support for it, hence the
small numpy solver here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..config import require
from .sim3_data import (
    CHI2_2DOF_99,
    Sim3Error,
    check_intrinsics_sim3,
    check_pixels,
    check_points_in_front,
    check_sigmas,
)
from .sim3_ransac import Sim3RansacResult, ransac_sim3
from .sim3_refine import Sim3RefineResult, refine_sim3


# --- similarity helpers ---------------------------------------------------------------------------
def sim3_matrix(T_dst_src: np.ndarray, scale: float) -> np.ndarray:
    """4x4 ``[[scale R, t], [0, 1]]`` of a similarity given as rigid part and scale."""
    S = np.array(T_dst_src, dtype=float, copy=True)
    S[:3, :3] *= scale
    return S


def sim3_inverse(T_dst_src: np.ndarray, scale: float) -> tuple[np.ndarray, float]:
    """``(T_src_dst, 1 / scale)``: p_src = R^T (p_dst - t) / scale."""
    R, t = T_dst_src[:3, :3], T_dst_src[:3, 3]
    T_src_dst = np.eye(4)
    T_src_dst[:3, :3] = R.T
    T_src_dst[:3, 3] = -R.T @ t / scale
    return T_src_dst, 1.0 / scale


def sim3_transform_points(T_dst_src: np.ndarray, scale: float, points_src: np.ndarray):
    """(N, 3) points of frame src moved into frame dst: ``scale * R p + t``."""
    points_src = np.asarray(points_src, dtype=float).reshape(-1, 3)
    return scale * points_src @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]


# --- two-keyframe estimate ------------------------------------------------------------------------
@dataclass
class Sim3Config:
    """Parameters of :func:`estimate_sim3` (defaults follow ORB-SLAM's loop-closing Sim3)."""

    pixel_sigma_px: float = 1.0  # keypoint noise when no per-point sigmas are given
    chi2_threshold: float = CHI2_2DOF_99  # per-image gate in sigma^2 (RANSAC and refinement)
    fix_scale: bool = False  # True when both maps are metric (stereo / RGB-D): the rigid case
    # RANSAC
    ransac_confidence: float = 0.999
    ransac_max_iterations: int = 2000
    ransac_batch: int = 64
    ransac_refine_rounds: int = 3
    ransac_min_edge_factor: float = 2.0  # minimal-sample edges >= this x summed 3D gates
    seed: int = 0
    # refinement
    refine_huber_k: float = 1.345  # whitened units: bends at k * sigma
    # combined relative depth noise of a matched pair of map points for the refinement's depth
    # residuals; 0 leaves them out (ORB-SLAM: reprojection only)
    refine_depth_sigma_rel: float = 0.0
    refine_max_iterations: int = 20
    refine_rounds: int = 2
    refine_relative_tol: float = 1e-6
    # acceptance
    accept_min_inliers: int = 20
    # RMS per-image error of the inliers; the map points are held fixed, so each residual carries
    # both keyframes' noise: about 2 px (2D norm) at 1 px keypoint noise in each
    accept_max_residual_px: float = 3.0
    accept_min_inlier_ratio: float = 0.2  # final inliers / correspondences
    # marginal standard deviations (worst axis) of the refined similarity: reject solutions that
    # fit but are ill-conditioned. Translation is relative to the median inlier depth in A, since
    # A's units need not be metres.
    accept_max_sigma_rot_deg: float = 0.5
    accept_max_sigma_trans_rel: float = 0.02
    # 3 %, not 2: two ground robots' monocular maps of corridor walls (one depth, so scale and
    # translation along the view trade) had no candidate under 2 % (revisit world: 2.1-10 %),
    # and merged at 3 % as when their keyframes were denser
    accept_max_sigma_scale_rel: float = 0.03

    def validate(self) -> None:
        require(self.pixel_sigma_px > 0, "pixel_sigma_px must be > 0")
        require(self.chi2_threshold > 0, "chi2_threshold must be > 0 (9.21: 2-dof 99 %)")
        require(0 < self.ransac_confidence < 1, "ransac_confidence must be in (0, 1)")
        for name in (
            "ransac_max_iterations",
            "ransac_batch",
            "refine_max_iterations",
            "refine_rounds",
        ):
            require(getattr(self, name) >= 1, f"{name} must be >= 1")
        require(self.ransac_refine_rounds >= 0, "ransac_refine_rounds must be >= 0")
        require(self.ransac_min_edge_factor >= 0, "ransac_min_edge_factor must be >= 0")
        require(self.refine_huber_k > 0, "refine_huber_k must be > 0")
        require(self.refine_depth_sigma_rel >= 0, "refine_depth_sigma_rel must be >= 0 (0: off)")
        require(self.refine_relative_tol > 0, "refine_relative_tol must be > 0")
        require(self.accept_min_inliers >= 3, "accept_min_inliers must be >= 3")
        require(self.accept_max_residual_px > 0, "accept_max_residual_px must be > 0")
        require(0 <= self.accept_min_inlier_ratio <= 1, "accept_min_inlier_ratio must be in [0, 1]")
        require(self.accept_max_sigma_rot_deg > 0, "accept_max_sigma_rot_deg must be > 0")
        require(self.accept_max_sigma_trans_rel > 0, "accept_max_sigma_trans_rel must be > 0")
        require(self.accept_max_sigma_scale_rel > 0, "accept_max_sigma_scale_rel must be > 0")


@dataclass
class Sim3Result:
    """Outcome of :func:`estimate_sim3`: ``p_a = scale * R p_b + t`` with ``T_a_b`` = (R, t).

    ``T_a_b`` / ``scale`` are the best estimate even when rejected (None / NaN if there is none).
    """

    accepted: bool
    reason: str
    T_a_b: np.ndarray | None = None
    scale: float = np.nan
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (N,) bool
    residual_px: float = np.nan  # RMS per-image reprojection error of the inliers
    initial_residual_px: float = np.nan  # same at the RANSAC estimate
    sigma_rot_deg: float = np.inf  # marginal std of the rotation (worst axis)
    sigma_trans: float = np.inf  # marginal std of the translation, in A's length units
    sigma_scale_rel: float = np.inf  # marginal std of log(scale)
    covariance: np.ndarray = field(default_factory=lambda: np.full((7, 7), np.inf))
    n_correspondences: int = 0
    inlier_ratio: float = 0.0
    ransac_inliers: int = 0
    ransac_iterations: int = 0
    timings_ms: dict = field(default_factory=dict)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def sim3_a_b(self) -> np.ndarray | None:
        """4x4 ``[[scale R, t], [0, 1]]`` (None without an estimate)."""
        return None if self.T_a_b is None else sim3_matrix(self.T_a_b, self.scale)


def _verdict(ref: Sim3RefineResult, ratio: float, points_a: np.ndarray, cfg: Sim3Config) -> str:
    """ "accepted", or why not: too few inliers, too large a residual, too small an inlier
    ``ratio``, or ill-conditioned (a marginal sigma above its bound)."""
    n_inl = ref.n_inliers
    depth_a = float(np.median(points_a[ref.inliers, 2])) if n_inl else np.nan
    sigma_trans_rel = ref.sigma_trans / depth_a if n_inl else np.inf
    if n_inl < cfg.accept_min_inliers:
        return f"too few inliers after refinement ({n_inl} < {cfg.accept_min_inliers})"
    if not ref.rms_px <= cfg.accept_max_residual_px:
        return f"residual {ref.rms_px:.2f} px > {cfg.accept_max_residual_px} px"
    if ratio < cfg.accept_min_inlier_ratio:
        return f"inlier ratio {ratio:.2f} < {cfg.accept_min_inlier_ratio}"
    if not ref.sigma_rot_deg <= cfg.accept_max_sigma_rot_deg:
        return f"ill-conditioned: rotation sigma {ref.sigma_rot_deg:.2f} deg"
    if not sigma_trans_rel <= cfg.accept_max_sigma_trans_rel:
        return f"ill-conditioned: translation sigma {sigma_trans_rel:.1%} of the median depth"
    if not ref.sigma_scale_rel <= cfg.accept_max_sigma_scale_rel:
        return f"ill-conditioned: scale sigma {ref.sigma_scale_rel:.1%}"
    return "accepted"


@dataclass
class _View:
    """One keyframe's side of the correspondences, checked: map points in its camera frame, their
    pixels, its intrinsics and the keypoints' sigmas."""

    points: np.ndarray
    uv: np.ndarray
    K: np.ndarray
    sigma: np.ndarray


def _checked_view(points_cam, uv_px, K, sigma_px, name: str, n: int | None = None) -> _View:
    points = check_points_in_front(points_cam, f"points_{name}_cam", n)
    n = len(points)
    return _View(
        points,
        check_pixels(uv_px, f"uv_{name}_px", n),
        check_intrinsics_sim3(K, f"K_{name}"),
        check_sigmas(sigma_px, f"sigma_{name}_px", n),
    )


def _ransac(a: _View, b: _View, cfg: Sim3Config) -> Sim3RansacResult:
    # B is the source: RANSAC's T_dst_src is then T_a_b.
    return ransac_sim3(
        b.points,
        a.points,
        uv_src_px=b.uv,
        uv_dst_px=a.uv,
        K_src=b.K,
        K_dst=a.K,
        sigma_src_px=b.sigma,
        sigma_dst_px=a.sigma,
        chi2_threshold=cfg.chi2_threshold,
        fix_scale=cfg.fix_scale,
        confidence=cfg.ransac_confidence,
        max_iterations=cfg.ransac_max_iterations,
        batch_size=cfg.ransac_batch,
        seed=cfg.seed,
        refine_rounds=cfg.ransac_refine_rounds,
        min_edge_factor=cfg.ransac_min_edge_factor,
    )


def _refine(a: _View, b: _View, ransac: Sim3RansacResult, cfg: Sim3Config) -> Sim3RefineResult:
    return refine_sim3(
        ransac.T_dst_src,
        ransac.scale,
        b.points,
        b.uv,
        b.K,
        a.points,
        a.uv,
        a.K,
        active=ransac.inliers,
        sigma_src_px=b.sigma,
        sigma_dst_px=a.sigma,
        chi2_threshold=cfg.chi2_threshold,
        depth_sigma_rel=cfg.refine_depth_sigma_rel,
        huber_k=cfg.refine_huber_k,
        fix_scale=cfg.fix_scale,
        max_iterations=cfg.refine_max_iterations,
        rounds=cfg.refine_rounds,
        relative_tol=cfg.refine_relative_tol,
    )


def estimate_sim3(
    points_a_cam: np.ndarray,
    uv_a_px: np.ndarray,
    K_a: np.ndarray,
    points_b_cam: np.ndarray,
    uv_b_px: np.ndarray,
    K_b: np.ndarray,
    config: Sim3Config | None = None,
    *,
    sigma_a_px: np.ndarray | float | None = None,
    sigma_b_px: np.ndarray | float | None = None,
) -> Sim3Result:
    """Similarity ``T_a_b, scale`` between two keyframes from N matched map points.

    Row i is one correspondence: map point i in A's camera frame with its observed pixel in A, and
    its match in B's camera frame with its pixel in B. ``sigma_*_px`` (one or per point, e.g. the
    keypoint's pyramid scale) default to ``config.pixel_sigma_px``. Pipeline: RANSAC (reprojection
    gate in both images) -> robust refinement -> acceptance on inlier count, residual, inlier ratio
    and the marginal sigmas. Invalid input raises :class:`Sim3Error`.
    """
    cfg = config if config is not None else Sim3Config()
    if not isinstance(cfg, Sim3Config):
        raise Sim3Error(f"config must be a Sim3Config, got {type(cfg).__name__}")
    cfg.validate()
    t0 = time.perf_counter()
    timings: dict = {}
    a = _checked_view(
        points_a_cam, uv_a_px, K_a, cfg.pixel_sigma_px if sigma_a_px is None else sigma_a_px, "a"
    )
    n = len(a.points)
    b = _checked_view(
        points_b_cam, uv_b_px, K_b, cfg.pixel_sigma_px if sigma_b_px is None else sigma_b_px, "b", n
    )

    def finish(reason: str, **fields) -> Sim3Result:
        timings["total"] = 1e3 * (time.perf_counter() - t0)
        fields.setdefault("inliers", np.zeros(n, dtype=bool))
        return Sim3Result(
            reason == "accepted", reason, n_correspondences=n, timings_ms=timings, **fields
        )

    if n < cfg.accept_min_inliers:
        return finish(f"too few correspondences ({n} < {cfg.accept_min_inliers})")
    ransac = _ransac(a, b, cfg)
    timings["ransac"] = 1e3 * (time.perf_counter() - t0)
    common = dict(ransac_inliers=ransac.n_inliers, ransac_iterations=ransac.n_iterations)
    if ransac.T_dst_src is None:
        return finish(
            "no usable minimal sample: the points are collinear, coincident or too close together",
            **common,
        )
    if ransac.n_inliers < cfg.accept_min_inliers:
        return finish(
            f"RANSAC found too few inliers ({ransac.n_inliers} < {cfg.accept_min_inliers})",
            T_a_b=ransac.T_dst_src,
            scale=ransac.scale,
            inliers=ransac.inliers,
            **common,
        )
    t1 = time.perf_counter()
    ref = _refine(a, b, ransac, cfg)
    timings["refine"] = 1e3 * (time.perf_counter() - t1)
    ratio = ref.n_inliers / n
    return finish(
        _verdict(ref, ratio, a.points, cfg),
        T_a_b=ref.T_dst_src,
        scale=ref.scale,
        inliers=ref.inliers,
        residual_px=ref.rms_px,
        initial_residual_px=ref.initial_rms_px,
        sigma_rot_deg=ref.sigma_rot_deg,
        sigma_trans=ref.sigma_trans,
        sigma_scale_rel=ref.sigma_scale_rel,
        covariance=ref.covariance,
        inlier_ratio=ratio,
        **common,
    )
