"""Binary (ORB) descriptor utilities shared by tracking, place recognition and rendezvous.

Descriptors are ``(N, 32) uint8`` arrays (256 bits each); distances are Hamming bit counts.
"""

from __future__ import annotations

import numpy as np

from .errors import CoopSlamError

DESCRIPTOR_BYTES = 32
_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_M8 = np.uint64(0x00FF00FF00FF00FF)
_H0001 = np.uint64(0x0001000100010001)
_S1, _S2, _S4, _S8, _S48 = (np.uint64(s) for s in (1, 2, 4, 8, 48))


class DescriptorError(CoopSlamError):
    """Descriptor arrays of the wrong shape or type."""


def as_descriptors(desc, name: str = "descriptors") -> np.ndarray:
    """Return ``desc`` as a contiguous (N, 32) uint8 array or raise DescriptorError."""
    arr = np.asarray(desc)
    if arr.dtype != np.uint8:
        raise DescriptorError(f"{name} must be uint8, got {arr.dtype}")
    if arr.ndim == 1:
        if arr.size % DESCRIPTOR_BYTES:
            raise DescriptorError(
                f"{name} has {arr.size} bytes, not a multiple of {DESCRIPTOR_BYTES}"
            )
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


def popcount_u64_sum(x: np.ndarray) -> np.ndarray:
    """Bit count over the last axis of a uint64 array (destroys ``x``).

    SWAR bit counting on 64-bit words: ~5x faster than a byte lookup table, which is what makes a
    vocabulary transform of 1000 descriptors take about a millisecond. A descriptor is 4 words.
    """
    t = x >> _S1
    t &= _M1
    x -= t
    t = x >> _S2
    t &= _M2
    x &= _M2
    x += t
    t = x >> _S4
    x += t
    x &= _M4  # each byte now holds the bit count of its byte (<= 8)
    s = x[..., 0].copy()
    for j in range(1, x.shape[-1]):  # 4 words: byte counts stay <= 32, no carry between bytes
        s += x[..., j]
    # Fold bytes into 16-bit lanes before the horizontal sum: the total reaches 256, which would
    # overflow the top byte of the usual multiply-by-0x0101... trick.
    t = s >> _S8
    t &= _M8
    s &= _M8
    s += t
    s *= _H0001
    s >>= _S48
    return s


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance between equally long descriptor arrays (N, 32) -> (N,)."""
    x = as_descriptors(a, "a").view(np.uint64) ^ as_descriptors(b, "b").view(np.uint64)
    return popcount_u64_sum(x).astype(np.int32)


def match_ratio(
    query: np.ndarray,
    train: np.ndarray,
    ratio: float = 0.8,
    max_distance: int = 64,
    mutual: bool = True,
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
