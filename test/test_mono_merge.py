"""Monocular robots in the server core (#23): merges by similarity, the monocular map's scale, and
its keyframes metric in the team map after a merge with a metric robot."""

import numpy as np
import pytest

from coop_slam.evaluation.metrics import ate
from coop_slam.geometry import invert, transform_error
from coop_slam.team.server import TeamServer
from helpers import (
    TEAM_T_WORLD_MAP,
    as_monocular,
    cylinder_world,
    team_keyframes,
    team_server_config,
    team_world,
)

UNITS_PER_M = 2.5  # the monocular map's own length unit: 0.4 m


_config = team_server_config


@pytest.fixture(scope="module")
def world():
    return team_world()


def _mono_b(points, desc, yaws, kid0=1, t0=100.0):
    kfs = team_keyframes(
        2, yaws, points, desc, kid0=kid0, offset=(0.2, 0.1), seed=100 + kid0, t0=t0
    )
    return [as_monocular(kf, UNITS_PER_M) for kf in kfs]


def test_monocular_robot_merges_with_a_metric_one_by_a_similarity(world):
    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(), vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    assert server.is_metric(1)
    merges = []
    for kf in _mono_b(points, desc, np.linspace(2.0, 3.0, 8)):
        merges += server.add_keyframe(kf)
        if not merges:
            assert not server.is_metric(2) and server.map_scale(2) == 1.0
    assert len(merges) == 1 and server.groups.groups() == [[1, 2]]
    m = merges[0]
    # The similarity's scale: robot 2's own units into robot 1's metres.
    assert m.scale == pytest.approx(1 / UNITS_PER_M, rel=0.02)
    assert server.is_metric(2)
    assert server.map_scale(2) == pytest.approx(1 / UNITS_PER_M, rel=0.02)
    # The merge is rigid in metres, as any.
    dt, dr = transform_error(m.T_mapA_mapB, invert(TEAM_T_WORLD_MAP[1]) @ TEAM_T_WORLD_MAP[2])
    assert dt < 0.02 and dr < 0.5
    # Keyframes the robot sends later arrive in its own units and sit metric in the team map.
    later = _mono_b(points, desc, np.linspace(3.1, 3.6, 4), kid0=20, t0=120.0)
    for kf in later:
        server.add_keyframe(kf)
    T_group_map_true = invert(TEAM_T_WORLD_MAP[1]) @ TEAM_T_WORLD_MAP[2]
    for kf in later:
        T_map_cam_m = kf.T_map_cam.copy()
        T_map_cam_m[:3, 3] /= UNITS_PER_M  # in metres, as the truth
        stored = server.store.record((2, kf.keyframe_id)).T_map_cam
        assert transform_error(stored, T_map_cam_m)[0] < 0.03
        dt, dr = transform_error(
            server.T_group_cam(2, kf.keyframe_id), T_group_map_true @ T_map_cam_m
        )
        assert dt < 0.03 and dr < 0.5, (kf.keyframe_id, dt, dr)


def test_global_ba_that_bends_a_monocular_map_leaves_it_as_the_pose_graph_had_it(world):
    """A global BA result that moves a monocular map's keyframes by a similarity is taken; one
    that bends them (here by 5 % of their spread) is not for that map -- it keeps its pose-graph
    poses -- while the metric map's refined poses are taken either way."""
    from coop_slam.team.global_ba import GlobalBaResult, unbent_mono

    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(), vocab)
    for kf in kfs_a + _mono_b(points, desc, np.linspace(2.0, 3.0, 8)):
        server.add_keyframe(kf)
    assert server.groups.groups() == [[1, 2]]
    before = {k: server.T_group_cam(*k) for k in sorted(server.store.keys())}
    mono = [k for k in before if k[0] == 2]
    assert len(mono) >= 3

    def ba_result(move):
        poses = {k: T.copy() for k, T in before.items()}
        for i, k in enumerate(mono):
            poses[k][:3, 3] = move(i, poses[k][:3, 3])
        return GlobalBaResult(poses, len(poses), 0, 0, 0, 0.0, 0.0, 0.0, 0.0, {k: 0 for k in poses})

    xyz = np.array([before[k][:3, 3] for k in mono])
    spread = np.sqrt(np.mean(np.sum((xyz - xyz.mean(axis=0)) ** 2, axis=1)))
    share = server.config.global_ba.mono_max_bend
    similar = unbent_mono(ba_result(lambda i, t: 1.03 * t + [0.1, 0, 0]), before, {2}, share)
    assert set(similar.poses) == set(before)
    bend = np.where(np.arange(len(mono)) % 2, 1.0, -1.0) * 0.05 * spread
    bent = unbent_mono(ba_result(lambda i, t: t + [0, bend[i], 0]), before, {2}, share)
    assert set(bent.poses) == {k for k in before if k[0] == 1}
    assert set(bent.components) == set(bent.poses)


@pytest.mark.parametrize("similarity_inliers", [40, 10_000])
def test_a_merge_by_a_similarity_has_its_own_inlier_count(world, similarity_inliers):
    """Place recognition holds a similarity (a monocular side: 3D-3D inliers on the points its
    local mapping triangulated) to merge_min_inliers_similarity, not to the rigid count."""
    points, desc, kfs_a, vocab = world
    cfg = _config()
    cfg.place_recognition.merge_min_inliers = 10_000  # no rigid merge could pass
    cfg.place_recognition.merge_min_inliers_similarity = similarity_inliers
    cfg.rendezvous.auto = False  # place recognition alone
    server = TeamServer(cfg, vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    for kf in _mono_b(points, desc, np.linspace(2.0, 3.0, 8)):
        server.add_keyframe(kf)
    assert len(server.merges) == (1 if similarity_inliers == 40 else 0)


def test_monocular_keyframes_never_merge_with_an_unrelated_place(world):
    _, _, kfs_a, vocab = world
    other_points, other_desc = cylinder_world(seed=99)  # a different building
    server = TeamServer(_config(), vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    server.request_rendezvous(1, 2, stamp_s=0.0)  # together: co-observations merge on one
    kfs_b = team_keyframes(2, np.linspace(0, 2 * np.pi, 20), other_points, other_desc, seed=7)
    for kf in kfs_b:
        assert server.add_keyframe(as_monocular(kf, UNITS_PER_M)) == []
    assert server.merges == [] and server.groups.groups() == [[1], [2]]
    assert not server.is_metric(2)


def test_two_monocular_robots_merge_in_the_first_ones_units(world):
    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(), vocab)
    for kf in kfs_a[::2]:
        server.add_keyframe(as_monocular(kf, 1.0))  # robot 1: its units are metres by chance
    merges = []
    for kf in _mono_b(points, desc, np.linspace(2.0, 3.0, 8)):
        merges += server.add_keyframe(kf)
    assert len(merges) == 1 and server.groups.groups() == [[1, 2]]
    assert not server.is_metric(1) and not server.is_metric(2)
    assert server.map_scale(1) == 1.0
    assert server.map_scale(2) == pytest.approx(1 / UNITS_PER_M, rel=0.02)
    # Monocular maps only: both scales drift in the team graph, each held by one weak prior, and
    # the link's scale measures them.
    assert {key[0] for _, key, _ in server.graph.edges("scale_prior")} == {1, 2}


def test_ate_with_scale_correction_recovers_the_scale():
    rng = np.random.default_rng(0)
    n = 50
    poses_gt = np.tile(np.eye(4), (n, 1, 1))
    poses_gt[:, :3, 3] = np.cumsum(rng.normal(0, 0.1, (n, 3)), axis=0)
    poses_est = poses_gt.copy()
    poses_est[:, :3, 3] *= UNITS_PER_M
    stamps = np.arange(n, dtype=float)
    res = ate(stamps, poses_est, stamps, poses_gt, correct_scale=True)
    assert res.rmse_m < 1e-6 and res.scale == pytest.approx(1 / UNITS_PER_M)
    assert ate(stamps, poses_est, stamps, poses_gt).rmse_m > 0.1


# --- a marker sighting gives a monocular map its scale ----------------------------------------
def test_marker_scale_estimate_with_a_moving_or_standing_observed_robot():
    from coop_slam.geometry import se3_from_quat
    from coop_slam.team.marker_scale import estimate_scale

    rng = np.random.default_rng(0)
    n, s_true = 10, 1 / UNITS_PER_M
    T_A_B = se3_from_quat([1.0, -2.0, 0.3], [0, 0, 0.3, 1.0])
    c_m = np.c_[np.linspace(0, 2, n), 0.3 * np.sin(np.linspace(0, 3, n)), np.zeros(n)]
    for b in (
        np.c_[np.linspace(3, 3.5, n), np.linspace(0, 1, n), np.zeros(n)],  # moving
        np.tile([[3.0, 0.5, 0.0]], (n, 1)),  # standing
    ):
        q = (T_A_B[:3, :3] @ b.T).T + T_A_B[:3, 3] - c_m + rng.normal(0, 0.005, (n, 3))
        scale, rms = estimate_scale(c_m / s_true, q, b)
        assert scale == pytest.approx(s_true, rel=0.02) and rms < 0.02


def test_sightings_of_a_metric_robots_marker_fix_a_monocular_maps_scale(world):
    """Robot 2 (monocular) drives along a wall while it sights robot 1's marker: the server gives
    its map metres without any feature match between the two."""
    from coop_slam.geometry import se3_from_quat
    from helpers import make_keyframe

    _, _, _, vocab = world
    server = TeamServer(_config(), vocab)
    T_body_cam = se3_from_quat([0.1, 0.0, 0.3], [-0.5, 0.5, -0.5, 0.5])
    T_world_map = {1: TEAM_T_WORLD_MAP[1], 2: TEAM_T_WORLD_MAP[2]}
    poses = {}  # robot -> (stamps, T_map_cam metric)
    for robot, path in (
        (1, lambda t: [0.2 * t, 1.0, 0.0]),  # robot 1 creeps along
        (2, lambda t: [0.3 * t, -1.0 + 0.05 * t, 0.0]),  # robot 2 drives past it
    ):
        stamps = np.arange(0.0, 10.0, 0.5)
        T = [se3_from_quat(path(t), [0.0, 0.0, 0.05 * t, 1.0]) for t in stamps]
        poses[robot] = (stamps, T)
        for k, (t, T_map_cam) in enumerate(zip(stamps, T)):
            kf = make_keyframe(n=60, robot_id=robot, keyframe_id=k + 1, seed=100 * robot + k)
            kf.stamp_s, kf.T_map_cam = float(t), T_map_cam.copy()
            server.add_keyframe(as_monocular(kf, UNITS_PER_M) if robot == 2 else kf)
    assert not server.is_metric(2)
    for k, t in enumerate(poses[2][0]):
        T_world_camA = T_world_map[2] @ poses[2][1][k]
        T_world_bodyB = T_world_map[1] @ poses[1][1][k] @ invert(T_body_cam)
        T_camA_bodyB = invert(T_world_camA) @ T_world_bodyB
        server.sighting(2, 1, float(t), T_camA_bodyB, T_body_cam)
    assert server.is_metric(2) and server.groups.groups() == [[1], [2]]
    assert server.map_scale(2) == pytest.approx(1 / UNITS_PER_M, rel=0.02)


def test_the_team_cloud_follows_a_monocular_keyframes_local_scale(world):
    """Once a monocular map is metric its scale may drift in the team graph: each keyframe's
    points are drawn at its local scale about its camera."""
    points, desc, kfs_a, vocab = world
    cfg = _config()
    cfg.fuse_radius_m = 0.0  # robot 2's points stay its own (fused ones are drawn once)
    server = TeamServer(cfg, vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    for kf in _mono_b(points, desc, np.linspace(2.0, 3.0, 8)):
        server.add_keyframe(kf)
    assert server.groups.groups() == [[1, 2]]
    server.optimize()
    assert server.graph._scale_drift == {2}  # metric by the merge: its scale may now drift

    def camera_distances():
        cloud, _, robots = server.team_cloud()
        centres = np.array(
            [server.T_group_cam(*k)[:3, 3] for k in server.store.keys() if k[0] == 2]
        )
        mine = cloud[robots == 2]
        return np.median(np.min(np.linalg.norm(mine[:, None] - centres[None], axis=2), axis=1))

    before = camera_distances()
    for key in [k for k in server.store.keys() if k[0] == 2]:
        server.graph._log_scale[key] = np.log(0.5)
    assert camera_distances() == pytest.approx(0.5 * before, rel=0.15)


def test_a_delta_update_of_a_rescaled_map_keeps_its_other_points(world):
    """A delta update is completed from the keyframe the server holds, in the robot's own units
    (the server rescaled the map at the merge): its points the patch leaves out stay where the
    server had them (they were scaled a second time)."""
    import dataclasses

    from coop_slam.wire.observations import complete_update, patch_of
    from coop_slam.wire.record import ACTION_UPDATE

    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(), vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    mono = _mono_b(points, desc, np.linspace(2.0, 3.0, 8))
    for kf in mono:
        server.add_keyframe(kf)
    s = server.map_scale(2)
    assert s == pytest.approx(1 / UNITS_PER_M, rel=0.02)
    kf = mono[-1]
    own = server.stored_record(2, 0, kf.keyframe_id)
    np.testing.assert_allclose(own.map_points, kf.map_points, rtol=1e-5)
    np.testing.assert_allclose(own.T_map_cam, kf.T_map_cam, atol=1e-6)
    patched = np.flatnonzero(kf.map_point_ids)[:1]  # local BA moved one point
    per_kp = kf.map_points_per_keypoint()
    per_kp[patched] += 0.1
    upd = dataclasses.replace(
        kf, action=ACTION_UPDATE, map_points=per_kp[kf.map_point_ids != 0].astype(np.float32)
    )
    ids, pts = patch_of(upd, patched)
    sent = dataclasses.replace(upd, map_point_ids=ids, map_points=pts)
    server.add_keyframe(complete_update(sent, server.stored_record(2, 0, kf.keyframe_id), patched))
    held = server.store.record((2, kf.keyframe_id))
    np.testing.assert_allclose(held.map_points, upd.map_points * s, rtol=1e-4)
