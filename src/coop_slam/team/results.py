"""What the server's stitching produces: verified matches, merges between groups and constraints
inside a group. Plain data, shared by the stages that make and consume them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ids import KeyframeKey, MapId
from ..registration.relative_pose import RelativePoseResult

TYPE_LOOP = "loop"  # a robot's own loop closure (a loop factor in the pose graph)

TYPE_PLACE_RECOGNITION = "place_recognition"
TYPE_RENDEZVOUS = "rendezvous"
# a pair of merged robots' keyframes the team map predicts to overlap (see .overlap_links)
TYPE_OVERLAP = "overlap"
# a constraint between two robots already in one group, as a merge event (whatever found it)
TYPE_LINK = "link"


@dataclass
class Verified:
    """A geometrically verified match of two keyframes (``result.T_a_b``: b's camera in a's),
    not yet a merge or a constraint. ``kind`` is what found it (a TYPE_*)."""

    kind: str
    key_a: KeyframeKey
    key_b: KeyframeKey
    result: RelativePoseResult
    stamp_s: float  # when the match became possible (the later keyframe or cue)


@dataclass
class MergeResult:
    type: str
    map_a: MapId  # reference map (its group's frame is kept)
    map_b: MapId
    keyframe_a: int
    keyframe_b: int
    stamp_s: float  # stamp of the keyframe that triggered the merge
    # Robot b's map in robot a's, and the matched keyframes' relative pose: first from the
    # verified registration, then as the merge's optimization placed them (welding window).
    T_mapA_mapB: np.ndarray
    T_camA_camB: np.ndarray
    inliers: int
    residual_px: float
    group: list[int]
    welded: int = 0  # further verified keyframe pairs the merge rests on (welding window)
    # The verified similarity's scale, b's lengths into a's (1: a rigid merge); the side without
    # metric scale was rescaled by it (see .map_scale), so the transforms above are rigid.
    scale: float = 1.0


@dataclass
class ConstraintResult:
    """A verified constraint inside one group: a loop closure (same robot) or a further link
    between two merged robots."""

    type: str
    key_a: KeyframeKey
    key_b: KeyframeKey
    stamp_s: float
    T_camA_camB: np.ndarray
    inliers: int
    residual_px: float


def map_pair(a: MapId, b: MapId) -> tuple[MapId, MapId]:
    """A robot pair as the key of pair tables (match counts, pending merges, cues)."""
    return (min(a, b), max(a, b))
