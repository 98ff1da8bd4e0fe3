"""Global bundle adjustment of a merged group: perturbed keyframe poses of two robots, tied by
linked map points, are pulled back to the truth; bad groups are refused. The helpers' depth is near
exact, so most tests give the depth factor that sensor's small disparity noise; one checks that the
default (noise estimated from the data) finds it small too."""

import numpy as np
import pytest

from coop_slam.geometry import invert, se3, se3_from_quat, transform_error
from coop_slam.team.global_ba import GlobalBaConfig, GlobalBaError, global_bundle_adjustment
from coop_slam.team.keyframe_store import stored_keyframe
from coop_slam.team.pose_graph import TeamPoseGraph
from helpers import camera, cylinder_world, looking_out_pose, observe

EXACT_DEPTH = GlobalBaConfig(iterations=20, disparity_sigma_px=0.05)
T_WORLD_MAP = {1: np.eye(4), 2: se3_from_quat([-1.0, 0.5, 0.1], [0, 0, -0.4, 1.0])}


def _team():
    points, desc = cylinder_world(seed=3)
    records, truth = [], {}
    for robot, yaws, centre in (
        (1, np.linspace(0, 3.0, 12), (0.0, 0.0)),
        (2, np.linspace(1.5, 4.5, 12), (0.3, -0.2)),
    ):
        for k, yaw in enumerate(yaws):
            T_world_cam = looking_out_pose(yaw, center=centre)
            rec = observe(
                points, desc, T_world_cam, T_WORLD_MAP[robot], robot, k + 1, seed=k + 10 * robot
            )
            records.append(stored_keyframe(rec, robot))  # (as the server holds it: map = robot)
            truth[(robot, k + 1)] = T_world_cam
    # observe() numbers map points by world point: the same id in both robots is one point.
    ids = set(records[0].map_point_ids.tolist())
    for r in records[1:12]:
        ids |= set(r.map_point_ids.tolist())
    links = [((1, int(i)), (2, int(i))) for i in sorted(ids - {0})]
    return records, truth, links


def _perturbed(truth, fixed, seed=0):
    rng = np.random.default_rng(seed)
    out = {}
    for key, T in truth.items():
        if key == fixed:
            out[key] = T.copy()
            continue
        w = rng.normal(0, 0.01, 3)
        c, s = np.cos(w[2]), np.sin(w[2])
        out[key] = T @ se3(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), rng.normal(0, 0.05, 3))
    return out


def test_global_ba_pulls_perturbed_team_back_to_truth():
    records, truth, links = _team()
    fixed = (1, 1)
    start = _perturbed(truth, fixed)
    res = global_bundle_adjustment(records, start, links, {fixed}, EXACT_DEPTH)
    before = [transform_error(start[k], truth[k])[0] for k in truth]
    after = [transform_error(res.poses[k], truth[k])[0] for k in truth]
    assert np.mean(before) > 0.04 and np.mean(after) < 0.01
    assert np.allclose(res.poses[fixed], truth[fixed], atol=1e-6)
    assert res.rms_after < res.rms_before and res.keyframes == 24
    # Robot 2 is tied to robot 1 by the linked points alone (no pose-graph constraint here).
    assert max(transform_error(res.poses[k], truth[k])[0] for k in truth if k[0] == 2) < 0.02


def test_global_ba_result_survives_the_next_pose_graph_optimization():
    records, truth, links = _team()
    graph = TeamPoseGraph()
    start = _perturbed(truth, (1, 1), seed=1)
    for rec in records:  # client poses = the perturbed ones, as a drifting client would send them
        graph.add_keyframe(rec.robot_id, rec.keyframe_id, start[(rec.robot_id, rec.keyframe_id)])
    graph.add_merge(1, 6, 2, 1, invert(truth[(1, 6)]) @ truth[(2, 1)])
    graph.optimize_full()
    res = global_bundle_adjustment(
        records, {k: graph.T_group_cam(*k) for k in truth}, links, {(1, 1)}, EXACT_DEPTH
    )
    graph.adopt_estimates(res.poses)
    graph.optimize_full()
    after = [transform_error(graph.T_group_cam(*k), truth[k])[0] for k in truth]
    assert np.mean(after) < 0.015


def test_global_ba_estimates_the_depth_noise_from_the_data():
    records, truth, links = _team()
    start = _perturbed(truth, (1, 1), seed=3)
    res = global_bundle_adjustment(records, start, links, {(1, 1)}, GlobalBaConfig(iterations=20))
    before = np.mean([transform_error(start[k], truth[k])[0] for k in truth])
    after = np.mean([transform_error(res.poses[k], truth[k])[0] for k in truth])
    assert 0.03 <= res.disparity_sigma_px < 0.5  # much better than the weak first pass (1 px)
    assert after < 0.3 * before


def test_global_ba_refuses_bad_groups():
    records, truth, links = _team()
    with pytest.raises(GlobalBaError, match="no keyframes"):
        global_bundle_adjustment([], {}, [])
    other = camera(f=600.0)
    records[3].camera = other
    with pytest.raises(GlobalBaError, match="one camera model"):
        global_bundle_adjustment(records, truth, links)


def test_planar_global_ba_holds_ground_robots_at_their_height_and_tilt():
    """Ground robots (global_ba.planar_motion): the robots' planes are the group's xy plane at
    their camera height, the cameras' floor normal -y; with weak depth, keyframes thrown off in
    height (5 cm) come back closer to it than without the prior."""
    from coop_slam.team.global_ba import _planes

    records, truth, links = _team()
    keys = [(r.robot_id, r.keyframe_id) for r in records]
    up_cam, T_group_plane = _planes(records, truth, keys)
    assert np.allclose(up_cam, [0.0, -1.0, 0.0], atol=1e-9)
    for T_plane in T_group_plane:
        assert np.allclose(T_plane[:3, 2], [0.0, 0.0, 1.0], atol=1e-9)  # the floor normal
        assert abs(T_plane[2, 3] - 1.2) < 1e-6  # the cameras' height in the group frame
    start = _perturbed(truth, (1, 1), seed=4)
    height_err = {}
    for planar in (False, True):
        config = GlobalBaConfig(iterations=20, disparity_sigma_px=0.5, planar_motion=planar)
        res = global_bundle_adjustment(records, start, links, {(1, 1)}, config)
        height_err[planar] = np.mean([abs(res.poses[k][2, 3] - truth[k][2, 3]) for k in truth])
    assert height_err[True] < height_err[False] and height_err[True] < 0.008


def test_keyframes_sharing_no_point_keep_their_pose_graph_placement():
    """Robot 2's keyframes share no point with robot 1's (no links): the images cannot place
    them against robot 1, so their component is held at its first keyframe where the pose graph
    put it (here 20 deg and 1 m off robot 1's truth), and refined within itself."""
    records, truth, _ = _team()
    off = se3_from_quat([1.0, 0.0, 0.0], [0, 0, np.sin(np.radians(10)), np.cos(np.radians(10))])
    placed = {k: (off @ T if k[0] == 2 else T) for k, T in truth.items()}
    start = _perturbed(placed, (1, 1), seed=5)
    start[(2, 1)] = placed[(2, 1)]
    res = global_bundle_adjustment(records, start, [], {(1, 1)}, EXACT_DEPTH)
    assert {k: c for k, c in res.components.items()} == {k: k[0] - 1 for k in truth}
    assert np.allclose(res.poses[(2, 1)], placed[(2, 1)], atol=1e-6)
    for k in truth:
        assert transform_error(res.poses[k], placed[k])[0] < 0.02, k


def test_poses_refined_apart_are_not_tied_to_each_other():
    """Two keyframes refined in different components of a global BA: the odometry factor between
    them keeps the client's relative pose (the BA did not measure theirs); refined in one
    component, it takes the refined one."""
    turned = se3_from_quat(
        [1.0, 0.0, 0.0], [0, 0, np.sin(np.radians(7.5)), np.cos(np.radians(7.5))]
    )
    for components, expected in (
        ({(1, 1): 0, (1, 2): 1}, se3(np.eye(3), [1.0, 0, 0])),
        (None, turned),
    ):
        graph = TeamPoseGraph()
        graph.add_keyframe(1, 1, np.eye(4))
        graph.add_keyframe(1, 2, se3(np.eye(3), [1.0, 0.0, 0.0]))
        graph.optimize_full()
        graph.adopt_estimates({(1, 1): np.eye(4), (1, 2): turned}, components)
        graph.optimize_full()
        assert np.allclose(graph.T_group_cam(1, 2), expected, atol=1e-4), components


def test_components_need_enough_shared_points_and_a_component_without_depth_holds_its_scale():
    """Two keyframes sharing 2 landmarks are not tied (their relative pose stays free); one
    without depth is held at two keyframes, the first and the farthest from it."""
    from coop_slam.team.global_ba import _hold_each_component, keyframe_components

    obs = [(0, p) for p in range(20)] + [(1, p) for p in range(20)]  # 0-1: 20 shared
    obs += [(1, 30), (1, 31)] + [(2, 30), (2, 31)] + [(2, p) for p in range(40, 60)]
    obs += [(3, p) for p in range(40, 60)]  # 2-3: 20 shared, 1-2: 2
    obs_kf, obs_pt = (np.array(v) for v in zip(*obs))
    assert keyframe_components(5, obs_kf, obs_pt, 15).tolist() == [0, 0, 1, 1, 2]
    assert len(set(keyframe_components(5, obs_kf, obs_pt, 1).tolist())) == 2  # 4 alone
    labels = np.array([0, 0, 1, 1, 1])
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 5, 0], [0, 7, 0], [0, 6, 0]], float)
    fixed, components = _hold_each_component(
        np.array([True, False, False, False, False]),
        labels,
        np.array([True, True, False, False, False]),
        positions,
    )
    assert fixed.tolist() == [True, False, True, True, False]
    assert components.tolist() == [0, 0, 1, 1, 1]


def _hinged_map(hinge_points: int = 16):
    """One robot's 12 keyframes turning on the spot, in two blocks (1-6, 7-12) that share only
    ``hinge_points`` map points between keyframes 6 and 7 (the others are numbered apart): a
    budgeted robot's keyframes held whole, with a gap between them."""
    import dataclasses

    points, desc = cylinder_world(seed=3)
    yaws = np.linspace(0, 3.0, 12)
    truth = {(1, k + 1): looking_out_pose(yaw) for k, yaw in enumerate(yaws)}
    raw = [observe(points, desc, truth[(1, k)], np.eye(4), 1, k, seed=k) for k in range(1, 13)]
    shared = sorted(set(raw[5].map_point_ids.tolist()) & set(raw[6].map_point_ids.tolist()) - {0})
    hinge = np.random.default_rng(0).choice(shared, hinge_points, replace=False)
    records = []
    for r in raw:
        if r.keyframe_id > 6:
            ids = r.map_point_ids.astype(np.int64)
            ids = np.where((ids != 0) & ~np.isin(ids, hinge), ids + 100_000, ids)
            r = dataclasses.replace(r, map_point_ids=ids.astype(np.uint32))
        records.append(stored_keyframe(r, 1))
    return records, truth


def test_odometry_priors_hold_a_block_of_keyframes_tied_by_few_points():
    """Keyframes 7-12 hang on 16 points: without the robot's odometry between neighbouring
    keyframes the BA, started at the truth, carries them centimetres off (the images hardly
    measure where they are); the odometry prior holds them to its sigma."""
    records, truth = _hinged_map()
    tight = dict(odometry_rot_sigma_rad=0.001, odometry_trans_sigma_m=0.001)
    tight.update(odometry_rot_sigma_per_m=0.0, odometry_trans_sigma_per_m=0.0)
    errors = {}
    for name, priors in (("none", dict(odometry_rot_sigma_rad=0.0)), ("tight", tight)):
        config = GlobalBaConfig(iterations=20, disparity_sigma_px=0.05, **priors)
        res = global_bundle_adjustment(records, dict(truth), [], {(1, 1)}, config)
        assert set(res.components.values()) == {0}  # one component: the hinge ties the blocks
        errors[name] = max(transform_error(res.poses[(1, k)], truth[(1, k)])[0] for k in (7, 12))
    assert errors["none"] > 0.03 and errors["tight"] < 0.005, errors


def test_odometry_priors_join_neighbouring_keyframes_of_each_metric_map_segment():
    """Consecutive keyframes of one map segment, metric maps only (a monocular map's poses are
    in its own unit); the prior's sigmas grow with the distance between the keyframes."""
    import dataclasses

    from coop_slam.team.global_ba import build_problem, odometry_pairs
    from helpers import as_monocular

    records, truth, _ = _team()
    records = list(records)
    for k in range(3, 12):  # robot 1 re-initialized at its 4th keyframe
        records[k] = dataclasses.replace(records[k], map_segment=1)
    for k in range(12, 24):
        records[k] = as_monocular(records[k], 1.0)
    pairs = odometry_pairs(records)
    assert pairs == [(0, 1), (1, 2)] + [(k, k + 1) for k in range(3, 11)]
    problem, *_ = build_problem(records[:12], truth, [], {(1, 1)}, GlobalBaConfig())
    assert problem.between_pairs.tolist() == [list(p) for p in pairs]
    dist = np.linalg.norm(problem.between_T[:, :3, 3], axis=1)
    config = GlobalBaConfig()
    assert np.allclose(
        problem.between_sigmas[:, 1],
        config.odometry_trans_sigma_m + config.odometry_trans_sigma_per_m * dist,
    )


def test_odometry_priors_do_not_tie_components_the_images_keep_apart():
    """Keyframes 7-12 share only 5 points with 1-6 (fewer than component_min_shared): their
    component keeps its pose-graph placement (here 20 cm off the robot's odometry), and keyframe
    6 is not pulled towards it by the prior to keyframe 7."""
    records, truth = _hinged_map(hinge_points=5)
    off = se3(np.eye(3), [0.2, 0.0, 0.0])
    start = {k: (off @ T if k[1] > 6 else T) for k, T in truth.items()}
    tight = dict(odometry_rot_sigma_rad=0.001, odometry_trans_sigma_m=0.001)
    config = GlobalBaConfig(iterations=20, disparity_sigma_px=0.05, **tight)
    res = global_bundle_adjustment(records, start, [], {(1, 1)}, config)
    assert len(set(res.components.values())) == 2
    assert transform_error(res.poses[(1, 6)], truth[(1, 6)])[0] < 0.01
    assert transform_error(res.poses[(1, 7)], start[(1, 7)])[0] < 1e-6  # held where it was
