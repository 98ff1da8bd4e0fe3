"""Pairing two streams by timestamp: colour with depth images, estimates with ground truth, frames
with poses. The one nearest-stamp association every reader and metric uses."""

from __future__ import annotations

import numpy as np


def associate(
    stamps_query, stamps_ref, max_dt_s: float, one_to_one: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i_query, i_ref): each query stamp with its nearest reference stamp, kept when
    they are at most ``max_dt_s`` apart (a tie goes to the earlier reference). With
    ``one_to_one`` a reference stamp pairs with its first query only (in query order), as TUM's
    colour/depth association does. ``stamps_ref`` need not be sorted."""
    stamps_query = np.asarray(stamps_query, float).reshape(-1)
    stamps_ref = np.asarray(stamps_ref, float).reshape(-1)
    if len(stamps_query) == 0 or len(stamps_ref) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    order = np.argsort(stamps_ref, kind="stable")
    sr = stamps_ref[order]
    if len(sr) == 1:
        idx = np.zeros(len(stamps_query), int)
    else:
        idx = np.clip(np.searchsorted(sr, stamps_query), 1, len(sr) - 1)
        left = idx - 1
        idx = np.where(np.abs(sr[left] - stamps_query) <= np.abs(sr[idx] - stamps_query), left, idx)
    ok = np.abs(sr[idx] - stamps_query) <= max_dt_s
    i_query, i_ref = np.nonzero(ok)[0], order[idx[ok]]
    if one_to_one and len(i_ref):
        _, first = np.unique(i_ref, return_index=True)
        keep = np.sort(first)
        i_query, i_ref = i_query[keep], i_ref[keep]
    return i_query, i_ref
