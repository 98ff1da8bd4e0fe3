"""Closed-form weighted rigid / similarity alignment of 3D-3D correspondences (Umeyama 1991).

``T_dst_src, scale = umeyama(points_src, points_dst)`` minimises
``sum_i w_i || p_dst_i - (scale * R p_src_i + t) ||^2``; ``T_dst_src`` holds R and t (a proper
rigid transform), ``scale`` is 1 unless ``with_scale``. The batched form solves many small problems
at once (RANSAC minimal sets) with one stacked SVD.
"""

from __future__ import annotations

import numpy as np

from .camera import RegistrationError


def umeyama_batch(
    points_src: np.ndarray,
    points_dst: np.ndarray,
    weights: np.ndarray | None = None,
    with_scale: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Stacked alignment of (H, n, 3) point sets -> (T_dst_src (H, 4, 4), scale (H,)).

    No validation: degenerate sets give an arbitrary (but finite, proper) rotation.
    """
    src = np.asarray(points_src, dtype=float)
    dst = np.asarray(points_dst, dtype=float)
    if weights is None:
        w = np.full(src.shape[:2], 1.0 / src.shape[1])
    else:
        w = np.asarray(weights, dtype=float)
        w = w / w.sum(axis=1, keepdims=True)
    mu_src = np.einsum("hn,hnk->hk", w, src)
    mu_dst = np.einsum("hn,hnk->hk", w, dst)
    src_c = src - mu_src[:, None]
    dst_c = dst - mu_dst[:, None]
    cov = np.einsum("hn,hni,hnj->hij", w, dst_c, src_c)
    U, D, Vt = np.linalg.svd(cov)
    # Reflection guard: flip the weakest axis when det(U V^T) = -1 so R is a proper rotation.
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d[d == 0] = 1.0
    S = np.ones((len(src), 3))
    S[:, 2] = d
    R = np.einsum("hij,hj,hjk->hik", U, S, Vt)
    if with_scale:
        var_src = np.einsum("hn,hn->h", w, (src_c**2).sum(axis=2))
        scale = (D * S).sum(axis=1) / np.maximum(var_src, 1e-300)
    else:
        scale = np.ones(len(src))
    T = np.tile(np.eye(4), (len(src), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_dst - scale[:, None] * np.einsum("hij,hj->hi", R, mu_src)
    return T, scale


def umeyama(
    points_src: np.ndarray,
    points_dst: np.ndarray,
    weights: np.ndarray | None = None,
    with_scale: bool = False,
) -> tuple[np.ndarray, float]:
    """Weighted alignment of (N, 3) correspondences -> (T_dst_src 4x4, scale).

    Raises RegistrationError for mismatched or non-finite input, fewer than 3 points, non-positive
    weights or a degenerate (collinear) configuration.
    """
    src = np.asarray(points_src, dtype=float)
    dst = np.asarray(points_dst, dtype=float)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise RegistrationError(f"point sets must both be (N, 3), got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise RegistrationError(f"alignment needs at least 3 correspondences, got {len(src)}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise RegistrationError("point sets contain NaN or inf")
    if weights is not None:
        weights = np.asarray(weights, dtype=float).reshape(-1)
        if len(weights) != len(src) or not np.all(np.isfinite(weights)) or (weights < 0).any():
            raise RegistrationError("weights must be finite, >= 0 and one per correspondence")
        if weights.sum() <= 0:
            raise RegistrationError("weights sum to zero")
        weights = weights[None]
    # Collinear sets leave the rotation about their line undetermined.
    for name, pts in (("source", src), ("destination", dst)):
        sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if sv[1] <= 1e-9 * max(sv[0], 1e-12) or sv[0] <= 1e-12:
            raise RegistrationError(
                f"{name} points are collinear or coincident: no unique rotation"
            )
    T, scale = umeyama_batch(src[None], dst[None], weights, with_scale)
    return T[0], float(scale[0])
