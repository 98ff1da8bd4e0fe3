"""Fused, voxel-downsampled team point cloud for display and export.

Once maps are merged, the robots' map points are expressed in ``world`` and overlapping areas hold
each surface several times (once per robot). :func:`fuse_points` turns points known to be the same
physical point (matches) into one and merges near-duplicates from different robots, so overlapping
maps show no doubled surfaces; :func:`voxel_downsample` bounds the cloud's size. Everything is
vectorised numpy / scipy (no per-point Python loops).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import CoopSlamError
from ..geometry import transform_points

# RGB, one colour per robot (robot_id % len): distinct on white and black backgrounds.
ROBOT_PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    dtype=np.uint8,
)
_MAX_FUSION_ROUNDS = 100  # each round merges at least one pair; real clouds need a handful


class FusionError(CoopSlamError):
    """Point arrays of inconsistent shapes, non-finite points or invalid match indices."""


def robot_colours(robot_ids) -> np.ndarray:
    """(N, 3) uint8 RGB colours from a fixed palette (robot 1 gets the first colour)."""
    ids = np.asarray(robot_ids, dtype=np.int64).reshape(-1)
    return ROBOT_PALETTE[(ids - 1) % len(ROBOT_PALETTE)]


def gather_map_points(
    records, T_view_map, per_keyframe: bool = False, map_of=lambda rec: rec.robot_id
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 3), map ids (N,), point_ids (N,)) from keyframe records, each map's points
    moved into the frame shown by ``T_view_map(map id)`` (a callable or a dict); ``map_of(rec)``
    a record's map (a client's: its robot; the server's: its map id). With ``per_keyframe`` the
    callable takes the record instead, so a pose graph that bent a robot's trajectory moves each
    keyframe's points with its own keyframe. A map point seen by several keyframes of a map
    appears once, at its position in the latest of them."""
    lookup = T_view_map if callable(T_view_map) else T_view_map.__getitem__
    chunks, robots, ids, order = [], [], [], []
    for rec in records:
        pid = rec.map_point_ids[rec.map_point_ids != 0].astype(np.int64)
        T = lookup(rec) if per_keyframe else lookup(map_of(rec))
        chunks.append(transform_points(T, rec.map_points))
        robots.append(np.full(len(pid), map_of(rec), np.int64))
        ids.append(pid)
        order.append(np.full(len(pid), rec.keyframe_id, np.int64))
    if not chunks:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64)
    points, robots, ids, order = (np.concatenate(a) for a in (chunks, robots, ids, order))
    # Latest keyframe first within each (robot, point id), then keep the first of each.
    sort = np.lexsort((-order, ids, robots))
    keep = np.ones(len(sort), bool)
    keep[1:] = (np.diff(robots[sort]) != 0) | (np.diff(ids[sort]) != 0)
    sel = sort[keep]
    return points[sel], robots[sel], ids[sel]


def _group_mean(
    labels: np.ndarray, n_groups: int, points: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    total = np.bincount(labels, weights=weights, minlength=n_groups)
    return (
        np.stack(
            [
                np.bincount(labels, weights=points[:, c] * weights, minlength=n_groups)
                for c in range(3)
            ],
            axis=1,
        )
        / total[:, None]
    )


def _merge_groups(labels, n_groups, points, weights, robots, ids):
    """Collapse points sharing a label: weighted mean position; robot and id of the member with the
    smallest robot id (the point then belongs to the reference robot's map)."""
    means = _group_mean(labels, n_groups, points, weights)
    first = np.lexsort((robots, labels))  # by label, then robot id
    take = first[np.unique(labels[first], return_index=True)[1]]
    return means, np.bincount(labels, weights=weights, minlength=n_groups), robots[take], ids[take]


def _trees(points: np.ndarray, robots: np.ndarray) -> list[tuple[int, np.ndarray, cKDTree]]:
    """(robot, its point indices, KD-tree of its points) per robot."""
    out = []
    for r in np.unique(robots):
        idx = np.nonzero(robots == r)[0]
        out.append((r, idx, cKDTree(points[idx], balanced_tree=False, compact_nodes=False)))
    return out


def _take_nearer(points, query, candidates, tree, radius_m, best_d, best_j) -> None:
    """Where the nearest of ``candidates`` (the points ``tree`` holds) is closer to a point of
    ``query`` than radius_m and than its best so far, it becomes that point's best."""
    d, k = tree.query(points[query], distance_upper_bound=radius_m)
    better = (d < radius_m) & (d < best_d[query])
    best_d[query[better]] = d[better]
    best_j[query[better]] = candidates[k[better]]


def _nearest_other_robot(points, robots, trees, query, radius_m, best_d, best_j) -> None:
    """Set best_d / best_j of the points ``query`` to their nearest point of another robot
    closer than radius_m (inf / -1: none); robots in tree order, the first wins a tie."""
    best_d[query], best_j[query] = np.inf, -1
    for r, idx_r, tree in trees:
        others = query[robots[query] != r]
        if len(others):
            _take_nearer(points, others, idx_r, tree, radius_m, best_d, best_j)


def _mutual_pairs(best_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j), i < j, that are each other's best."""
    i = np.nonzero(best_j >= 0)[0]
    j = best_j[i]
    mutual = (best_j[j] == i) & (i < j)
    return i[mutual], j[mutual]


def _fuse_cross_robot(points, weights, robots, ids, radius_m: float):
    """Merge points of different robots closer than radius_m in rounds of mutual-nearest pairs.

    Each point's nearest point of another robot is kept from round to round and searched again
    only for the merged points and the points whose nearest was merged; every other point saw no
    candidate move or vanish, only the new means appear, so its nearest is the nearer of the old
    one and the nearest new mean. Later rounds, which merge few pairs, then cost little. The
    result is that of searching every point again in every round."""
    n = len(points)
    best_d, best_j = np.full(n, np.inf), np.full(n, -1)
    trees = _trees(points, robots)
    _nearest_other_robot(points, robots, trees, np.arange(n), radius_m, best_d, best_j)
    for _ in range(_MAX_FUSION_ROUNDS):
        i, j = _mutual_pairs(best_j)
        if len(i) == 0:
            break
        labels = np.arange(len(points))
        labels[j] = i
        # Relabel to 0..G-1 keeping order, then collapse each pair.
        _, labels = np.unique(labels, return_inverse=True)
        merged_old = np.zeros(len(points), bool)
        merged_old[i] = merged_old[j] = True
        stale = merged_old | ((best_j >= 0) & merged_old[np.maximum(best_j, 0)])
        points, weights, robots, ids = _merge_groups(
            labels, labels.max() + 1, points, weights, robots, ids
        )
        # the kept points' best in the new numbering (rows of stale points are recomputed)
        new_best_d, new_best_j = np.full(len(points), np.inf), np.full(len(points), -1)
        keep = ~merged_old
        keep[i] = True  # a pair's first point's row becomes the pair's mean
        new_best_d[labels[keep]] = best_d[keep]
        has = keep & (best_j >= 0)
        new_best_j[labels[has]] = labels[best_j[has]]
        best_d, best_j = new_best_d, new_best_j
        means = np.unique(labels[i])
        # Everyone else only gained candidates, the new means: the nearer of its old best and the
        # nearest mean of another robot.
        for r in np.unique(robots):
            other_means = means[robots[means] != r]
            if not len(other_means):
                continue
            tree = cKDTree(points[other_means])
            idx_r = np.nonzero(robots == r)[0]
            _take_nearer(points, idx_r, other_means, tree, radius_m, best_d, best_j)
        trees = _trees(points, robots)
        query = np.unique(np.concatenate([means, labels[stale]]))
        _nearest_other_robot(points, robots, trees, query, radius_m, best_d, best_j)
    return points, weights, robots, ids


def fuse_points(
    points_team, robot_ids, point_ids, matches=None, radius_m: float = 0.02
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse a team cloud -> (points (M, 3), point_ids (M,), robot_ids (M,)).

    ``matches`` (K, 2) are index pairs known to be one physical point: each connected set of them
    becomes one point at the mean. Then points of different robots closer than ``radius_m`` are
    merged (count-weighted mean) in rounds of mutual-nearest pairs until no such pair is left;
    mutual pairs avoid chaining a dense surface into one blob. A fused point keeps the robot id and
    point id of its member with the smallest robot id. Points of one robot are never merged with
    each other (its SLAM already keeps them distinct).
    """
    points = np.asarray(points_team, dtype=float).reshape(-1, 3)
    robots = np.asarray(robot_ids).reshape(-1)
    ids = np.asarray(point_ids).reshape(-1)
    n = len(points)
    if len(robots) != n or len(ids) != n:
        raise FusionError(
            f"points ({n}), robot_ids ({len(robots)}) and point_ids ({len(ids)}) "
            "must have one entry per point"
        )
    if not np.all(np.isfinite(points)):
        raise FusionError("points contain NaN or inf")
    if not radius_m >= 0:
        raise FusionError(f"fusion radius must be >= 0, got {radius_m}")
    weights = np.ones(n)
    if matches is not None and len(matches):
        m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
        if m.min() < 0 or m.max() >= n:
            raise FusionError(f"match indices must be in [0, {n}), got [{m.min()}, {m.max()}]")
        adj = coo_matrix((np.ones(len(m)), (m[:, 0], m[:, 1])), shape=(n, n))
        n_groups, labels = connected_components(adj, directed=False)
        points, weights, robots, ids = _merge_groups(labels, n_groups, points, weights, robots, ids)
    if radius_m > 0 and len(points):
        points, weights, robots, ids = _fuse_cross_robot(points, weights, robots, ids, radius_m)
    return points, ids, robots


def voxel_downsample(points, labels=None, voxel_m: float = 0.05):
    """One point per occupied voxel -> (points (V, 3), labels).

    Points are averaged per voxel. ``labels`` may be (N, C) values such as RGB colours (averaged,
    rounded back to their integer dtype) or (N,) integer labels such as robot ids (most frequent
    label of the voxel, ties to the smallest); None gives None.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if not voxel_m > 0:
        raise FusionError(f"voxel size must be > 0, got {voxel_m}")
    if not np.all(np.isfinite(points)):
        raise FusionError("points contain NaN or inf")
    if labels is not None:
        labels = np.asarray(labels)
        if len(labels) != len(points):
            raise FusionError(f"{len(labels)} labels for {len(points)} points")
    if len(points) == 0:
        return points, (None if labels is None else labels[:0])
    cells = np.floor(points / voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if np.prod(dims.astype(float)) < 2**62:
        flat = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]  # one sortable key
        _, voxel = np.unique(flat, return_inverse=True)
    else:
        _, voxel = np.unique(cells, axis=0, return_inverse=True)
    voxel = voxel.reshape(-1)
    n_vox = int(voxel.max()) + 1
    out = _group_mean(voxel, n_vox, points, np.ones(len(points)))
    if labels is None:
        return out, None
    if labels.ndim == 1:
        # Mode per voxel: count (voxel, label) pairs, keep the largest count of each voxel.
        pairs, counts = np.unique(
            np.stack([voxel, labels.astype(np.int64)], axis=1), axis=0, return_counts=True
        )
        order = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))
        first = order[np.unique(pairs[order, 0], return_index=True)[1]]
        return out, pairs[first, 1].astype(labels.dtype)
    cols = labels.reshape(len(labels), -1).astype(float)
    counts = np.bincount(voxel, minlength=n_vox)
    mean = (
        np.stack(
            [np.bincount(voxel, weights=cols[:, c], minlength=n_vox) for c in range(cols.shape[1])],
            axis=1,
        )
        / counts[:, None]
    )
    if np.issubdtype(labels.dtype, np.integer):
        mean = np.rint(mean)
    return out, mean.astype(labels.dtype).reshape((n_vox,) + labels.shape[1:])
