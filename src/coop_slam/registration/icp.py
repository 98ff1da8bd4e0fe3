"""ICP between the 3D feature points of two keyframes, gated by descriptor distance.

Each iteration moves the points of j into frame i with the current ``T_i_j``, finds for each the
``k`` spatial nearest neighbours in i (cKDTree built once), keeps the neighbour with the smallest
Hamming distance that is within both the spatial gate and ``max_hamming``, makes the association
one-to-one, and re-solves with weighted Umeyama (weights 1/sigma^2 of the pair). The spatial gate
starts at ``start_factor`` x the noise threshold and shrinks geometrically to 1x (a robust
schedule: wide enough to pull in a coarse initial guess, tight at the end to reject outliers).
Unlike ratio-test matching this also finds ambiguous-looking but geometrically consistent pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..descriptors import as_descriptors, hamming_rows
from ..errors import GeometryError
from ..geometry import check_se3, invert, rotation_angle_deg, transform_points
from .camera import RegistrationError, check_points
from .umeyama import umeyama_batch


@dataclass
class IcpResult:
    """``pairs`` are (idx_i, idx_j) associations (original indices) under the final ``T_i_j``."""

    T_i_j: np.ndarray
    pairs: np.ndarray  # (K, 2) int
    rms_m: float
    n_iterations: int
    converged: bool


def _associate(
    tree: cKDTree,
    points_i: np.ndarray,
    desc_i: np.ndarray,
    sigma_i: np.ndarray,
    moved_j: np.ndarray,
    desc_j: np.ndarray,
    sigma_j: np.ndarray,
    gate_n_sigma: float,
    max_hamming: int,
    k: int,
) -> np.ndarray:
    """(K, 2) one-to-one (i, j) associations passing the spatial and descriptor gates."""
    n_i = len(points_i)
    radius = gate_n_sigma * np.sqrt(sigma_j**2 + sigma_i.max() ** 2)
    dist, nn = tree.query(moved_j, k=min(k, n_i), distance_upper_bound=float(radius.max()))
    dist, nn = dist.reshape(len(moved_j), -1), nn.reshape(len(moved_j), -1)
    found = nn < n_i  # missing neighbours come back as index n_i with infinite distance
    nn_safe = np.where(found, nn, 0)
    j_idx = np.broadcast_to(np.arange(len(moved_j))[:, None], nn.shape)
    gate = gate_n_sigma * np.sqrt(sigma_i[nn_safe] ** 2 + sigma_j[j_idx] ** 2)
    ham = hamming_rows(desc_i[nn_safe.ravel()], desc_j[j_idx.ravel()]).reshape(nn.shape)
    ok = found & (dist <= gate) & (ham <= max_hamming)
    if not ok.any():
        return np.zeros((0, 2), dtype=int)
    # Best candidate per j: smallest Hamming distance, then smallest spatial distance.
    score = np.where(ok, ham + np.minimum(dist / np.maximum(gate, 1e-12), 1.0) * 0.5, np.inf)
    best = np.argmin(score, axis=1)
    rows = np.flatnonzero(np.isfinite(score[np.arange(len(score)), best]))
    cand_i = nn_safe[rows, best[rows]]
    cand_score = score[rows, best[rows]]
    # One-to-one: an i point claimed by several j keeps the best-scoring one.
    order = np.argsort(cand_score, kind="stable")
    _, first = np.unique(cand_i[order], return_index=True)
    keep = order[first]
    pairs = np.stack([cand_i[keep], rows[keep]], axis=1)
    return pairs[np.argsort(pairs[:, 1], kind="stable")]


def icp_descriptor(
    points_i: np.ndarray,
    desc_i: np.ndarray,
    sigma_i_m: np.ndarray,
    points_j: np.ndarray,
    desc_j: np.ndarray,
    sigma_j_m: np.ndarray,
    T_i_j_init: np.ndarray,
    gate_n_sigma: float = 3.0,
    start_factor: float = 4.0,
    decay: float = 0.5,
    max_hamming: int = 64,
    k_neighbours: int = 4,
    max_iterations: int = 30,
    tol_m: float = 1e-4,
    tol_rad: float = 1e-4,
    min_pairs: int = 3,
) -> IcpResult:
    """Refine ``T_i_j`` by ICP on two feature point sets (NaN rows = no point, ignored).

    ``sigma_*_m`` are per-point noise sigmas; the pair gate is ``gate_n_sigma`` x their root sum of
    squares (times the current schedule factor).
    """
    points_i = check_points(points_i, "points_i", allow_nan_rows=True)
    points_j = check_points(points_j, "points_j", allow_nan_rows=True)
    desc_i, desc_j = as_descriptors(desc_i, "desc_i"), as_descriptors(desc_j, "desc_j")
    sigma_i = np.asarray(sigma_i_m, dtype=float).reshape(-1)
    sigma_j = np.asarray(sigma_j_m, dtype=float).reshape(-1)
    if not (len(desc_i) == len(sigma_i) == len(points_i)) or not (
        len(desc_j) == len(sigma_j) == len(points_j)
    ):
        raise RegistrationError(
            "ICP inputs: points, descriptors and sigmas must have equal lengths"
        )
    try:
        T_i_j = check_se3(T_i_j_init, "T_i_j_init").copy()
    except GeometryError as exc:
        raise RegistrationError(str(exc)) from None
    valid_i = np.isfinite(points_i[:, 0]) & np.isfinite(sigma_i)
    valid_j = np.isfinite(points_j[:, 0]) & np.isfinite(sigma_j)
    vi, vj = np.flatnonzero(valid_i), np.flatnonzero(valid_j)
    empty = IcpResult(T_i_j, np.zeros((0, 2), dtype=int), np.nan, 0, False)
    if len(vi) < min_pairs or len(vj) < min_pairs:
        return empty
    p_i, d_i, s_i = points_i[vi], desc_i[vi], sigma_i[vi]
    p_j, d_j, s_j = points_j[vj], desc_j[vj], sigma_j[vj]
    tree = cKDTree(p_i)

    def associate(T_i_j: np.ndarray, n_sigma: float) -> np.ndarray:
        moved_j = transform_points(T_i_j, p_j)
        return _associate(
            tree, p_i, d_i, s_i, moved_j, d_j, s_j, n_sigma, max_hamming, k_neighbours
        )

    factor, converged, it = max(start_factor, 1.0), False, 0
    prev_pairs = np.zeros((0, 2), dtype=int)
    for it in range(1, max_iterations + 1):
        pairs = associate(T_i_j, gate_n_sigma * factor)
        if len(pairs) < min_pairs:
            return IcpResult(T_i_j, np.zeros((0, 2), dtype=int), np.nan, it, False)
        if factor <= 1.0 and np.array_equal(pairs, prev_pairs):
            converged = True  # same associations give the same solution: a fixed point
            break
        prev_pairs = pairs
        w = 1.0 / (s_i[pairs[:, 0]] ** 2 + s_j[pairs[:, 1]] ** 2)
        T_new, _ = umeyama_batch(p_j[pairs[:, 1]][None], p_i[pairs[:, 0]][None], w[None])
        delta = invert(T_i_j) @ T_new[0]
        T_i_j = T_new[0]
        step_rad = np.radians(rotation_angle_deg(delta[:3, :3]))
        if factor <= 1.0 and np.linalg.norm(delta[:3, 3]) < tol_m and step_rad < tol_rad:
            converged = True
            break
        factor = max(1.0, factor * decay)
    # Final association with the final transform, so pairs and rms describe T_i_j itself.
    pairs = associate(T_i_j, gate_n_sigma)
    if len(pairs) == 0:
        return IcpResult(T_i_j, np.zeros((0, 2), dtype=int), np.nan, it, False)
    res = transform_points(T_i_j, p_j[pairs[:, 1]]) - p_i[pairs[:, 0]]
    rms = float(np.sqrt((res**2).sum(axis=1).mean()))
    return IcpResult(
        T_i_j, np.stack([vi[pairs[:, 0]], vj[pairs[:, 1]]], axis=1), rms, it, converged
    )
