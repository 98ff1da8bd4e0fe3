"""Two-view map initialization of a monocular client (ORB-SLAM's Initializer, pure core).

A monocular camera measures no depth, so its map has to start from two views of the same scene:
the relative pose of the current frame to a reference frame and the 3D points of their matched
keypoints, both recovered from the matches alone. As ORB-SLAM does, two models are fitted (RANSAC)
and scored on all matches with symmetric transfer errors under a chi-square test:

* a homography H (planar scenes, or little parallax), and
* a fundamental matrix F = K^-T E K^-1 from the essential matrix E (general 3D scenes).

``R_H = S_H / (S_H + S_F)`` above ``h_ratio_threshold`` (0.45) selects the homography. The chosen
model is decomposed into its candidate motions (4 for H, OpenCV's ``decomposeHomographyMat``; 4 for
E, the candidates ``cv2.recoverPose`` chooses among, from ``decomposeEssentialMat``), the inliers
are triangulated under each, and the candidate with most points in front of both cameras with small
reprojection errors wins (points at infinity do not vote: they fit every candidate). Initialization
is accepted only when the median parallax is large enough, the winner is clear and it explains
enough of the inliers; otherwise the result says why (e.g. "not enough parallax: keep moving"), and
the caller tries again with a later frame. As in ORB-SLAM, a plane seen while moving towards it
stays ambiguous (the homography's two decompositions both put the points in front of the cameras)
until the motion has a sideways component.

RANSAC (OpenCV's USAC_ACCURATE, deterministic) gives both models; E is then refined on its inliers
by minimizing the Sampson error over (R, unit t), which made the translation direction several
times more accurate on synthetic tests; H is decomposed as OpenCV polished it.

The map has no metric scale: the translation comes out with unit length, and
:func:`scale_to_median_depth` rescales pose and points so the median depth of the points in the
reference camera is 1 (ORB-SLAM's convention). Whatever the unit, it stays the map's unit; only
another sensor (or a metric map it is merged with) can give it metres.

Conventions: ``T_a_b`` maps points from frame b into frame a (``p_a = T_a_b @ p_b``); ``T_cur_ref``
maps reference-camera points into the current camera. Camera optical frames: x right, y down,
z forward. Pixels are level-0 image coordinates; ``K`` is the 3x3 pinhole matrix.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..config import require
from ..errors import CoopSlamError
from ..geometry import skew
from ..registration.matching import match_descriptors
from .features import OrbKeypoints
from .matching import rotation_consistent

MODEL_HOMOGRAPHY = "homography"
MODEL_ESSENTIAL = "essential"

REASON_FEW_MATCHES = "too few matches"
REASON_NO_MODEL = "no model fits the matches"
REASON_PARALLAX = "not enough parallax: keep moving"
REASON_AMBIGUOUS = "ambiguous motion: several solutions explain the matches, keep moving"
REASON_FEW_POINTS = "too few points triangulate"

# Cosine of the parallax below which a point counts as "at infinity" (0.36 deg, ORB-SLAM's
# 0.99998): its depth sign is noise, so a negative depth does not count against a solution.
_COS_INFINITY = 0.99998


class MonoInitError(CoopSlamError):
    """Invalid input to the two-view initialization (shapes, NaN, intrinsics)."""


@dataclass
class MonoInitConfig:
    """Parameters of the two-view initialization. Pixel values refer to pyramid level 0."""

    sigma_px: float = 1.0  # keypoint position noise (ORB-SLAM's level-0 sigma) [px]
    # RANSAC inlier thresholds: the 95 % chi-square gates below at sigma_px, as distances.
    ransac_h_px: float = 2.45  # homography transfer error, sqrt(5.991) sigma [px]
    ransac_e_px: float = 1.96  # Sampson / epipolar distance, sqrt(3.841) sigma [px]
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 2000
    chi2_h: float = 5.991  # per-image transfer error gate (2 dof, 95 %) [sigma^2]
    chi2_f: float = 3.841  # per-image epipolar distance gate (1 dof, 95 %) [sigma^2]
    h_ratio_threshold: float = 0.45  # choose H when S_H / (S_H + S_F) exceeds this
    min_matches: int = 100  # fewer matches: do not even try (ORB-SLAM's 100)
    max_reprojection_px: float = 2.0  # triangulated point reprojection gate, both views [px]
    min_point_parallax_deg: float = 1.0  # points seen under less are not put in the map [deg]
    min_median_parallax_deg: float = 1.0  # median over the consistent points, else keep moving
    min_triangulated: int = 50  # points the initial map needs at least
    min_good_share: float = 0.9  # of the model's inliers the winner must explain
    # The winner is clear when every other candidate explains at most this share of its points
    # (ORB-SLAM: 0.7 for F, 0.75 for H).
    max_second_share: float = 0.7
    refine: bool = True  # refine E on its inliers (Sampson error) before scoring it
    # --- matching helper (match_for_initialization) ---
    match_ratio: float = 0.8  # Lowe ratio, brute force over the whole image
    match_max_distance: int = 50  # Hamming gate [bits] (ORB-SLAM's TH_LOW)
    match_check_orientation: bool = True  # rotation-histogram consistency
    match_max_displacement_px: float = 0.0  # drop matches that moved farther (0 = no gate) [px]

    def validate(self) -> None:
        for name in (
            "sigma_px",
            "ransac_h_px",
            "ransac_e_px",
            "chi2_h",
            "chi2_f",
            "max_reprojection_px",
        ):
            require(getattr(self, name) > 0, f"mono_init.{name} must be > 0")
        require(0 < self.ransac_confidence < 1, "mono_init.ransac_confidence must be in (0, 1)")
        require(self.ransac_max_iters >= 1, "mono_init.ransac_max_iters must be >= 1")
        require(0 < self.h_ratio_threshold < 1, "mono_init.h_ratio_threshold must be in (0, 1)")
        require(self.min_matches >= 8, "mono_init.min_matches must be >= 8 (8-point minimum)")
        require(self.min_point_parallax_deg >= 0, "mono_init.min_point_parallax_deg must be >= 0")
        require(self.min_median_parallax_deg >= 0, "mono_init.min_median_parallax_deg must be >= 0")
        require(self.min_triangulated >= 1, "mono_init.min_triangulated must be >= 1")
        require(0 < self.min_good_share <= 1, "mono_init.min_good_share must be in (0, 1]")
        require(0 < self.max_second_share < 1, "mono_init.max_second_share must be in (0, 1)")
        require(0 < self.match_ratio <= 1, "mono_init.match_ratio must be in (0, 1]")
        require(0 <= self.match_max_distance <= 256, "mono_init.match_max_distance: 0..256 bits")
        require(self.match_max_displacement_px >= 0, "mono_init.match_max_displacement_px >= 0")


@dataclass
class TwoViewResult:
    """Outcome of :func:`initialize_two_view`; ``success`` False means "try a later frame".

    When rejected, ``reason`` says why, ``T_cur_ref`` is None and the point arrays are empty; the
    diagnostics (model, scores, parallax, candidate counts) are filled as far as they were reached.
    """

    success: bool
    reason: str  # "" on success
    model: str  # MODEL_HOMOGRAPHY, MODEL_ESSENTIAL or "" (none fitted)
    T_cur_ref: np.ndarray | None  # (4, 4); translation of unit length (or scaled, see below)
    points_ref: np.ndarray  # (M, 3) triangulated points in the reference camera frame
    match_index: np.ndarray  # (M,) row of each point in the input match arrays
    parallax_deg: np.ndarray  # (M,) parallax angle of each point
    inliers: np.ndarray  # (N,) bool, inliers of the chosen model
    score_h: float = 0.0  # ORB-SLAM's S_H
    score_f: float = 0.0  # ORB-SLAM's S_F
    ratio_h: float = 0.0  # S_H / (S_H + S_F)
    median_parallax_deg: float = 0.0  # over the points the winning candidate explains
    # Per candidate motion, best first: points consistent with it, in front of both cameras and
    # not at infinity (the votes that choose the winner).
    candidate_votes: tuple[int, ...] = ()
    scale: float = 1.0  # factor applied to translation and points (scale_to_median_depth)

    @property
    def n_points(self) -> int:
        return len(self.points_ref)


@dataclass
class _Candidate:
    R: np.ndarray
    t: np.ndarray  # unit length
    good: np.ndarray  # (N_in,) bool: finite, reprojects within the gate, in front (unless at inf)
    keep: np.ndarray  # (N_in,) bool: good, in front of both cameras and enough parallax
    votes: np.ndarray  # (N_in,) bool: good, in front of both cameras and not at infinity
    points: np.ndarray  # (N_in, 3) in the reference camera
    parallax_deg: np.ndarray  # (N_in,)

    @property
    def n_good(self) -> int:
        return int(self.good.sum())

    @property
    def n_votes(self) -> int:
        """Points that tell this motion from the others: consistent, in front of both cameras and
        not at infinity (a point at infinity fits every candidate; its depth sign is noise)."""
        return int(self.votes.sum())

    @property
    def median_parallax_deg(self) -> float:
        return float(np.median(self.parallax_deg[self.good])) if self.good.any() else 0.0


# --- input checks ---------------------------------------------------------------------------------
def _as_uv(uv, name: str) -> np.ndarray:
    try:
        arr = np.ascontiguousarray(uv, dtype=np.float64)
    except (TypeError, ValueError):
        raise MonoInitError(f"{name} must be a numeric (N, 2) array of pixel coordinates") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise MonoInitError(
            f"{name} has shape {arr.shape}, expected (N, 2) pixel coordinates (u, v)"
        )
    if not np.all(np.isfinite(arr)):
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise MonoInitError(f"{name} holds {bad} row(s) with NaN or inf; drop those matches first")
    return arr


def check_intrinsics(K) -> np.ndarray:
    """``K`` as a float 3x3 pinhole matrix, or MonoInitError saying what is wrong."""
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise MonoInitError("K must be a numeric 3x3 camera matrix") from None
    if K.shape != (3, 3):
        raise MonoInitError(
            f"K has shape {K.shape}, expected the 3x3 matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"
        )
    if not np.all(np.isfinite(K)):
        raise MonoInitError("K contains NaN or inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0.0, 0.0, 1.0]).max() > 1e-9:
        raise MonoInitError(
            f"K = {K.tolist()} is not a pinhole matrix: need fx, fy > 0 and last row [0, 0, 1]"
        )
    return K


# --- model fitting and scoring --------------------------------------------------------------------
def _to_h(uv: np.ndarray) -> np.ndarray:
    return np.hstack([uv, np.ones((len(uv), 1))])


def score_homography(
    H_cur_ref: np.ndarray, uv_ref: np.ndarray, uv_cur: np.ndarray, sigma_px: float, chi2: float
) -> tuple[float, np.ndarray]:
    """ORB-SLAM's S_H: sum over both transfer directions of (chi2 - e^2 / sigma^2) where
    e^2 / sigma^2 < chi2; a match is an inlier when it passes in both directions."""
    inv_s2 = 1.0 / sigma_px**2
    score = 0.0
    inlier = np.ones(len(uv_ref), bool)
    try:
        H_ref_cur = np.linalg.inv(H_cur_ref)
    except np.linalg.LinAlgError:
        return 0.0, np.zeros(len(uv_ref), bool)
    for H, src, dst in ((H_cur_ref, uv_ref, uv_cur), (H_ref_cur, uv_cur, uv_ref)):
        p = _to_h(src) @ H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = p[:, :2] / p[:, 2:]
            e2 = ((proj - dst) ** 2).sum(axis=1) * inv_s2
        ok = np.isfinite(e2) & (e2 < chi2)
        score += float((chi2 - e2[ok]).sum())
        inlier &= ok
    return score, inlier


def score_fundamental(
    F_cur_ref: np.ndarray,
    uv_ref: np.ndarray,
    uv_cur: np.ndarray,
    sigma_px: float,
    chi2: float,
    chi2_score: float = 5.991,
) -> tuple[float, np.ndarray]:
    """ORB-SLAM's S_F: distances to the epipolar lines in both images, gated at ``chi2`` (1 dof)
    but scored against ``chi2_score`` (the 2-dof gate of S_H) so both scores are comparable."""
    inv_s2 = 1.0 / sigma_px**2
    x_ref, x_cur = _to_h(uv_ref), _to_h(uv_cur)
    score = 0.0
    inlier = np.ones(len(uv_ref), bool)
    # Line in the current image of each reference point, and in the reference image of each
    # current point.
    for lines, pts in ((x_ref @ F_cur_ref.T, x_cur), (x_cur @ F_cur_ref, x_ref)):
        num = (lines * pts).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            e2 = num**2 / (lines[:, 0] ** 2 + lines[:, 1] ** 2) * inv_s2
        ok = np.isfinite(e2) & (e2 < chi2)
        score += float((chi2_score - e2[ok]).sum())
        inlier &= ok
    return score, inlier


def _inv_intrinsics(K: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a pinhole K (np.linalg.inv of a 3x3 cost ~1 ms here: LAPACK call
    overhead, and the refinement needs it hundreds of times)."""
    fx, fy, cx, cy, s = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    return np.array(
        [[1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)], [0, 1 / fy, -cy / fy], [0, 0, 1]]
    )


def fundamental_from_pose(R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """F with x_cur^T F x_ref = 0 for the motion ``p_cur = R p_ref + t``."""
    K_inv = _inv_intrinsics(K)
    return K_inv.T @ skew(t) @ R @ K_inv


# --- triangulation and candidate checks -----------------------------------------------------------
def triangulate(
    R: np.ndarray, t: np.ndarray, uv_ref: np.ndarray, uv_cur: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """(N, 3) points in the reference camera, linear (DLT) from both views; NaN where degenerate."""
    P_ref = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P_cur = K @ np.hstack([R, t.reshape(3, 1)])
    X = cv2.triangulatePoints(P_ref, P_cur, uv_ref.T.copy(), uv_cur.T.copy())
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = (X[:3] / X[3]).T
    pts[~np.isfinite(pts).all(axis=1)] = np.nan
    return pts


def _project(K: np.ndarray, pts: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return (pts[:, :2] / pts[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2]


def _check_candidate(
    R: np.ndarray,
    t: np.ndarray,
    uv_ref: np.ndarray,
    uv_cur: np.ndarray,
    K: np.ndarray,
    cfg: MonoInitConfig,
) -> _Candidate:
    """Triangulate under one motion and classify the points (ORB-SLAM's CheckRT)."""
    t = t / np.linalg.norm(t)
    pts = triangulate(R, t, uv_ref, uv_cur, K)
    finite = np.isfinite(pts).all(axis=1)
    pts_cur = pts @ R.T + t
    center_cur = -R.T @ t  # the current camera's centre in the reference frame
    ray_ref = pts
    ray_cur = pts - center_cur
    with np.errstate(divide="ignore", invalid="ignore"):
        cos_par = (ray_ref * ray_cur).sum(axis=1) / (
            np.linalg.norm(ray_ref, axis=1) * np.linalg.norm(ray_cur, axis=1)
        )
    cos_par = np.where(finite, np.clip(cos_par, -1.0, 1.0), 1.0)
    parallax = np.degrees(np.arccos(cos_par))
    in_front = (pts[:, 2] > 0) & (pts_cur[:, 2] > 0)
    at_infinity = cos_par >= _COS_INFINITY
    gate2 = cfg.max_reprojection_px**2
    with np.errstate(invalid="ignore"):
        err_ref = ((_project(K, pts) - uv_ref) ** 2).sum(axis=1)
        err_cur = ((_project(K, pts_cur) - uv_cur) ** 2).sum(axis=1)
        reproj_ok = (err_ref <= gate2) & (err_cur <= gate2)
    good = finite & reproj_ok & (in_front | at_infinity)
    keep = good & in_front & (parallax >= cfg.min_point_parallax_deg)
    votes = good & in_front & ~at_infinity
    return _Candidate(R, t, good, keep, votes, pts, parallax)


def _homography_motions(H: np.ndarray, K: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    n_sol, Rs, ts, _ = cv2.decomposeHomographyMat(H, K)
    out = []
    for i in range(n_sol):
        t = np.asarray(ts[i], float).reshape(3)
        # An exact pure rotation decomposes with t = 0: no direction, nothing to triangulate.
        norm = np.linalg.norm(t)
        if norm > 1e-12:
            out.append((np.asarray(Rs[i], float), t / norm))
    return out


def _essential_motions(E: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    R1, R2, t = cv2.decomposeEssentialMat(E)
    t = t.reshape(3)
    return [(R1, t), (R1, -t), (R2, t), (R2, -t)]


def _refine_motion(
    R: np.ndarray,
    t: np.ndarray,
    uv_ref: np.ndarray,
    uv_cur: np.ndarray,
    K: np.ndarray,
    sigma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Minimize the Sampson epipolar error over (R, unit t) on the given matches.

    RANSAC's motion comes from a minimal sample; refining on all inliers brings it to the accuracy
    the matches allow. Five parameters: a rotation increment and two tangent steps of t.
    """
    x_ref, x_cur = _to_h(uv_ref), _to_h(uv_cur)
    # Tangent basis of the unit sphere at t.
    b1 = np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(t, b1)

    def motion(p):
        Rp = Rotation.from_rotvec(p[:3]).as_matrix() @ R
        tp = t + p[3] * b1 + p[4] * b2
        return Rp, tp / np.linalg.norm(tp)

    def residuals(p):
        F = fundamental_from_pose(*motion(p), K)
        Fx = x_ref @ F.T  # epipolar lines in the current image
        Ftx = x_cur @ F  # ... in the reference image
        num = (x_cur * Fx).sum(axis=1)
        den = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
        return num / np.sqrt(den)

    sol = least_squares(residuals, np.zeros(5), loss="soft_l1", f_scale=sigma, method="trf")
    return motion(sol.x)


def _fit_homography(
    uv_ref: np.ndarray, uv_cur: np.ndarray, cfg: MonoInitConfig
) -> tuple[np.ndarray | None, float, np.ndarray]:
    """(H_cur_ref, S_H, inliers) of the homography model; (None, 0, none) when none fits."""
    n = len(uv_ref)
    # USAC_ACCURATE (RANSAC with local optimization, fixed seed: deterministic) because plain
    # RANSAC is slow to give up on a non-planar scene (docs/tuning.md).
    H, _ = cv2.findHomography(
        uv_ref, uv_cur, cv2.USAC_ACCURATE, cfg.ransac_h_px, None, cfg.ransac_max_iters,
        cfg.ransac_confidence,
    )  # fmt: skip
    if H is None or H.shape != (3, 3) or not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
        return None, 0.0, np.zeros(n, bool)
    # No refinement of our own: OpenCV polishes H on its inliers, and a symmetric-transfer
    # refinement (tried) did not improve the decomposed motion (docs/tuning.md).
    score, inliers = score_homography(H, uv_ref, uv_cur, cfg.sigma_px, cfg.chi2_h)
    return H, score, inliers


def _fit_essential(
    uv_ref: np.ndarray, uv_cur: np.ndarray, K: np.ndarray, cfg: MonoInitConfig
) -> tuple[np.ndarray | None, float, np.ndarray]:
    """(E, S_F, inliers) of the essential-matrix model; (None, 0, none) when none fits."""
    n = len(uv_ref)
    # USAC_ACCURATE: plain RANSAC returns the model of its best minimal sample, which under
    # pixel noise is off by degrees in the translation direction (docs/tuning.md).
    E, _ = cv2.findEssentialMat(
        uv_ref, uv_cur, K, cv2.USAC_ACCURATE, cfg.ransac_confidence, cfg.ransac_e_px,
        maxIters=cfg.ransac_max_iters,
    )  # fmt: skip
    if E is None or E.shape[0] < 3 or not np.isfinite(E).all():
        return None, 0.0, np.zeros(n, bool)
    E = E[:3]  # a degenerate sample can return several stacked solutions; take the first
    K_inv = _inv_intrinsics(K)
    score, inliers = score_fundamental(
        K_inv.T @ E @ K_inv, uv_ref, uv_cur, cfg.sigma_px, cfg.chi2_f, cfg.chi2_h
    )
    if not cfg.refine:
        return E, score, inliers
    # Refining (R, t) refines E: all four decompositions give the same E up to sign, and the
    # Sampson error does not see the sign. Twice: the second pass starts from the inliers of the
    # first, which the first pass's better E gathers more completely.
    R, _, t = cv2.decomposeEssentialMat(E)
    t = t.reshape(3)
    for _ in range(2):
        if inliers.sum() < 8:
            break
        R, t = _refine_motion(R, t, uv_ref[inliers], uv_cur[inliers], K, cfg.sigma_px)
        E = skew(t) @ R
        score, inliers = score_fundamental(
            K_inv.T @ E @ K_inv, uv_ref, uv_cur, cfg.sigma_px, cfg.chi2_f, cfg.chi2_h
        )
    return E, score, inliers


# --- the initializer ------------------------------------------------------------------------------
def _rejected(reason: str, n: int, **diag) -> TwoViewResult:
    return TwoViewResult(
        success=False,
        reason=reason,
        model=diag.pop("model", ""),
        T_cur_ref=None,
        points_ref=np.zeros((0, 3)),
        match_index=np.zeros(0, int),
        parallax_deg=np.zeros(0),
        inliers=diag.pop("inliers", np.zeros(n, bool)),
        **diag,
    )


def initialize_two_view(
    uv_ref_px, uv_cur_px, K, config: MonoInitConfig | None = None
) -> TwoViewResult:
    """Relative pose and initial map from N matched keypoints of a reference and a current frame.

    ``uv_ref_px[i]`` and ``uv_cur_px[i]`` are the pixel positions (level 0) of match i (matching is
    the caller's; :func:`match_for_initialization` matches two frames' ORB features). Returns a
    :class:`TwoViewResult`: on success ``T_cur_ref`` (unit-length translation: the map has no metric
    scale) and the triangulated points in the reference camera frame with the rows of the matches
    they come from; on rejection the reason. Apply :func:`scale_to_median_depth` to get ORB-SLAM's
    map unit (median point depth 1). Raises MonoInitError on malformed input.
    """
    cfg = config if config is not None else MonoInitConfig()
    cfg.validate()
    uv_ref = _as_uv(uv_ref_px, "uv_ref_px")
    uv_cur = _as_uv(uv_cur_px, "uv_cur_px")
    if len(uv_ref) != len(uv_cur):
        raise MonoInitError(
            f"uv_ref_px has {len(uv_ref)} rows but uv_cur_px {len(uv_cur)}: row i of both must be "
            "the same match"
        )
    K = check_intrinsics(K)
    n = len(uv_ref)
    if n < cfg.min_matches:
        return _rejected(f"{REASON_FEW_MATCHES}: {n} < min_matches {cfg.min_matches}", n)

    # Both models on the same matches, each polished on its inliers before it is scored.
    H, score_h, in_h = _fit_homography(uv_ref, uv_cur, cfg)
    E, score_f, in_f = _fit_essential(uv_ref, uv_cur, K, cfg)
    if score_h + score_f <= 0:
        return _rejected(REASON_NO_MODEL, n)
    ratio_h = score_h / (score_h + score_f)
    if ratio_h > cfg.h_ratio_threshold:
        model, inliers, motions = MODEL_HOMOGRAPHY, in_h, _homography_motions(H, K)
    else:
        model, inliers, motions = MODEL_ESSENTIAL, in_f, _essential_motions(E)
    diag = {
        "model": model,
        "inliers": inliers,
        "score_h": score_h,
        "score_f": score_f,
        "ratio_h": ratio_h,
    }
    idx = np.flatnonzero(inliers)
    if len(idx) < cfg.min_triangulated:
        return _rejected(
            f"{REASON_FEW_POINTS}: the {model} has only {len(idx)} inliers "
            f"(< min_triangulated {cfg.min_triangulated})",
            n,
            **diag,
        )
    if not motions:  # the homography of a pure rotation
        return _rejected(f"{REASON_PARALLAX} (the {model} has no translation)", n, **diag)
    a, b = uv_ref[idx], uv_cur[idx]
    cands = sorted(
        (_check_candidate(R, t, a, b, K, cfg) for R, t in motions),
        key=lambda c: (c.n_votes, c.n_good),
        reverse=True,
    )
    best = cands[0]
    diag["candidate_votes"] = tuple(c.n_votes for c in cands)
    diag["median_parallax_deg"] = best.median_parallax_deg
    # Parallax first: under (near) pure rotation every candidate explains the matches equally
    # well, and the useful message is to move, not that the solution is ambiguous.
    if best.median_parallax_deg < cfg.min_median_parallax_deg:
        return _rejected(
            f"{REASON_PARALLAX} (median parallax {best.median_parallax_deg:.2f} deg < "
            f"{cfg.min_median_parallax_deg:g} deg)",
            n,
            **diag,
        )
    if len(cands) > 1 and cands[1].n_votes > cfg.max_second_share * best.n_votes:
        return _rejected(
            f"{REASON_AMBIGUOUS} ({model} candidates put {cands[0].n_votes} and "
            f"{cands[1].n_votes} of {len(idx)} inliers in front of both cameras)",
            n,
            **diag,
        )
    need = max(cfg.min_triangulated, int(np.ceil(cfg.min_good_share * len(idx))))
    n_keep = int(best.keep.sum())
    if best.n_good < need or n_keep < cfg.min_triangulated:
        return _rejected(
            f"{REASON_FEW_POINTS}: {best.n_good} of {len(idx)} {model} inliers consistent "
            f"(need {need}), {n_keep} triangulated with parallax >= "
            f"{cfg.min_point_parallax_deg:g} deg (need {cfg.min_triangulated})",
            n,
            **diag,
        )
    T = np.eye(4)
    T[:3, :3] = best.R
    T[:3, 3] = best.t
    return TwoViewResult(
        success=True,
        reason="",
        T_cur_ref=T,
        points_ref=best.points[best.keep],
        match_index=idx[best.keep],
        parallax_deg=best.parallax_deg[best.keep],
        **diag,
    )


def scale_to_median_depth(result: TwoViewResult) -> TwoViewResult:
    """The result rescaled so the median depth of its points in the reference camera is 1.

    ORB-SLAM's map unit for monocular maps: the scale is arbitrary (the map has no metric scale),
    this only fixes it to something of the order of the scene. ``scale`` records the factor.
    """
    if not result.success or result.T_cur_ref is None or result.n_points == 0:
        raise MonoInitError("scale_to_median_depth needs a successful initialization with points")
    median = float(np.median(result.points_ref[:, 2]))
    if not median > 0:
        raise MonoInitError(f"median point depth {median} is not positive; cannot scale")
    s = 1.0 / median
    T = result.T_cur_ref.copy()
    T[:3, 3] *= s
    return dataclasses.replace(
        result, T_cur_ref=T, points_ref=result.points_ref * s, scale=result.scale * s
    )


# --- matching helper ------------------------------------------------------------------------------
def match_for_initialization(
    kp_ref: OrbKeypoints, kp_cur: OrbKeypoints, config: MonoInitConfig | None = None
) -> np.ndarray:
    """(K, 2) int (ref index, cur index) ORB matches between the two frames of an initialization.

    Brute-force descriptor matching with ratio test and cross check
    (:func:`coop_slam.registration.match_descriptors`), then, as ORB-SLAM's SearchForInitialization,
    the rotation-histogram consistency (:func:`.matching.rotation_consistent`) and an optional gate
    on how far a keypoint moved.
    """
    cfg = config if config is not None else MonoInitConfig()
    cfg.validate()
    if len(kp_ref) < 2 or len(kp_cur) < 2:
        return np.zeros((0, 2), int)
    pairs = match_descriptors(
        kp_ref.descriptors,
        kp_cur.descriptors,
        ratio=cfg.match_ratio,
        max_distance=cfg.match_max_distance,
        mutual=True,
    )
    if len(pairs) and cfg.match_max_displacement_px > 0:
        moved = np.linalg.norm(kp_cur.uv_px[pairs[:, 1]] - kp_ref.uv_px[pairs[:, 0]], axis=1)
        pairs = pairs[moved <= cfg.match_max_displacement_px]
    if len(pairs) > 10 and cfg.match_check_orientation:
        keep = rotation_consistent(kp_ref.angle_deg[pairs[:, 0]], kp_cur.angle_deg[pairs[:, 1]])
        pairs = pairs[keep]
    return pairs
