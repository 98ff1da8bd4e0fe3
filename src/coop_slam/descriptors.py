"""Binary (ORB) descriptor utilities shared by tracking, place recognition and rendezvous.

Descriptors are ``(N, 32) uint8`` arrays (256 bits each); distances are Hamming bit counts.
"""

from __future__ import annotations

import numpy as np

from .errors import CoopSlamError

DESCRIPTOR_BYTES = 32
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


class DescriptorError(CoopSlamError):
    """Descriptor arrays of the wrong shape or type."""


def as_descriptors(desc, name: str = "descriptors") -> np.ndarray:
    """Return ``desc`` as a contiguous (N, 32) uint8 array or raise DescriptorError."""
    arr = np.asarray(desc)
    if arr.dtype != np.uint8:
        raise DescriptorError(f"{name} must be uint8, got {arr.dtype}")
    if arr.ndim == 1:
        if arr.size % DESCRIPTOR_BYTES:
            raise DescriptorError(f"{name} has {arr.size} bytes, not a multiple of {DESCRIPTOR_BYTES}")
        arr = arr.reshape(-1, DESCRIPTOR_BYTES)
    if arr.ndim != 2 or arr.shape[1] != DESCRIPTOR_BYTES:
        raise DescriptorError(f"{name} has shape {arr.shape}, expected (N, {DESCRIPTOR_BYTES})")
    return np.ascontiguousarray(arr)


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) int32 Hamming distances between the rows of ``a`` (N, 32) and ``b`` (M, 32)."""
    a = as_descriptors(a, "a")
    b = as_descriptors(b, "b")
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)), dtype=np.int32)
    # Bits as 0/1 floats: |a xor b| = |a| + |b| - 2 a.b, one BLAS product instead of an N*M*32 XOR.
    bits_a = np.unpackbits(a, axis=1).astype(np.float32)
    bits_b = np.unpackbits(b, axis=1).astype(np.float32)
    dist = bits_a.sum(1)[:, None] + bits_b.sum(1)[None, :] - 2.0 * (bits_a @ bits_b.T)
    return np.rint(dist).astype(np.int32)


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance between equally long descriptor arrays (N, 32) -> (N,)."""
    return _POPCOUNT[np.bitwise_xor(as_descriptors(a, "a"), as_descriptors(b, "b"))].sum(
        axis=1, dtype=np.int32
    )


def match_ratio(
    query: np.ndarray, train: np.ndarray, ratio: float = 0.8, max_distance: int = 64, mutual: bool = True
) -> np.ndarray:
    """Nearest-neighbour matches with Lowe's ratio test; (K, 2) int array of (query_idx, train_idx).

    ``mutual`` also requires the train descriptor's best match to be the query one (cross check).
    """
    dist = hamming_matrix(query, train)
    if dist.size == 0 or dist.shape[1] < 2:
        return np.zeros((0, 2), dtype=int)
    order = np.argpartition(dist, 1, axis=1)[:, :2]
    rows = np.arange(len(dist))
    d0 = dist[rows, order[:, 0]]
    d1 = dist[rows, order[:, 1]]
    swap = d1 < d0
    best = np.where(swap, order[:, 1], order[:, 0])
    d_best, d_second = np.minimum(d0, d1), np.maximum(d0, d1)
    keep = (d_best <= max_distance) & (d_best < ratio * d_second)
    if mutual:
        back = np.argmin(dist, axis=0)
        keep &= back[best] == rows
    q = rows[keep]
    return np.stack([q, best[keep]], axis=1).astype(int)
