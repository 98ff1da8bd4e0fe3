"""Links where merged maps overlap (team.overlap_links): a merge welded on the pairs around its
matched keyframes, links between merged robots after it, and the gate for weakly supported
constraints; on the synthetic feature world of the server tests, with known truth."""

import dataclasses

import numpy as np
import pytest

from coop_slam.geometry import invert, se3, transform_error
from coop_slam.registration.relative_pose import estimate_pnp
from coop_slam.team.config import ServerConfig
from coop_slam.team.overlap_links import shared_view
from coop_slam.team.results import TYPE_OVERLAP, TYPE_PLACE_RECOGNITION, Verified
from coop_slam.team.server import TeamServer
from helpers import TEAM_T_WORLD_MAP, camera, team_keyframes, team_world


@pytest.fixture(scope="module")
def world():
    return team_world()


def _config(**links) -> ServerConfig:
    cfg = ServerConfig(robots=[1, 2])
    cfg.global_ba.after_merge = False  # the pose graph alone is under test
    cfg.links = dataclasses.replace(cfg.links, **links)
    return cfg


def _rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return se3(np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), [0, 0, 0])


def test_shared_view_counts_what_the_other_camera_sees():
    cam = camera()
    rng = np.random.default_rng(0)
    points = np.column_stack(
        [rng.uniform(-1, 1, 500), rng.uniform(-0.7, 0.7, 500), rng.uniform(2.5, 3, 500)]
    )
    K, size = cam.K, (cam.width, cam.height)
    assert shared_view(points, np.eye(4), K, size, 3.0) > 0.95
    half = se3(np.eye(3), [1.7, 0, 0])  # b seen from 1.7 m to its left: about half its view
    assert 0.3 < shared_view(points, half, K, size, 3.0) < 0.7
    turned = se3(np.array([[0, 0, 1.0], [0, 1, 0], [-1, 0, 0]]), [0, 0, 0])  # 90 deg apart
    assert shared_view(points, turned, K, size, 3.0) == 0.0
    assert shared_view(points, np.eye(4), K, size, 2.0) == 0.0  # all beyond a's range
    assert shared_view(points[:0], np.eye(4), K, size, 3.0) == 0.0


def _two_robots(world, links_enabled=True, **links):
    """Robot 2 looks where robot 1 looked, from 20 cm aside; nothing merges on its own."""
    points, desc, kfs_a, vocab = world
    cfg = _config(enabled=links_enabled, **links)
    cfg.place_recognition.enabled = False
    cfg.rendezvous.auto = False
    server = TeamServer(cfg, vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    for kf in team_keyframes(
        2, np.linspace(2.0, 3.0, 8), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
    ):
        server.add_keyframe(kf)
    return server


def _merge_off_by(server, deg: float):
    """Merge robots 1 and 2 on keyframes (1, 16) and (2, 5) with the verified pose turned by
    ``deg``; returns the map transform's error (m, deg) after the merge's optimization."""
    key_a, key_b = (1, 16), (2, 5)
    res = estimate_pnp(server.store.view(key_a), server.store.view(key_b))
    assert res.accepted
    res.T_a_b = res.T_a_b @ _rot_x(deg)
    server.stitcher.merge(Verified(TYPE_PLACE_RECOGNITION, key_a, key_b, res, 110.0))
    server.optimize(full=True)
    truth = invert(TEAM_T_WORLD_MAP[1]) @ TEAM_T_WORLD_MAP[2]
    return transform_error(invert(server.T_group_map(1)) @ server.T_group_map(2), truth)


def test_a_merge_welded_on_its_neighbourhood_outweighs_one_bad_pair(world):
    welded = _two_robots(world)
    dt, dr = _merge_off_by(welded, 2.0)
    assert welded.merges[0].welded >= 3
    alone = _two_robots(world, weld_window=0, sweep_pairs=0)
    dt0, dr0 = _merge_off_by(alone, 2.0)
    assert alone.merges[0].welded == 0
    assert dr0 > 1.0  # the one pair sets the transform
    assert dr < 0.5 and dt < 0.03


def test_welded_pairs_are_what_the_truth_says(world):
    server = _two_robots(world)
    _merge_off_by(server, 0.0)
    key_a, key_b = (1, 16), (2, 5)
    pairs = server.links.weld(key_a, key_b, {1}, {2}, 110.0)
    assert pairs and all(v.kind == TYPE_OVERLAP for v in pairs)
    for v in pairs:
        T_world_a = TEAM_T_WORLD_MAP[1] @ server.store.record(v.key_a).T_map_cam
        T_world_b = TEAM_T_WORLD_MAP[2] @ server.store.record(v.key_b).T_map_cam
        dt, dr = transform_error(v.result.T_a_b, invert(T_world_a) @ T_world_b)
        assert v.key_a[0] == 1 and v.key_b[0] == 2 and dt < 0.01 and dr < 0.2


def test_merged_robots_keep_linking_where_their_maps_overlap(world):
    """After the merge, robot 2's new keyframes look where robot 1 looked from other places: they
    link to robot 1's keyframes by the predicted overlap, each link true to within 1 cm."""
    points, desc, _, _ = world

    def run(enabled):
        server = _two_robots(world, links_enabled=enabled)
        _merge_off_by(server, 0.0)
        later = team_keyframes(
            2,
            np.linspace(3.2, 4.5, 8),
            points,
            desc,
            kid0=20,
            offset=(-0.3, 0.2),
            seed=200,
            t0=120.0,
        )
        for kf in later:
            server.add_keyframe(kf)
        return server

    server = run(True)
    links = [c for c in server.constraints if c.type == TYPE_OVERLAP]
    assert len(links) >= 3
    for c in links:
        T_world_a = TEAM_T_WORLD_MAP[c.key_a[0]] @ server.store.record(c.key_a).T_map_cam
        T_world_b = TEAM_T_WORLD_MAP[c.key_b[0]] @ server.store.record(c.key_b).T_map_cam
        dt, dr = transform_error(c.T_camA_camB, invert(T_world_a) @ T_world_b)
        assert c.key_a[0] != c.key_b[0] and dt < 0.01 and dr < 0.2
    assert not [c for c in run(False).constraints if c.type == TYPE_OVERLAP]


def test_weak_constraints_only_refine_the_estimate(world):
    """A verified constraint with fewer than loops.min_inliers is taken where it agrees with the
    estimate (weak gate), refused where it would move the map by more."""
    server = _two_robots(world)
    _merge_off_by(server, 0.0)
    key_a, key_b = (1, 17), (2, 6)
    res = estimate_pnp(server.store.view(key_a), server.store.view(key_b))
    server.config.loops.min_inliers = res.n_inliers + 1
    server.config.loops.min_interval_kf = 0
    assert server.stitcher.add_constraint(Verified(TYPE_PLACE_RECOGNITION, key_a, key_b, res, 0))
    off = dataclasses.replace(res, T_a_b=res.T_a_b @ _rot_x(5.0))  # within the strong gate only
    assert not server.stitcher.add_constraint(
        Verified(TYPE_PLACE_RECOGNITION, key_a, key_b, off, 0)
    )
    server.config.loops.min_inliers = res.n_inliers
    assert server.stitcher.add_constraint(Verified(TYPE_PLACE_RECOGNITION, key_a, key_b, off, 0))


def test_link_candidates_need_a_shared_view(world):
    """Keyframes looking the other way are never proposed."""
    server = _two_robots(world)
    _merge_off_by(server, 0.0)
    # Robot 1's keyframe k looks along (k - 1) * 10 deg, robot 2's keyframe 5 along 147 deg.
    opposite = [(1, k) for k in range(1, 37) if abs((k - 1) * 10 - 327) < 20]
    assert len(opposite) == 4
    assert server.links.best_partners((2, 5), opposite) == []
    best = server.links.best_partners((2, 5), [(1, k) for k in range(1, 37)], n=3)
    assert best and all(abs((k - 1) * 10 - 147) <= 40 for _, k in best)


def test_markers_shrink_with_the_map():
    from coop_slam.team.view import MIN_MARKER_SCALE, marker_scale

    world = {1: np.array([[0, 0, 0], [12.0, 3, 0]]), 2: np.array([[1, 1, 0.0]])}
    kitchen = {1: np.array([[0, 0, 0], [2.5, 1, 0]])}
    assert marker_scale(world) == 1.0
    assert marker_scale(kitchen) == pytest.approx(0.25)
    assert marker_scale({1: np.array([[0, 0, 0.0]])}) == MIN_MARKER_SCALE
    assert marker_scale({}) == 1.0


def test_a_late_merge_links_across_the_overlap(world):
    """A merge after the last keyframes still links the two maps beyond its welding window."""
    server = _two_robots(world)
    _merge_off_by(server, 0.0)
    links = [c for c in server.constraints if c.type == TYPE_OVERLAP]
    assert len(links) >= 3 and all(c.key_a[0] == 1 and c.key_b[0] == 2 for c in links)
    unswept = _two_robots(world, sweep_pairs=0)
    _merge_off_by(unswept, 0.0)
    assert unswept.constraints == []
