"""What the team map looks like on screen: the stitched cloud, the optimized keyframe paths and the
merge / constraint edges, in the frame RViz shows (``world``).

Merged groups are drawn in their group frame; groups not merged with the world group (the one
holding the team's smallest robot id) are shifted along x, so unmerged maps do not overlap.
Pure functions: the server hands in the keyframes and how to place them.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..geometry import invert
from ..ids import KeyframeKey
from ..wire.record import KeyframeRecord
from .fusion import fuse_points, gather_map_points, robot_colours, voxel_downsample
from .groups import MergeGroups
from .results import ConstraintResult, MergeResult

PoseOf = Callable[[int, int], np.ndarray]  # (robot, keyframe) -> T_group_cam


def view_offsets(groups: MergeGroups, world_root: int, offset_m: float) -> dict[int, np.ndarray]:
    """robot -> ``T_view_group``: the shift of its group on screen (identity for the world
    group, ``offset_m`` along x per further group, in order of their root robot)."""
    roots = sorted({groups.root(r) for r in groups.robots} - {world_root})
    order = [world_root] + roots
    offsets = {}
    for robot in groups.robots:
        offsets[robot] = np.eye(4)
        offsets[robot][0, 3] = order.index(groups.root(robot)) * offset_m
    return offsets


def team_paths_and_edges(
    keys: list[KeyframeKey],
    offsets: dict[int, np.ndarray],
    T_group_cam: PoseOf,
    merges: list[MergeResult],
    constraints: list[ConstraintResult],
) -> tuple[dict[int, np.ndarray], list[tuple[str, np.ndarray, np.ndarray]]]:
    """Keyframe positions per robot (K, 3), by keyframe id, and the merge / constraint edges
    (type, position a, position b) between stored keyframes, in the view frame."""

    def position(key):
        return (offsets[key[0]] @ T_group_cam(*key))[:3, 3]

    stored = set(keys)
    paths = {}
    for robot in sorted({r for r, _ in keys}):
        ids = sorted(k for r, k in keys if r == robot)
        paths[robot] = np.array([position((robot, k)) for k in ids])
    links = [(m.type, (m.map_a, m.keyframe_a), (m.map_b, m.keyframe_b)) for m in merges]
    links += [(c.type, c.key_a, c.key_b) for c in constraints]
    edges = [
        (kind, position(ka), position(kb))
        for kind, ka, kb in links
        if ka in stored and kb in stored
    ]
    return paths, edges


CloudSnapshot = list[tuple[KeyframeRecord, np.ndarray]]  # (keyframe, T_view_map of its points)


def cloud_snapshot(
    records: list[KeyframeRecord],
    offsets: dict[int, np.ndarray],
    T_group_cam: PoseOf,
    local_scale: Callable[[int, int], float] | None = None,
) -> CloudSnapshot:
    """What the stitched cloud is built from, fixed now: each keyframe with the transform that
    moves its map points to where the team map has them on screen -- its optimized pose (and,
    for a monocular map whose scale the team graph lets drift, its ``local_scale`` about the
    camera) in its group's place. The records are not copied: the server replaces a record on
    every change, never alters one, so the snapshot can be built while the server goes on."""
    out = []
    for rec in records:
        T = T_group_cam(rec.map_id, rec.keyframe_id)
        s = 1.0 if local_scale is None else local_scale(rec.map_id, rec.keyframe_id)
        if s != 1.0:
            T = T @ np.diag([s, s, s, 1.0])
        out.append((rec, offsets[rec.map_id] @ T @ invert(rec.T_map_cam)))
    return out


def build_cloud(
    snapshot: CloudSnapshot, fuse_radius_m: float, voxel_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stitched cloud of a snapshot: points (N, 3) in the view frame, rgb (N, 3) uint8 per robot,
    robot ids (N,). Each keyframe's points move with its own transform, duplicates of
    overlapping maps are fused, the result voxel-downsampled."""
    if not snapshot:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64)
    T_of = {id(rec): T for rec, T in snapshot}
    points, robots, ids = gather_map_points(
        [rec for rec, _ in snapshot],
        lambda rec: T_of[id(rec)],
        per_keyframe=True,
        map_of=lambda rec: rec.map_id,
    )
    points, ids, robots = fuse_points(points, robots, ids, radius_m=fuse_radius_m)
    points, robots = voxel_downsample(points, robots, voxel_m)
    return points, robot_colours(robots), robots


# Labels, paths and edges are sized for a map this wide [m] (the synthetic worlds); a smaller map
# (a 3 m kitchen) draws them proportionally smaller, down to MIN_MARKER_SCALE, so that they do not
# cover what they label.
MARKER_REFERENCE_SPAN_M = 10.0
MIN_MARKER_SCALE = 0.25


def marker_scale(paths: dict[int, np.ndarray]) -> float:
    """Size factor of the team view's markers: the horizontal span of the keyframe paths
    (robot -> (K, 3) positions as drawn) against MARKER_REFERENCE_SPAN_M, within
    [MIN_MARKER_SCALE, 1]."""
    pos = [p for p in paths.values() if len(p)]
    if not pos:
        return 1.0
    allpos = np.concatenate(pos)
    span = float(np.max(np.ptp(allpos[:, :2], axis=0)))
    return float(np.clip(span / MARKER_REFERENCE_SPAN_M, MIN_MARKER_SCALE, 1.0))
