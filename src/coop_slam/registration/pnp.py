"""PnP RANSAC of keyframe B's keypoints against keyframe A's 3D points -> ``T_camA_camB``.

OpenCV's solver works with the object frame (camera A) and returns ``T_camB_camA``; it is
inverted here so callers only see the ``T_a_b`` convention. The RANSAC pose is refined with
Levenberg-Marquardt on its inliers and the inlier set recomputed with the refined pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import invert, se3, transform_points
from .camera import RegistrationError, check_intrinsics, check_points, project

PNP_METHODS = {"ap3p": cv2.SOLVEPNP_AP3P, "epnp": cv2.SOLVEPNP_EPNP}


@dataclass
class PnpResult:
    """``T_camA_camB`` (and its inverse ``T_camB_camA``, as the solver found it) are None when
    RANSAC found no pose."""

    T_camA_camB: np.ndarray | None
    inliers: np.ndarray  # (N,) bool
    errors_px: np.ndarray  # (N,) reprojection error in B (inf behind the camera); None unrefined
    T_camB_camA: np.ndarray | None = None

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def reprojection_errors(T_camB_camA: np.ndarray, points_camA, uv_px_b, K_b) -> np.ndarray:
    """(N,) pixel distance between B's keypoints and A's points projected into B (inf behind)."""
    uv = project(transform_points(T_camB_camA, points_camA), K_b)
    err = np.linalg.norm(uv - uv_px_b, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def pnp_ransac(
    points_camA: np.ndarray,
    uv_px_b: np.ndarray,
    K_b: np.ndarray,
    reprojection_px: float = 3.0,
    max_iterations: int = 500,
    confidence: float = 0.999,
    method: str = "ap3p",
    min_inliers: int = 6,
    refine: bool = True,
) -> PnpResult:
    """Pose of camera B in camera A from (N, 3) points of A and their (N, 2) pixels in B.

    With ``refine`` the RANSAC pose is refined (Levenberg-Marquardt on its inliers) and the
    inliers recomputed; without, RANSAC's pose and inliers are returned as they are, for a caller
    that refines with its own model (the odometry's pose optimization)."""
    points_camA = check_points(points_camA, "points_camA")
    uv_px_b = np.asarray(uv_px_b, dtype=float)
    if uv_px_b.shape != (len(points_camA), 2) or not np.all(np.isfinite(uv_px_b)):
        raise RegistrationError(
            f"uv_px_b must be finite ({len(points_camA)}, 2), got {uv_px_b.shape}"
        )
    K_b = check_intrinsics(K_b, "K_b")
    if method not in PNP_METHODS:
        raise RegistrationError(f"unknown PnP method '{method}'; use one of {sorted(PNP_METHODS)}")
    n = len(points_camA)
    none = PnpResult(None, np.zeros(n, dtype=bool), np.full(n, np.inf))
    if n < max(min_inliers, 4):  # AP3P needs 4 points (3 + 1 to disambiguate), EPnP 4 too
        return none
    try:
        ok, rvec, tvec, idx = cv2.solvePnPRansac(
            points_camA,
            uv_px_b,
            K_b,
            None,
            iterationsCount=int(max_iterations),
            reprojectionError=float(reprojection_px),
            confidence=float(confidence),
            flags=PNP_METHODS[method],
        )
    except cv2.error:  # degenerate input (e.g. all points on a line)
        return none
    if not ok or idx is None or len(idx) < max(min_inliers, 4):
        return none
    idx = idx.ravel()
    if not refine:
        T_camB_camA = se3(cv2.Rodrigues(rvec)[0], tvec.ravel())
        inliers = np.zeros(n, dtype=bool)
        inliers[idx] = True
        return PnpResult(invert(T_camB_camA), inliers, None, T_camB_camA)
    rvec, tvec = cv2.solvePnPRefineLM(points_camA[idx], uv_px_b[idx], K_b, None, rvec, tvec)
    T_camB_camA = se3(cv2.Rodrigues(rvec)[0], tvec.ravel())
    errors = reprojection_errors(T_camB_camA, points_camA, uv_px_b, K_b)
    inliers = errors < reprojection_px
    if inliers.sum() < max(min_inliers, 4):
        return PnpResult(None, inliers, errors)
    return PnpResult(invert(T_camB_camA), inliers, errors, T_camB_camA)
