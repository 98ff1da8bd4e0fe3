"""Descriptor correspondences between two keyframes (ratio test, optionally within BoW groups).

Without groups every feature of A competes with every feature of B. With groups (a BoW feature
vector: for each vocabulary node shared by both keyframes, the feature indices of A and of B under
it) the ratio test runs inside each group only, as ORB-SLAM's SearchByBoW does, which is faster
and less ambiguous in repetitive scenes.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from ..descriptors import as_descriptors, hamming_rows, match_ratio
from .camera import RegistrationError


def _unique_pairs(pairs: np.ndarray, desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """Keep each feature of A and of B in at most one pair, preferring the smallest distance."""
    if len(pairs) == 0:
        return pairs
    dist = hamming_rows(desc_a[pairs[:, 0]], desc_b[pairs[:, 1]])
    pairs = pairs[np.argsort(dist, kind="stable")]
    pairs = pairs[np.sort(np.unique(pairs[:, 0], return_index=True)[1])]
    pairs = pairs[np.sort(np.unique(pairs[:, 1], return_index=True)[1])]
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def match_descriptors(
    desc_a: np.ndarray,
    desc_b: np.ndarray,
    ratio: float = 0.8,
    max_distance: int = 64,
    mutual: bool = True,
    groups: Iterable[tuple[Sequence[int], Sequence[int]]] | None = None,
) -> np.ndarray:
    """(K, 2) int array of (idx_a, idx_b) correspondences, each feature used at most once.

    ``groups``: optional candidate sets ``[(indices_a, indices_b), ...]``; a pair can only match
    inside a group. In a group with a single candidate on one side the ratio test runs from the
    other side; with one candidate on both sides only ``max_distance`` applies.
    """
    desc_a = as_descriptors(desc_a, "desc_a")
    desc_b = as_descriptors(desc_b, "desc_b")
    if groups is None:
        pairs = match_ratio(desc_a, desc_b, ratio=ratio, max_distance=max_distance, mutual=mutual)
        return pairs.reshape(-1, 2).astype(int)
    found = []
    singles = []
    for ia, ib in groups:  # loop over vocabulary nodes, not points: each call is vectorised
        ia = np.asarray(ia, dtype=int).reshape(-1)
        ib = np.asarray(ib, dtype=int).reshape(-1)
        if len(ia) == 0 or len(ib) == 0:
            continue
        if ia.min() < 0 or ia.max() >= len(desc_a) or ib.min() < 0 or ib.max() >= len(desc_b):
            raise RegistrationError("a candidate group holds a feature index out of range")
        if len(ib) >= 2:
            sub = match_ratio(desc_a[ia], desc_b[ib], ratio, max_distance, mutual)
            found.append(np.stack([ia[sub[:, 0]], ib[sub[:, 1]]], axis=1))
        elif len(ia) >= 2:
            sub = match_ratio(desc_b[ib], desc_a[ia], ratio, max_distance, mutual)
            found.append(np.stack([ia[sub[:, 1]], ib[sub[:, 0]]], axis=1))
        else:
            singles.append((ia[0], ib[0]))
    if singles:
        single = np.asarray(singles, dtype=int)
        dist = hamming_rows(desc_a[single[:, 0]], desc_b[single[:, 1]])
        found.append(single[dist <= max_distance])
    if not found:
        return np.zeros((0, 2), dtype=int)
    return _unique_pairs(np.concatenate(found).astype(int), desc_a, desc_b)
