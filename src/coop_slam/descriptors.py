"""Binary (ORB) descriptor utilities shared by tracking, place recognition and rendezvous.

Descriptors are ``(N, 32) uint8`` arrays (256 bits each); distances are Hamming bit counts.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .errors import CoopSlamError

DESCRIPTOR_BYTES = 32
_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_M8 = np.uint64(0x00FF00FF00FF00FF)
_H0001 = np.uint64(0x0001000100010001)
_S1, _S2, _S4, _S8, _S48, _S56 = (np.uint64(s) for s in (1, 2, 4, 8, 48, 56))


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


# Working memory [bytes] of one block of a distance matrix. Descriptors are compared block of rows
# by block of rows, so the memory needed does not grow with the product of the keyframes' sizes:
# two keyframes of 20,000 keypoints (a message the server accepts) would otherwise need a dense
# 20k x 20k matrix and its temporaries, 6.5 GB, and stall the server for half a minute.
BLOCK_BYTES = 32 << 20
_BLOCK_CELL_BYTES = 8  # per matrix cell: the float32 product and a float32 temporary


def _row_blocks(n_rows: int, n_cols: int):
    """Slices of rows such that a block of ``n_cols`` columns stays within BLOCK_BYTES."""
    step = max(1, BLOCK_BYTES // (_BLOCK_CELL_BYTES * max(1, n_cols)))
    for start in range(0, n_rows, step):
        yield slice(start, min(start + step, n_rows))


def _bits(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 256) float32 bits and (N,) float32 bit counts of descriptors."""
    bits = np.unpackbits(desc, axis=1).astype(np.float32)
    return bits, bits.sum(axis=1)


def _distance_block(bits_a, count_a, bits_b, count_b) -> np.ndarray:
    """(n, M) float32 Hamming distances of a block of rows (exact: integers up to 256)."""
    # |a xor b| = |a| + |b| - 2 a.b: one BLAS product instead of an N*M*32 XOR.
    dist = bits_a @ bits_b.T
    dist *= -2.0
    dist += count_a[:, None]
    dist += count_b[None, :]
    return dist


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) int32 Hamming distances between the rows of ``a`` (N, 32) and ``b`` (M, 32).

    The result itself is N x M x 4 bytes; the working memory beyond it stays within a block (see
    :data:`BLOCK_BYTES`). Matching should not ask for the whole matrix: :func:`match_ratio` keeps
    only what it needs of each block."""
    a = as_descriptors(a, "a")
    b = as_descriptors(b, "b")
    out = np.empty((len(a), len(b)), dtype=np.int32)
    if len(a) == 0 or len(b) == 0:
        return out
    bits_b, count_b = _bits(b)
    for rows in _row_blocks(len(a), len(b)):
        out[rows] = _distance_block(*_bits(a[rows]), bits_b, count_b)
    return out


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


_H01 = np.uint64(0x0101010101010101)


@njit(cache=True, nogil=True)
def hamming(a, b) -> int:
    """Bits differing between two descriptors given as four uint64 words each (a compiled
    kernel's view of a (N, 32) uint8 array: ``desc.view(np.uint64)``)."""
    total = 0
    for w in range(4):
        x = a[w] ^ b[w]
        x = x - ((x >> _S1) & _M1)
        x = (x & _M2) + ((x >> _S2) & _M2)
        x = (x + (x >> _S4)) & _M4
        total += int((x * _H01) >> _S56)
    return total


@njit(cache=True, nogil=True)
def most_distinctive(words, valid):
    """Per row of up to m descriptors (``words``: (n, m, 4) uint64 words; ``valid``: (n, m) which
    are there), the index of the one with the least median Hamming distance to the row's
    descriptors (itself included; the lower median of an even count; ties: the first); 0 for a
    row without any. (ORB-SLAM's distinctive descriptor of a map point.)"""
    n, m = valid.shape
    best = np.zeros(n, np.int64)
    dist = np.empty(m, np.int64)
    for i in range(n):
        n_valid = 0
        for a in range(m):
            n_valid += valid[i, a]
        k = (max(n_valid, 1) - 1) // 2
        least = -1
        for a in range(m):
            if not valid[i, a]:
                continue
            count = 0
            for b in range(m):
                if valid[i, b]:
                    dist[count] = hamming(words[i, a], words[i, b])
                    count += 1
            median = np.sort(dist[:count])[k]
            if least < 0 or median < least:
                least, best[i] = median, a
    return best


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
    The distances are computed block of query rows by block (see :data:`BLOCK_BYTES`), keeping per
    query row its best and second-best distance and per train row its best query so far.
    """
    query = as_descriptors(query, "a")
    train = as_descriptors(train, "b")
    n, m = len(query), len(train)
    if n == 0 or m < 2:
        return np.zeros((0, 2), dtype=int)
    bits_t, count_t = _bits(train)
    best = np.empty(n, dtype=np.int64)
    d_best = np.empty(n, dtype=np.int32)
    d_second = np.empty(n, dtype=np.int32)
    col_best = np.full(m, np.inf, dtype=np.float32)  # per train row: smallest distance so far
    col_arg = np.zeros(m, dtype=np.int64)  # ... and the first query row reaching it
    cols = np.arange(m)
    for rows in _row_blocks(n, m):
        dist = _distance_block(*_bits(query[rows]), bits_t, count_t)
        r = np.arange(dist.shape[0])
        j = np.argmin(dist, axis=1)
        best[rows], d_best[rows] = j, dist[r, j]
        if mutual:
            i = np.argmin(dist, axis=0)
            d_col = dist[i, cols]
            better = d_col < col_best  # strict: on ties the earlier row wins, as one argmin would
            col_best[better] = d_col[better]
            col_arg[better] = i[better] + rows.start
        dist[r, j] = np.inf
        d_second[rows] = dist.min(axis=1)
    keep = (d_best <= max_distance) & (d_best < ratio * d_second)
    q = np.arange(n)
    if mutual:
        keep &= col_arg[best] == q
    return np.stack([q[keep], best[keep]], axis=1).astype(int)
