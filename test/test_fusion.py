"""Team cloud fusion: matched points, cross-robot near-duplicates, voxel downsampling, colours."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from coop_slam.geometry import se3
from coop_slam.team.fusion import (
    ROBOT_PALETTE,
    FusionError,
    fuse_points,
    gather_map_points,
    robot_colours,
    voxel_downsample,
)
from helpers import make_keyframe

RADIUS = 0.02


def overlapping_maps(seed=0, n=3000):
    """Two robots seeing one wall (points 5 cm apart, each robot with 3 mm noise), plus points
    only robot 2 sees."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(np.arange(0, 2.5, 0.05), np.arange(0, 1.5, 0.05)), -1).reshape(
        -1, 2
    )
    wall = np.column_stack([grid, np.zeros(len(grid))])
    p1 = wall + rng.normal(0, 0.003, wall.shape)
    p2 = np.vstack([wall + rng.normal(0, 0.003, wall.shape), rng.uniform(3, 4, (200, 3))])
    points = np.vstack([p1, p2])
    robots = np.r_[np.full(len(p1), 1), np.full(len(p2), 2)]
    ids = np.r_[np.arange(len(p1)) + 1, np.arange(len(p2)) + 1]
    return points, robots, ids, len(wall)


def cross_robot_pairs(points, robots, radius):
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    return pairs[robots[pairs[:, 0]] != robots[pairs[:, 1]]]


def test_overlapping_maps_show_no_doubled_surface():
    points, robots, ids, n_wall = overlapping_maps()
    assert len(cross_robot_pairs(points, robots, RADIUS)) >= n_wall  # doubled wall before fusion
    fused, _, fused_robots = fuse_points(points, robots, ids, radius_m=RADIUS)
    assert len(cross_robot_pairs(fused, fused_robots, RADIUS)) == 0
    # Every wall point pair became one point; robot 2's own points stay.
    assert len(fused) == n_wall + 200
    assert np.count_nonzero(fused_robots == 1) == n_wall
    # Fused wall points sit between the two observations (close to the true grid).
    wall = fused[fused_robots == 1]
    assert np.abs(wall[:, 2]).max() < 0.01


def test_matched_points_become_one():
    points = np.array([[0, 0, 0], [0.5, 0, 0], [0.52, 0, 0], [1, 1, 1], [3, 0, 0.0]])
    robots = np.array([1, 2, 3, 2, 1])
    ids = np.array([10, 20, 30, 40, 50])
    # 0-1 and 1-2 are one physical point (far apart here: matches override the radius).
    fused, fused_ids, fused_robots = fuse_points(
        points, robots, ids, matches=[[0, 1], [1, 2]], radius_m=0.0
    )
    assert len(fused) == 3
    k = np.nonzero(fused_ids == 10)[0][0]
    np.testing.assert_allclose(fused[k], [1.02 / 3, 0, 0])
    assert fused_robots[k] == 1
    assert sorted(fused_ids.tolist()) == [10, 40, 50]


def test_same_robot_points_are_not_merged():
    points = np.array([[0, 0, 0], [0.005, 0, 0], [0.01, 0, 0]])
    fused, _, _ = fuse_points(points, [1, 1, 1], [1, 2, 3], radius_m=RADIUS)
    assert len(fused) == 3


def test_dense_overlap_does_not_collapse_into_a_blob():
    # 1 cm spacing (below the radius): chained merging would collapse the line into one point.
    x = np.arange(0, 1, 0.01)
    line = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    points = np.vstack([line, line + [0.003, 0, 0]])
    robots = np.r_[np.ones(len(x), int), np.full(len(x), 2)]
    fused, _, fused_robots = fuse_points(points, robots, np.arange(len(points)), radius_m=RADIUS)
    assert len(cross_robot_pairs(fused, fused_robots, RADIUS)) == 0
    assert len(fused) >= len(x) * 0.9


def test_empty_input_and_bad_input():
    fused, ids, robots = fuse_points(np.zeros((0, 3)), [], [], matches=np.zeros((0, 2), int))
    assert fused.shape == (0, 3) and len(ids) == 0 and len(robots) == 0
    pts, lab = voxel_downsample(np.zeros((0, 3)), np.zeros(0, int), 0.1)
    assert pts.shape == (0, 3) and len(lab) == 0
    assert robot_colours([]).shape == (0, 3)
    with pytest.raises(FusionError):
        fuse_points(np.zeros((3, 3)), [1, 2], [1, 2, 3])
    with pytest.raises(FusionError):
        fuse_points(np.zeros((2, 3)), [1, 2], [1, 2], matches=[[0, 5]])
    with pytest.raises(FusionError):
        fuse_points(np.full((1, 3), np.nan), [1], [1])
    with pytest.raises(FusionError):
        voxel_downsample(np.zeros((2, 3)), None, 0.0)


def test_voxel_downsample_bounds_and_labels():
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 1, (20000, 3))
    colours = rng.integers(0, 256, (20000, 3)).astype(np.uint8)
    voxel = 0.1
    out, out_colours = voxel_downsample(points, colours, voxel)
    assert len(out) <= 10**3 and len(out) == len(np.unique(np.floor(points / voxel), axis=0))
    assert out_colours.dtype == np.uint8 and out_colours.shape == (len(out), 3)
    # Each mean lies in a voxel that was occupied.
    occupied = {tuple(c) for c in np.floor(points / voxel).astype(int)}
    assert all(tuple(c) in occupied for c in np.floor(out / voxel).astype(int))
    # Integer labels: most frequent label per voxel.
    pts = np.array([[0.01, 0, 0], [0.02, 0, 0], [0.03, 0, 0], [0.5, 0, 0]])
    out, lab = voxel_downsample(pts, np.array([2, 1, 2, 3]), 0.1)
    assert lab.tolist() == [2, 3]
    np.testing.assert_allclose(out[0], [0.02, 0, 0])
    assert voxel_downsample(pts, None, 0.1)[1] is None


def test_robot_colours_are_fixed_per_robot():
    colours = robot_colours([1, 2, 1, 11])
    assert colours.dtype == np.uint8 and colours.shape == (4, 3)
    assert (colours[0] == colours[2]).all() and (colours[0] == colours[3]).all()
    assert (colours[0] != colours[1]).any()
    assert len({tuple(c) for c in ROBOT_PALETTE}) == len(ROBOT_PALETTE)


def test_gather_map_points_from_keyframes():
    a1 = make_keyframe(n=10, robot_id=1, keyframe_id=1, seed=0)
    a2 = make_keyframe(n=10, robot_id=1, keyframe_id=2, seed=1)  # same point ids, moved by BA
    b1 = make_keyframe(n=10, robot_id=2, keyframe_id=1, seed=2)
    T_world_map = {1: np.eye(4), 2: se3(t=[10, 0, 0])}
    points, robots, ids = gather_map_points([a2, b1, a1], T_world_map)
    assert len(points) == 10 and sorted(robots.tolist()) == [1] * 5 + [2] * 5
    k = np.nonzero((robots == 1) & (ids == 1))[0][0]
    np.testing.assert_allclose(points[k], a2.map_points[0], rtol=1e-6)  # latest keyframe wins
    np.testing.assert_allclose(points[robots == 2], b1.map_points + [10, 0, 0], rtol=1e-6)
    assert gather_map_points([], T_world_map)[0].shape == (0, 3)


def _fuse_from_scratch(points, robots, ids, radius):
    """Reference: every round searches every point's nearest point of another robot anew."""
    weights = np.ones(len(points))
    while True:
        best_d, best_j = np.full(len(points), np.inf), np.full(len(points), -1)
        for r in np.unique(robots):
            own = robots == r
            idx_r, others = np.nonzero(own)[0], np.nonzero(~own)[0]
            d, k = cKDTree(points[own]).query(points[others], distance_upper_bound=radius)
            better = (d < radius) & (d < best_d[others])
            best_d[others[better]], best_j[others[better]] = d[better], idx_r[k[better]]
        i = np.nonzero(best_j >= 0)[0]
        mutual = (best_j[best_j[i]] == i) & (i < best_j[i])
        i, j = i[mutual], best_j[i][mutual]
        if not len(i):
            return points, ids, robots
        labels = np.arange(len(points))
        labels[j] = i
        _, labels = np.unique(labels, return_inverse=True)
        total = np.bincount(labels, weights=weights)
        points = (
            np.stack([np.bincount(labels, weights=points[:, c] * weights) for c in range(3)], 1)
            / total[:, None]
        )
        first = np.lexsort((robots, labels))
        take = first[np.unique(labels[first], return_index=True)[1]]
        weights, robots, ids = total, robots[take], ids[take]


def test_fusion_rounds_equal_searching_everything_each_round():
    """Four robots' noisy copies of one dense surface take many rounds of mutual pairs: keeping
    each point's nearest between rounds gives exactly the from-scratch result."""
    rng = np.random.default_rng(5)
    surface = rng.uniform(0, 0.5, (1500, 3)) * [1, 1, 0.02]
    points = np.vstack([surface + rng.normal(0, 0.006, surface.shape) for _ in range(4)])
    robots = np.repeat(np.arange(1, 5), len(surface))
    ids = np.tile(np.arange(1, len(surface) + 1), 4)
    ref_points, ref_ids, ref_robots = _fuse_from_scratch(points, robots, ids, RADIUS)
    fused, fused_ids, fused_robots = fuse_points(points, robots, ids, radius_m=RADIUS)
    assert len(ref_points) < 0.6 * len(points)  # a case where fusion does much
    np.testing.assert_allclose(fused, ref_points, atol=1e-12)
    np.testing.assert_array_equal(fused_ids, ref_ids)
    np.testing.assert_array_equal(fused_robots, ref_robots)
