"""Check a colour camera's focal length against a sequence's ground-truth motion.

The odometry takes the colour intrinsics from the camera model. A data set that publishes only its
depth camera's intrinsics (7-Scenes: 585 px, where a Kinect colour camera has about 525 px) makes
the odometry's rotations too small. Under the true motion between two frames, ORB matches satisfy
the epipolar constraint only with the right intrinsics, so the focal length that minimises their
(truncated) Sampson error is the one the colour images were taken with. Needs ground truth with
rotation in it; principal point and aspect ratio are taken from the model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..descriptors import match_ratio
from ..errors import CoopSlamError
from ..geometry import invert, rotation_angle_deg
from .features import orb_level0_uv


class IntrinsicsCheckError(CoopSlamError):
    """The sequence cannot tell the focal length (no ground truth, no rotation, no matches)."""


@dataclass
class FramePair:
    """Matched ORB keypoints of two frames and their true relative pose."""

    uv_a_px: np.ndarray  # (N, 2)
    uv_b_px: np.ndarray  # (N, 2)
    T_b_a: np.ndarray  # (4, 4) maps points of camera a into camera b


@dataclass
class FocalCheck:
    """Outcome of :func:`check_focal`."""

    focal_px: np.ndarray  # focal lengths tried
    error_px: np.ndarray  # mean truncated Sampson error at each [px]
    best_focal_px: float
    best_error_px: float
    model_focal_px: float
    model_error_px: float
    pairs: int
    matches: int

    @property
    def ratio(self) -> float:
        """Best focal length over the model's."""
        return self.best_focal_px / self.model_focal_px


def _uv(keypoints, orb) -> np.ndarray:
    pt = np.array([k.pt for k in keypoints]).reshape(-1, 2)
    octave = np.array([k.octave for k in keypoints], dtype=int)
    return orb_level0_uv(pt, octave, orb.getScaleFactor())


def match_pairs(
    load_gray: Callable[[int], np.ndarray],
    poses_se3: np.ndarray,
    gap: int = 8,
    min_rotation_deg: float = 2.0,
    max_pairs: int = 60,
    max_hamming: int = 40,
    progress: Callable[[int, int], None] | None = None,
) -> list[FramePair]:
    """Frame pairs ``(i, i + gap)`` whose true rotation is at least ``min_rotation_deg``, spread
    over the sequence, with cross-checked ORB matches. ``load_gray(i)`` gives frame i as a grey
    uint8 image; ``poses_se3`` (F, 4, 4) are ground-truth ``T_world_cam`` (NaN where unknown)."""
    poses_se3 = np.asarray(poses_se3, dtype=float)
    n = len(poses_se3)
    usable = []
    for i in range(max(0, n - gap)):
        A, B = poses_se3[i], poses_se3[i + gap]
        if not (np.isfinite(A).all() and np.isfinite(B).all()):
            continue
        T_b_a = invert(B) @ A
        if rotation_angle_deg(T_b_a[:3, :3]) >= min_rotation_deg:
            usable.append((i, T_b_a))
    if not usable:
        raise IntrinsicsCheckError(
            f"no frame pair {gap} frames apart turns by {min_rotation_deg} deg or more in the "
            "ground truth: the focal length cannot be told from this motion"
        )
    picks = np.unique(np.linspace(0, len(usable) - 1, min(max_pairs, len(usable))).astype(int))
    orb = cv2.ORB_create(2000)
    pairs = []
    for k, p in enumerate(picks):
        i, T_b_a = usable[p]
        kp_a, d_a = orb.detectAndCompute(load_gray(i), None)
        kp_b, d_b = orb.detectAndCompute(load_gray(i + gap), None)
        if d_a is not None and d_b is not None:
            # Mutual nearest neighbours only; the epipolar test itself needs no ratio test.
            m = match_ratio(d_a, d_b, ratio=1.0, max_distance=max_hamming, mutual=True)
            if len(m) >= 8:
                pairs.append(
                    FramePair(
                        _uv([kp_a[i] for i in m[:, 0]], orb),
                        _uv([kp_b[j] for j in m[:, 1]], orb),
                        T_b_a,
                    )
                )
        if progress is not None:
            progress(k + 1, len(picks))
    if not pairs:
        raise IntrinsicsCheckError("no frame pair has ORB matches: images empty or too dark?")
    return pairs


def sampson_errors(pair: FramePair, K: np.ndarray) -> np.ndarray:
    """Sampson distance [px] of each match to its epipolar line under the pair's true motion."""
    R, t = pair.T_b_a[:3, :3], pair.T_b_a[:3, 3]
    t_x = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    K_inv = np.linalg.inv(K)
    F = K_inv.T @ (t_x @ R) @ K_inv
    x_a = np.c_[pair.uv_a_px, np.ones(len(pair.uv_a_px))]
    x_b = np.c_[pair.uv_b_px, np.ones(len(pair.uv_b_px))]
    Fx_a = x_a @ F.T
    Ftx_b = x_b @ F
    num = np.abs(np.sum(x_b * Fx_a, axis=1))
    den = np.sqrt(Fx_a[:, 0] ** 2 + Fx_a[:, 1] ** 2 + Ftx_b[:, 0] ** 2 + Ftx_b[:, 1] ** 2)
    return num / np.maximum(den, 1e-12)


def check_focal(
    pairs: Sequence[FramePair],
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    scales: np.ndarray | None = None,
    truncate_px: float = 5.0,
) -> FocalCheck:
    """Mean Sampson error (each match's capped at ``truncate_px``, so outliers do not decide) for
    the model's focal lengths times each of ``scales``; the best scale is refined by a parabola
    through its neighbours."""
    if not pairs:
        raise IntrinsicsCheckError("no frame pairs to check")
    scales = np.linspace(0.8, 1.2, 41) if scales is None else np.asarray(scales, dtype=float)

    def error(scale: float) -> float:
        K = np.array([[fx * scale, 0.0, cx], [0.0, fy * scale, cy], [0.0, 0.0, 1.0]])
        e = np.concatenate([sampson_errors(p, K) for p in pairs])
        return float(np.mean(np.minimum(e, truncate_px)))

    errors = np.array([error(s) for s in scales])
    k = int(np.argmin(errors))
    best, best_error = float(scales[k]), float(errors[k])
    if 0 < k < len(scales) - 1:
        e0, e1, e2 = errors[k - 1 : k + 2]
        curvature = e0 - 2 * e1 + e2
        if curvature > 0:
            step = scales[k + 1] - scales[k]
            refined = float(scales[k] + 0.5 * step * (e0 - e2) / curvature)
            # The truncated error is not exactly a parabola: keep the grid point if it fits better.
            refined_error = error(refined)
            if refined_error <= e1:
                best, best_error = refined, refined_error
    return FocalCheck(
        focal_px=fx * scales,
        error_px=errors,
        best_focal_px=fx * best,
        best_error_px=best_error,
        model_focal_px=fx,
        model_error_px=error(1.0),
        pairs=len(pairs),
        matches=int(sum(len(p.uv_a_px) for p in pairs)),
    )
