"""K-majority clustering of binary descriptors, the step that grows a vocabulary tree by a level
(DBoW2's HKmeans with k-majority for ORB): :func:`coop_slam.bow.vocabulary.train` clusters all
nodes of a level at once with :func:`k_majority`, seeded by greedy k-means++.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

from ..descriptors import DESCRIPTOR_BYTES, hamming_rows, popcount_u64_sum

_CHUNK = 16384  # rows per assignment step: bounds the (chunk, k, 4) temporaries to a few MB


def _kmeans_pp(
    x64: np.ndarray,
    x: np.ndarray,
    group: np.ndarray,
    starts: np.ndarray,
    sizes: np.ndarray,
    k: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """Greedy k-means++ seeds for all groups at once: (G, k, 4) uint64 centres.

    Rows are sorted by group. Candidate seeds are drawn with probability ~ D^2 within their group
    via one global cumulative sum; as in scikit-learn's greedy k-means++, 2 + log(k) candidates are
    drawn per step and the one that lowers the group's potential most is kept. Plain k-means++
    (DBoW2) puts two seeds into one true cluster often enough that k-majority, which cannot undo
    it, splits ~5 % of clearly separated clusters. Groups with fewer than k distinct rows repeat a
    seed; the duplicate clusters stay empty and are dropped.
    """
    n_groups = len(starts)
    trials = 2 + int(np.log(k))
    centres = np.zeros((n_groups, k, x64.shape[1]), dtype=np.uint64)
    pick = starts + (rng.random(n_groups) * sizes).astype(np.int64)
    centres[:, 0] = x64[pick]
    min_d = hamming_rows(x, x[pick][group]).astype(np.float64)
    ends = starts + sizes - 1
    groups = np.arange(n_groups)
    for c in range(1, k):
        cs = np.cumsum(min_d * min_d)
        before = np.where(starts > 0, cs[np.maximum(starts - 1, 0)], 0.0)
        totals = cs[ends] - before
        u = before[None, :] + rng.random((trials, n_groups)) * totals[None, :]
        picks = np.clip(np.searchsorted(cs, u, side="right"), starts, ends)  # (trials, G)
        picks = np.where(totals > 0, picks, starts)
        dists = np.stack([np.minimum(min_d, hamming_rows(x, x[p][group])) for p in picks])
        potential = np.stack([np.bincount(group, weights=d * d, minlength=n_groups) for d in dists])
        best = potential.argmin(axis=0)  # (G,)
        centres[:, c] = x64[picks[best, groups]]
        min_d = dists[best[group], np.arange(len(group))]
    return centres


def _assign(x64: np.ndarray, group: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index (0..k-1) of the nearest centre of each row's group."""
    out = np.empty(len(x64), dtype=np.int64)
    for s in range(0, len(x64), _CHUNK):
        c = np.take(centres, group[s : s + _CHUNK], axis=0)  # (m, k, 4)
        c ^= x64[s : s + _CHUNK, None, :]
        out[s : s + _CHUNK] = popcount_u64_sum(c).argmin(axis=1)
    return out


def k_majority(
    x: np.ndarray,
    group: np.ndarray,
    starts: np.ndarray,
    sizes: np.ndarray,
    k: int,
    rng: np.random.Generator,
    max_iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Batched k-majority clustering of every group: (label 0..k-1 per row, (G, k, 32) centres).

    Centres are per-bit majorities of their members. The bit sums of all clusters of all groups
    come from one sparse (clusters x rows) @ (rows x 256) product per iteration.
    """
    x64 = x.view(np.uint64)
    n_groups = len(starts)
    centres = _kmeans_pp(x64, x, group, starts, sizes, k, rng)
    label = _assign(x64, group, centres)
    bits = np.unpackbits(x, axis=1).astype(np.float32)  # exact counts up to 2^24 members
    rows = np.arange(len(x))
    for _ in range(max_iterations):
        cluster = group * k + label
        counts = np.bincount(cluster, minlength=n_groups * k)
        indptr = np.concatenate([[0], np.cumsum(counts)])
        member = scipy.sparse.csr_matrix(
            (np.ones(len(x), np.float32), rows[np.argsort(cluster, kind="stable")], indptr),
            shape=(n_groups * k, len(x)),
        )
        sums = member @ bits
        filled = counts > 0  # empty clusters keep their old centre
        majority = 2.0 * sums[filled] >= counts[filled, None]  # ties -> 1 as DBoW2's FORB
        flat = centres.reshape(n_groups * k, -1)
        flat[filled] = np.packbits(majority, axis=1).view(np.uint64)
        new_label = _assign(x64, group, centres)
        if np.array_equal(new_label, label):
            break
        label = new_label
    return label, centres.view(np.uint8).reshape(n_groups, k, DESCRIPTOR_BYTES)
