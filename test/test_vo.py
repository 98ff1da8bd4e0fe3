"""Tests of the client's RGB-D visual odometry (coop_slam.vo): pose optimization, local BA, map
consistency under keyframe culling, tracking on a synthetic room, bad input, and RedKitchen
accuracy.
"""

from __future__ import annotations

import os
import threading
import time
import types

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import helpers_vo
from coop_slam.config import load_config, merge_overrides, with_values
from coop_slam.errors import ConfigError
from coop_slam.evaluation.vo_run import ate_rmse, keyframe_ate, run_sequence
from coop_slam.geometry import invert, se3, transform_error, transform_points
from coop_slam.optim.bundle import BaProblem, BaResult, planar_prior, run_local_ba
from coop_slam.vo import (
    EVENT_KEYFRAME_NEW,
    EVENT_KEYFRAME_REMOVE,
    EVENT_KEYFRAME_UPDATE,
    EVENT_NEW_SEGMENT,
    EVENT_WARNING,
    STATE_INITIALIZING,
    STATE_LOST,
    STATE_NEW_SEGMENT,
    STATE_OK,
    STATE_RELOCALIZED,
    VisualOdometry,
    VoConfig,
    VoError,
)
from coop_slam.vo.features import (
    OrbExtractor,
    _orb_level_split,
    level_images,
    level_scales,
    orb_level0_uv,
    orb_level_scales32,
    round_robin,
)
from coop_slam.vo.map import Map
from coop_slam.vo.pose_opt import optimize_pose

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REDKITCHEN = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "redkitchen_0000_0599"))
K = helpers_vo.CAMERA.K


def sync_config(**kw) -> VoConfig:
    """Deterministic configuration: local mapping runs synchronously inside track()."""
    return load_config(VoConfig, merge_overrides({"threaded": False}, kw))


@pytest.fixture(scope="module")
def room_sequence():
    return helpers_vo.sequence(n_frames=45, seed=3, step_m=0.012)


def _project(T_cam_map, points_map):
    pc = transform_points(T_cam_map, points_map)
    return (
        np.stack(
            [K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], 1
        ),
        pc[:, 2],
    )


def _random_pose(rng, rot_deg, trans_m):
    return se3(
        Rotation.from_rotvec(rng.normal(size=3) * np.radians(rot_deg) / np.sqrt(3)).as_matrix(),
        rng.normal(size=3) * trans_m / np.sqrt(3),
    )


# --- pose optimization and local BA ---------------------------------------------------------------
def test_pose_optimization_recovers_pose_and_rejects_outliers():
    rng = np.random.default_rng(0)
    points_map = rng.uniform([-2, -1.5, 1.5], [2, 1.5, 5], (400, 3))
    T_cam_map = _random_pose(rng, 5.0, 0.2)
    uv, z = _project(T_cam_map, points_map)
    bf = K[0, 0] * 0.08
    u_right = uv[:, 0] - bf / z
    uv = uv + rng.normal(0, 0.5, uv.shape)
    uv[:40] += rng.uniform(20, 60, (40, 2))  # gross outliers
    u_right[200:] = np.nan  # half of the keypoints without depth
    T_est, inlier = optimize_pose(np.eye(4), points_map, uv, u_right, np.ones(400), K, bf)
    t_err, r_err = transform_error(T_est, T_cam_map)
    assert t_err < 0.01 and r_err < 0.2
    assert not inlier[:40].any() and inlier[40:].mean() > 0.9


def test_projection_keeps_points_in_view_at_their_predicted_level():
    """project_points against ORB-SLAM's isInFrustum written out: in front, on the image, within
    0.8 x the nearest and 1.2 x the farthest distance the point can be seen at, at most 60 deg
    off its normal; the level from the distance."""
    from coop_slam.vo.matching import project_points

    rng = np.random.default_rng(5)
    n = 4000
    scales = 1.2 ** np.arange(8)
    T_cam_map = se3(Rotation.from_euler("xyz", [5, -10, 3], degrees=True).as_matrix(), [0.2, 0, 1])
    points = rng.uniform([-4, -3, -2], [4, 3, 8], (n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    max_dist = rng.uniform(0.5, 12.0, n)
    got = project_points(T_cam_map, points, K, 40.0, (640, 480), scales, max_dist, normals)

    points_cam = points @ T_cam_map[:3, :3].T + T_cam_map[:3, 3]
    z = points_cam[:, 2]
    uv = points_cam[:, :2] / z[:, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    ray = points - invert(T_cam_map)[:3, 3]
    dist = np.linalg.norm(ray, axis=1)
    cos = (ray * normals).sum(axis=1) / dist
    in_view = (z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    keep = in_view & (dist >= 0.8 * max_dist / scales[-1]) & (dist <= 1.2 * max_dist) & (cos >= 0.5)
    level = np.clip(np.ceil(np.log(max_dist / dist) / np.log(1.2)), 0, 7).astype(int)
    assert 200 < keep.sum() < in_view.sum() - 200
    np.testing.assert_array_equal(got.index, np.flatnonzero(keep))
    np.testing.assert_allclose(got.uv_px, uv[keep], atol=1e-9)
    np.testing.assert_allclose(got.depth_m, z[keep], atol=1e-12)
    np.testing.assert_allclose(got.u_right_px, uv[keep, 0] - 40.0 / z[keep], atol=1e-9)
    np.testing.assert_array_equal(got.pred_octave, level[keep])
    assert len(set(level[keep])) == 8
    plain = project_points(T_cam_map, points, K, 40.0, (640, 480), scales)  # frustum only
    np.testing.assert_array_equal(plain.index, np.flatnonzero(in_view))
    assert not plain.pred_octave.any()


def _search_reference(proj, point_desc, frame, radius_px, scales, max_distance, ratio, exclude,
                      chi2):  # fmt: skip
    """The projection search's rules, one point at a time (see search_by_projection)."""
    from coop_slam.vo.matching import tree_rank

    rank = tree_rank(frame)
    bits = np.unpackbits(point_desc[proj.index][:, None, :] ^ frame.descriptors[None], axis=2)
    bits = bits.sum(axis=2)
    ko = frame.octaves.astype(int)
    stereo = np.isfinite(frame.u_right_px)
    choice = {}
    for m in range(len(proj.index)):
        o = proj.pred_octave[m]
        d2 = ((frame.uv_px - proj.uv_px[m]) ** 2).sum(axis=1)
        ok = (np.sqrt(d2) <= radius_px * scales[o]) & (np.abs(ko - o) <= 1) & ~exclude
        if chi2 is not None:
            err2 = d2 + np.where(stereo, (proj.u_right_px[m] - frame.u_right_px) ** 2, 0.0)
            ok &= err2 / scales[ko] ** 2 <= np.where(stereo, chi2 * 7.815 / 5.991, chi2)
        cands = sorted((int(bits[m, k]), int(rank[k]), int(k)) for k in np.flatnonzero(ok))
        if not cands or cands[0][0] > max_distance:
            continue
        (d, _, k), second = cands[0], cands[1] if len(cands) > 1 else None
        if second and ko[second[2]] == ko[k] and d > ratio * second[0]:
            continue
        if k not in choice or d < choice[k][0]:
            choice[k] = (d, m)
    return sorted((m, k, d) for k, (d, m) in choice.items())


@pytest.mark.parametrize("chi2", [None, 5.991])
def test_projection_search_follows_its_rules_point_by_point(chi2):
    """The compiled search against its rules spelled out point by point: candidates within the
    octave-scaled radius at a neighbouring octave, the nearest descriptor, the ratio test at one
    level, one point per keypoint (ties: the lower point); the depth gate when given."""
    from coop_slam.vo.features import FrameFeatures
    from coop_slam.vo.matching import Projection, search_by_projection

    rng = np.random.default_rng(3)
    n_kp, n_pt = 300, 250
    scales = 1.2 ** np.arange(8)
    kp_desc = rng.integers(0, 256, (n_kp, 32), dtype=np.uint8)
    kp_uv = rng.uniform(0, [640, 480], (n_kp, 2))
    kp_ur = np.where(rng.random(n_kp) < 0.5, kp_uv[:, 0] - rng.uniform(5, 40, n_kp), np.nan)
    octaves = rng.integers(0, 8, n_kp).astype(np.uint8)
    frame = FrameFeatures(
        kp_uv, np.ones(n_kp, np.float32), np.full(n_kp, -1, np.float32), octaves, kp_desc,
        np.ones(n_kp, np.float32), np.zeros((n_kp, 3)), kp_ur,
    )  # fmt: skip
    # Points near keypoints, their descriptors a few bits off (many exact ties in distance).
    near = rng.integers(0, n_kp, n_pt)
    uv = kp_uv[near] + rng.normal(0, 4, (n_pt, 2))
    desc = kp_desc[near].copy()
    flips = rng.integers(0, 32, (n_pt, 3))
    for m in range(n_pt):
        desc[m, flips[m]] ^= np.uint8(1)
    proj = Projection(
        np.arange(n_pt), uv, uv[:, 0] - rng.uniform(5, 40, n_pt), np.ones(n_pt),
        np.clip(octaves[near].astype(int) + rng.integers(-1, 2, n_pt), 0, 7),
    )  # fmt: skip
    exclude = rng.random(n_kp) < 0.1
    got = search_by_projection(proj, desc, frame, 6.0, scales, 50, 0.9, exclude, chi2_gate=chi2)
    want = _search_reference(proj, desc, frame, 6.0, scales, 50, 0.9, exclude, chi2)
    assert len(want) > 30
    assert sorted(zip(*(a.tolist() for a in got))) == want


@pytest.mark.parametrize("seed, ratio", [(0, 1.0), (1, 1.0), (2, 0.9)])
def test_projection_search_breaks_ties_in_the_kd_trees_order(seed, ratio):
    """Where descriptors tie (four distinct ones here), a point's best and second best keypoints
    are the first of them in the KD tree's order (the order a KD-tree pair search gave them; the
    second's level decides the ratio test): clustered keypoints, duplicates, points off the
    image, search radii up to ~80 px."""
    from scipy.spatial import cKDTree

    from coop_slam.vo.features import FrameFeatures
    from coop_slam.vo.matching import Projection, search_by_projection, tree_rank

    rng = np.random.default_rng(seed)
    n_kp, n_pt = 700, 400
    scales = 1.2 ** np.arange(8)
    kp_uv = np.vstack([rng.uniform(0, [640, 480], (n_kp - 200, 2)), rng.normal(300, 8, (200, 2))])
    kp_uv[:20] = kp_uv[20:40]  # keypoints at one position
    kinds = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    kp_desc = kinds[rng.integers(0, 4, n_kp)]
    octaves = rng.integers(0, 8, n_kp).astype(np.uint8)
    frame = FrameFeatures(
        kp_uv, np.ones(n_kp, np.float32), np.full(n_kp, -1, np.float32), octaves, kp_desc,
        np.ones(n_kp, np.float32), np.zeros((n_kp, 3)), np.full(n_kp, np.nan),
    )  # fmt: skip
    uv = np.vstack([rng.uniform(-20, [660, 500], (n_pt - 50, 2)), kp_uv[:50]])
    desc = kinds[rng.integers(0, 4, n_pt)]
    desc[np.arange(n_pt), rng.integers(0, 32, n_pt)] ^= np.uint8(1)  # ties at a nonzero distance
    proj = Projection(np.arange(n_pt), uv, uv[:, 0], np.ones(n_pt), rng.integers(0, 8, n_pt))
    exclude = np.zeros(n_kp, bool)
    got = search_by_projection(proj, desc, frame, 22.0, scales, 256, ratio, exclude)
    want = _search_reference(proj, desc, frame, 22.0, scales, 256, ratio, exclude, None)
    assert len(want) > 100
    assert sorted(zip(*(a.tolist() for a in got))) == want
    # tree_rank is the order in which a KD-tree pair search lists each point's keypoints.
    pairs = cKDTree(uv).sparse_distance_matrix(frame.tree(), 80.0, output_type="ndarray")
    pairs = pairs[np.argsort(pairs["i"], kind="stable")]
    same_point = pairs["i"][1:] == pairs["i"][:-1]
    assert same_point.sum() > 3000
    assert np.all(np.diff(tree_rank(frame)[pairs["j"]])[same_point] > 0)


def _ba_scene(rng, n_kf=5, n_pts=300):
    points = rng.uniform([-2, -1.5, 3], [2, 1.5, 5], (n_pts, 3))
    poses = [
        se3(Rotation.from_euler("y", 2 * k, degrees=True).as_matrix(), [0.1 * k, 0, 0])
        for k in range(n_kf)
    ]
    obs_kf, obs_pt, uv, ur = [], [], [], []
    bf = K[0, 0] * 0.08
    for k, T in enumerate(poses):
        proj, z = _project(invert(T), points)
        for j in range(n_pts):
            obs_kf.append(k)
            obs_pt.append(j)
            uv.append(proj[j] + rng.normal(0, 0.3, 2))
            ur.append(proj[j, 0] - bf / z[j] + rng.normal(0, 0.3) if j % 2 == 0 else np.nan)
    return np.array(poses), points, np.array(obs_kf), np.array(obs_pt), np.array(uv), np.array(ur)


def _ba_problem(T_map_cam, fixed, points_map, obs_kf, obs_pt, uv, ur, octave, **kw) -> BaProblem:
    """A local BA problem over _ba_scene's camera and points (20 iterations)."""
    return BaProblem(
        segment=0,
        kf_ids=np.arange(1, len(T_map_cam) + 1),
        T_map_cam=T_map_cam,
        fixed=np.asarray(fixed),
        point_ids=np.arange(1, len(points_map) + 1),
        points_map=points_map,
        obs_kf=obs_kf,
        obs_pt=obs_pt,
        obs_kp=obs_pt,
        obs_uv=uv,
        obs_u_right=ur,
        obs_octave=octave,
        fx=K[0, 0],
        fy=K[1, 1],
        cx=K[0, 2],
        cy=K[1, 2],
        baseline_m=0.08,
        scale_factor=1.2,
        n_levels=8,
        iterations=20,
        **kw,
    )


def test_covisibility_edges_stay_ordered_by_weight():
    """An edge set, changed or dropped keeps a keyframe's edges by weight, descending; a changed
    edge goes after the others of its weight; dropping an absent edge or setting an unchanged one
    changes nothing."""
    vmap = Map(0)
    kf = types.SimpleNamespace(
        covisible_ids=np.array([4, 7, 9], np.uint32),
        covisible_weights=np.array([30, 20, 20], np.uint16),
    )
    vmap.keyframes[1] = kf

    def edges():
        return list(zip(kf.covisible_ids.tolist(), kf.covisible_weights.tolist()))

    vmap._set_edge(1, 5, 20)  # new: after the 20s already there
    assert edges() == [(4, 30), (7, 20), (9, 20), (5, 20)]
    vmap._set_edge(1, 9, 25)  # raised: moves up
    assert edges() == [(4, 30), (9, 25), (7, 20), (5, 20)]
    vmap._set_edge(1, 4, 10)  # lowered: to the end
    assert edges() == [(9, 25), (7, 20), (5, 20), (4, 10)]
    vmap._set_edge(1, 7, 20)  # unchanged: stays where it is
    assert edges() == [(9, 25), (7, 20), (5, 20), (4, 10)]
    vmap._set_edge(1, 5, 0)  # dropped
    vmap._set_edge(1, 8, 0)  # absent: nothing
    vmap._set_edge(2, 8, 5)  # no such keyframe: nothing
    assert edges() == [(9, 25), (7, 20), (4, 10)]
    assert kf.covisible_ids.dtype == np.uint32 and kf.covisible_weights.dtype == np.uint16


def test_local_ba_reduces_error_of_perturbed_map():
    rng = np.random.default_rng(1)
    poses, points, obs_kf, obs_pt, uv, ur = _ba_scene(rng)
    noisy_poses = np.array(
        [T if k == 0 else T @ _random_pose(rng, 1.0, 0.03) for k, T in enumerate(poses)]
    )
    noisy_points = points + rng.normal(0, 0.04, points.shape)
    fixed = [True] + [False] * (len(poses) - 1)
    octave = np.zeros(len(obs_kf), int)
    problem = _ba_problem(noisy_poses, fixed, noisy_points, obs_kf, obs_pt, uv, ur, octave)
    result = run_local_ba(problem)
    assert result.ok, result.message
    assert result.error_after < 0.5 * result.error_before

    def errors(Ts, pts):
        pose_err = max(transform_error(T, T_true)[0] for T, T_true in zip(Ts, poses))
        return pose_err, np.sqrt(np.mean(np.sum((pts - points) ** 2, axis=1)))

    pose_before, pts_before = errors(noisy_poses, noisy_points)
    pose_after, pts_after = errors(result.T_map_cam, result.points_map)
    assert np.allclose(result.T_map_cam[0], noisy_poses[0])  # the fixed keyframe did not move
    assert pose_after < 0.3 * pose_before and pose_after < 0.01
    assert pts_after < 0.5 * pts_before  # mono points 4 m away stay ~2 cm uncertain
    assert result.outlier_obs.mean() < 0.05


UP_CAM = np.array([0.0, -1.0, 0.0])  # floor normal of a level camera (optical frame: y down)


def _gtsam_error(problem, usable, T_map_cam, points_map) -> float:
    """GTSAM's objective (robust reprojection error, priors) of the problem's graph at a map."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    from coop_slam.optim import bundle

    graph = gtsam.NonlinearFactorGraph()
    bundle._add_keyframes(graph, gtsam.Values(), problem)
    bundle._add_points(graph, gtsam.Values(), problem, usable)
    values = gtsam.Values()
    for k, T in enumerate(T_map_cam):
        values.insert(X(k), gtsam.Pose3(T))
    for j, xyz in enumerate(points_map):
        values.insert(L(j), np.asarray(xyz, float))
    return graph.error(values)


@pytest.mark.parametrize("variant", ["stereo", "planar", "disparity", "monocular"])
def test_the_compiled_local_ba_minimises_gtsams_objective(variant):
    """The compiled solver (schur_ba: LM, points eliminated) minimises the objective of GTSAM's
    factor graph: from the same perturbed map, with outliers in the Huber kernel's linear part,
    it ends as low as GTSAM's optimizer and at the same poses -- mono and stereo residuals at
    three pyramid levels, fixed keyframes, and a ground robot's planar prior, a depth sensor's
    disparity noise or a monocular map's scale anchor. (Points differ by up to millimetres:
    along their rays the cost is flat, and both stop at a relative decrease of 1e-5.)"""
    from coop_slam.optim import bundle

    rng = np.random.default_rng(7)
    poses, points, obs_kf, obs_pt, uv, ur = _ba_scene(rng)
    noisy_poses = np.array(
        [T if k == 0 else T @ _random_pose(rng, 1.0, 0.03) for k, T in enumerate(poses)]
    )
    noisy_points = points + rng.normal(0, 0.04, points.shape)
    uv[::37] += 15.0
    fixed, kw = [True, True, False, False, False], {}
    if variant == "planar":
        kw = {"planar_up_cam": UP_CAM, "planar_sigmas": (np.radians(0.5), 0.01)}
    elif variant == "disparity":
        kw = {"disparity_sigma_px": 0.2}
    elif variant == "monocular":
        ur[:] = np.nan
        fixed, kw = [True, False, False, False, False], {"scale_anchor": (0, 4)}
    octave = rng.integers(0, 3, len(obs_kf))
    problem = _ba_problem(noisy_poses, fixed, noisy_points, obs_kf, obs_pt, uv, ur, octave, **kw)
    usable = np.isfinite(bundle.reprojection_chi2(problem, noisy_poses, noisy_points))
    T_compiled, X_compiled = bundle._optimize_compiled(problem, usable)
    T_gtsam, X_gtsam = bundle._optimize_gtsam(problem, usable)
    before = _gtsam_error(problem, usable, noisy_poses, noisy_points)
    compiled = _gtsam_error(problem, usable, T_compiled, X_compiled)
    gtsam_own = _gtsam_error(problem, usable, T_gtsam, X_gtsam)
    assert compiled < 0.3 * before and compiled <= gtsam_own * (1 + 1e-4), (compiled, gtsam_own)
    apart = max(transform_error(T, T0)[0] for T, T0 in zip(T_compiled, T_gtsam))
    assert apart < 2e-4 and np.array_equal(T_compiled[0], noisy_poses[0])


def test_the_local_ba_is_compiled_unless_it_has_relative_pose_priors(monkeypatch):
    """The client's local BA never builds GTSAM's graph; the server's global BA, which holds
    keyframes to their odometry, does."""
    from coop_slam.optim import bundle

    rng = np.random.default_rng(8)
    poses, points, obs_kf, obs_pt, uv, ur = _ba_scene(rng, n_kf=3, n_pts=60)
    octave = np.zeros(len(obs_kf), int)
    problem = _ba_problem(poses, [True, False, False], points, obs_kf, obs_pt, uv, ur, octave)
    used = []
    for name in ("_optimize_compiled", "_optimize_gtsam"):
        original = getattr(bundle, name)
        monkeypatch.setattr(
            bundle, name, lambda *a, _f=original, _n=name: used.append(_n) or _f(*a)
        )
    assert run_local_ba(problem).ok and used == ["_optimize_compiled"]
    between = {
        "between_pairs": np.array([[1, 2]]),
        "between_T": np.array([invert(poses[1]) @ poses[2]]),
        "between_sigmas": np.array([[0.01, 0.01]]),
    }
    problem = _ba_problem(
        poses, [True, False, False], points, obs_kf, obs_pt, uv, ur, octave, **between
    )
    assert run_local_ba(problem).ok and used == ["_optimize_compiled", "_optimize_gtsam"]


def _tilt_height(T_map_cam):
    """(tilt [deg], height [m]) of a camera pose against the start's level plane (up = -y)."""
    up = T_map_cam[:3, :3] @ UP_CAM
    return np.degrees(np.arccos(np.clip(up @ UP_CAM, -1, 1))), float(T_map_cam[:3, 3] @ UP_CAM)


def test_planar_prior_informs_only_height_and_tilt():
    yawed = se3(Rotation.from_euler("y", 30, degrees=True).as_matrix(), [1.0, 0.0, 2.0])
    T_prior, info = planar_prior(yawed, UP_CAM, np.radians(0.2), 0.01)
    assert np.allclose(T_prior, yawed)  # level, at start height: its own mean, whatever its heading
    assert np.linalg.matrix_rank(info, tol=1.0) == 3  # height, roll, pitch
    # Pitched 0.5 deg about the camera x axis and 3 cm up: chi2 = (0.5/0.2)^2 + (3/1)^2.
    off = yawed @ se3(Rotation.from_euler("x", 0.5, degrees=True).as_matrix(), [0, 0, 0])
    off[:3, 3] += 0.03 * UP_CAM
    T_prior, info = planar_prior(off, UP_CAM, np.radians(0.2), 0.01)
    assert np.allclose(T_prior, yawed, atol=1e-9)
    import gtsam

    err = gtsam.Pose3(T_prior).localCoordinates(gtsam.Pose3(off))
    assert err @ info @ err == pytest.approx(2.5**2 + 3.0**2, rel=1e-3)


def test_local_ba_planar_prior_holds_a_weakly_seen_keyframe_level():
    """A keyframe that sees only a few distant points without depth is barely constrained in
    pitch and height; a ground robot's planar prior puts it back on the floor plane."""
    rng = np.random.default_rng(4)
    poses, points, obs_kf, obs_pt, uv, ur = _ba_scene(rng)
    last = len(poses) - 1
    weak = (obs_kf != last) | (obs_pt < 12)  # the last keyframe keeps 12 observations ...
    ur = np.where(obs_kf == last, np.nan, ur)  # ... without depth
    tilted = poses.copy()
    tilted[last] = poses[last] @ se3(
        Rotation.from_euler("x", 1.0, degrees=True).as_matrix(), [0, 0, 0]
    )
    tilted[last][:3, 3] += 0.03 * UP_CAM

    def solve(planar):
        problem = _ba_problem(
            tilted,
            [True] * last + [False],
            points.copy(),
            obs_kf[weak],
            obs_pt[weak],
            uv[weak],
            ur[weak],
            np.full(int(weak.sum()), 4),  # coarse keypoints: 2 px each
            planar_up_cam=UP_CAM if planar else None,
            planar_sigmas=(np.radians(0.05), 0.003),
        )
        result = run_local_ba(problem)
        assert result.ok, result.message
        return _tilt_height(result.T_map_cam[last])

    tilt_free, height_free = solve(planar=False)
    tilt, height = solve(planar=True)
    assert tilt_free > 0.02 and abs(height_free) > 0.002  # BA alone leaves it off the plane
    assert tilt < 0.25 * tilt_free and abs(height) < 0.25 * abs(height_free)


# --- synthetic tracking ---------------------------------------------------------------------------
def _track_all(vo, stamps, frames):
    return [vo.track(s, img, d) for s, (img, d) in zip(stamps, frames)]


def test_no_frame_waits_for_the_compiler():
    """After kernels.warm_up (what setup and every node run first), tracking and local mapping
    (its BA too) call no compiled kernel with a signature it did not compile (or load from numba's
    cache): in a fresh interpreter, no kernel gains a signature while 20 frames are tracked."""
    import subprocess
    import sys

    code = """
import coop_slam, importlib, pkgutil, sys
sys.path.insert(0, "test")
import helpers_vo
from numba.core.registry import CPUDispatcher
from coop_slam import vo as vo_package
from coop_slam.vo import VisualOdometry, VoConfig
from coop_slam.vo.kernels import warm_up
stamps, frames, _ = helpers_vo.sequence(n_frames=20, seed=3, step_m=0.012)
modules = [importlib.import_module("coop_slam.vo." + m.name)
           for m in pkgutil.iter_modules(vo_package.__path__)]
modules.append(importlib.import_module("coop_slam.optim.schur_ba"))  # local BA, in-process here
kernels = {m.__name__ + "." + k: f for m in modules for k, f in vars(m).items()
           if isinstance(f, CPUDispatcher)}
warm_up()
before = {k: len(f.signatures) for k, f in kernels.items()}
with VisualOdometry(VoConfig(threaded=False), helpers_vo.CAMERA) as vo:
    for s, (img, d) in zip(stamps, frames):
        vo.track(s, img, d)
    assert vo.keyframes_made >= 2, vo.keyframes_made
late = sorted(k for k, f in kernels.items() if len(f.signatures) > before[k])
print("compiled (or loaded) while tracking:", late)
sys.exit(1 if late else 0)
"""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]


def test_tracks_synthetic_room(room_sequence):
    stamps, frames, gt = room_sequence
    with VisualOdometry(sync_config(), helpers_vo.CAMERA) as vo:
        results = _track_all(vo, stamps, frames)
        events = vo.drain_events()
        kfs = vo.keyframes()
        problems = vo.vo_map.check_consistency()
    assert all(r.ok for r in results), [r.message for r in results if not r.ok]
    assert {r.state for r in results} == {STATE_OK}
    assert kfs and all(len(kf.depth_image) for kf in kfs)  # for the team's dense map
    poses = np.array([r.T_map_cam for r in results])
    # The map frame is the first camera: compare against ground truth expressed the same way.
    gt_map = np.array([invert(gt[0]) @ T for T in gt])
    err_t = [transform_error(P, G)[0] for P, G in zip(poses, gt_map)]
    assert max(err_t) < 0.02, max(err_t)
    assert ate_rmse(stamps, poses, gt) < 0.01
    assert len(kfs) >= 2 and problems == []
    assert {e.kind for e in events} >= {EVENT_KEYFRAME_NEW}
    kf = kfs[-1]
    n = len(kf)
    assert kf.descriptors.shape == (n, 32) and kf.descriptors.dtype == np.uint8
    assert kf.keypoints_flat().shape == (4 * n,) and kf.octaves.dtype == np.uint8
    assert len(kf.map_points_xyz) == int((kf.map_point_ids > 0).sum())
    assert len(kf.covisible_ids) == len(kf.covisible_weights) >= 1


@pytest.mark.slow
def test_keyframe_culling_keeps_map_consistent(room_sequence):
    stamps, frames, _ = room_sequence
    # A keyframe at (almost) every frame makes most keyframes redundant, so culling has work to do.
    cfg = sync_config(keyframes={"ref_ratio": 1.0, "min_inliers": 5})
    with VisualOdometry(cfg, helpers_vo.CAMERA) as vo:
        results = _track_all(vo, stamps[:30], frames[:30])
        events = vo.drain_events()
        vmap = vo.vo_map
        assert vmap.check_consistency() == []
        removed = {e.keyframe_id for e in events if e.kind == EVENT_KEYFRAME_REMOVE}
        assert removed, "expected redundant keyframes to be culled"
        assert removed.isdisjoint(vmap.keyframes)
        ids, _ = vo.map_point_arrays()
        referenced = np.unique(np.concatenate([kf.map_point_ids for kf in vmap.keyframes.values()]))
        assert np.isin(referenced[referenced > 0], ids).all()
        for kf in vo.keyframes():
            assert set(kf.covisible_ids.tolist()).isdisjoint(removed)
        # Each point's reference keyframe: the oldest of its observers that culling left.
        xyz, ref = vo.map_points_with_reference()
        alive = vmap.points.alive_ids()
        oldest = [min(vmap.points.obs[int(p)], default=0) for p in alive]
        assert np.array_equal(ref, oldest) and np.array_equal(xyz, vmap.points.xyz[alive])
        assert (ref > 0).any() and not set(ref.tolist()) & removed
    assert all(r.ok for r in results)


def test_threaded_mapping_tracks_and_stops(room_sequence):
    stamps, frames, gt = room_sequence
    with VisualOdometry(VoConfig(threaded=True), helpers_vo.CAMERA) as vo:
        results = _track_all(vo, stamps[:25], frames[:25])
        vo.flush()
        assert vo.vo_map.check_consistency() == []
        assert vo.mapping_stats["ba_runs"] >= 1
    assert all(r.ok for r in results)
    assert ate_rmse(stamps[:25], np.array([r.T_map_cam for r in results]), gt[:25]) < 0.01


def test_a_prestarted_ba_process_is_the_one_the_next_odometry_uses(room_sequence):
    """A node starts the local BA's process before its camera's first frame, and waits for its
    kernels to load; the odometry made then takes that process (and runs its BA there,
    vo.ba.worker_nice nicer than itself), the next one starts its own."""
    from coop_slam.optim import bundle

    stamps, frames, _ = room_sequence
    starting = bundle.BaWorker()
    try:  # a child says when its kernels are loaded (that takes it a second or more) ...
        assert not starting.wait_ready(0.0)
        ready = []  # ... to every thread that waits for it (one reads the greeting)
        waiters = [
            threading.Thread(target=lambda: ready.append(starting.wait_ready(60.0)))
            for _ in range(2)
        ]
        for w in waiters:
            w.start()
        for w in waiters:
            w.join(timeout=90.0)
        assert ready == [True, True] and starting.wait_ready()
    finally:
        starting.close()
    bundle.prestart_worker()  # returns once the child is ready
    prestarted = bundle._PRESTARTED[0]
    assert prestarted._ready
    try:
        with VisualOdometry(VoConfig(threaded=True), helpers_vo.CAMERA) as vo:
            assert vo._mapper._worker is prestarted and not bundle._PRESTARTED
            want = min(os.getpriority(os.PRIO_PROCESS, 0) + VoConfig().ba.worker_nice, 19)
            tasks = os.listdir(f"/proc/{prestarted._proc.pid}/task")  # its libraries' threads too
            assert [os.getpriority(os.PRIO_PROCESS, int(t)) for t in tasks] == [want] * len(tasks)
            _track_all(vo, stamps[:12], frames[:12])
            vo.flush()
            assert vo.mapping_stats["ba_runs"] >= 1 and prestarted._proc.poll() is None
        assert prestarted._proc.poll() is not None, "closed with its odometry"
        other = bundle.take_worker()
        assert other is not prestarted
        other.close()
    finally:
        bundle._close_prestarted()  # none left for another test to take


def test_mapping_backlog_counts_keyframes_a_slow_mapper_has_not_finished(room_sequence):
    """A mapper slower than the camera is visible (mapping_backlog > 1), and flush() -- what a
    lock-step client does after each frame -- waits until it has caught up."""
    stamps, frames, _ = room_sequence
    cfg = sync_config(threaded=True, ba={"enabled": False})
    with VisualOdometry(cfg, helpers_vo.CAMERA) as vo:
        slow = vo._mapper.process

        def process(kf_id, run_ba):
            time.sleep(0.3)
            slow(kf_id, run_ba)

        vo._mapper.process = process
        backlog = []
        for s, (img, d) in zip(stamps[:25], frames[:25]):
            vo.track(s, img, d)
            backlog.append(vo.mapping_backlog)
        assert max(backlog) >= 2
        vo.flush()
        assert vo.mapping_backlog == 0
        created = sum(e.kind == EVENT_KEYFRAME_NEW for e in vo.drain_events())
        assert created == len(vo.keyframes()) + vo.mapping_stats["kf_culled"]


def test_mapping_steps_wait_for_the_frame_being_tracked(room_sequence):
    """Local mapping's steps do not run beside a frame's work (one interpreter: they would take
    its time) -- ``track``, and what a caller encloses with it in ``frame_in_progress`` -- but
    never wait for it longer than ``mapping_yield_max_s``."""
    stamps, frames, _ = room_sequence
    for wait_s, blocked in ((30.0, True), (0.05, False)):
        cfg = sync_config(threaded=True, ba={"enabled": False}, mapping={"yield_max_s": wait_s})
        with VisualOdometry(cfg, helpers_vo.CAMERA) as vo:
            for s, (img, d) in zip(stamps[:3], frames[:3]):
                vo.track(s, img, d)
            vo.flush()
            mapper, vmap = vo._mapper, vo.vo_map
            entered = threading.Event()

            def process(kf_id, run_ba, mapper=mapper, vmap=vmap, entered=entered):
                with mapper._step(vmap):
                    entered.set()

            mapper.process = process
            with vo.frame_in_progress():  # e.g. a node converting a frame and publishing
                vo.track(stamps[3], *frames[3])  # marks its own frame inside the caller's
                mapper.submit(max(vmap.keyframes))
                if blocked:
                    assert not entered.wait(0.3), "a mapping step ran beside the frame"
                else:
                    assert entered.wait(10.0)
            assert entered.wait(10.0)
            vo.flush()
            assert vo.mapping_backlog == 0


def test_relocalizes_after_blackout_and_starts_segment_when_lost_long(room_sequence):
    stamps, frames, _ = room_sequence
    black = np.zeros_like(frames[0][0])
    no_depth = np.zeros_like(frames[0][1])
    cfg = sync_config(relocalization={"max_lost_frames": 4})
    with VisualOdometry(cfg, helpers_vo.CAMERA) as vo:
        for s, (img, d) in zip(stamps[:10], frames[:10]):
            assert vo.track(s, img, d).ok
        last = vo.track(stamps[10], black, no_depth)
        assert not last.ok and last.state == STATE_LOST
        back = vo.track(stamps[11], *frames[11])
        assert back.ok and back.state == STATE_RELOCALIZED
        assert vo.track(stamps[12], *frames[12]).state == STATE_OK
        # A long blackout does not end the map: a covered camera sees nothing to relocalize on.
        states = [vo.track(stamps[13] + 0.01 * i, black, no_depth).state for i in range(1, 7)]
        assert set(states) == {STATE_LOST} and vo.map_segment == 0
        # Views the map cannot place do: a new map segment, announced by an event, starts at the
        # next frame with depth.
        noise = np.random.default_rng(0).integers(0, 256, black.shape, dtype=np.uint8)
        states = [vo.track(stamps[13] + 0.1 + 0.01 * i, noise, no_depth).state for i in range(6)]
        assert STATE_LOST in states and vo.map_segment == 1
        assert any(e.kind == EVENT_NEW_SEGMENT for e in vo.drain_events())
        restart = vo.track(stamps[20], *frames[20])
        assert restart.ok and restart.state == STATE_NEW_SEGMENT and restart.map_segment == 1
        assert np.allclose(restart.T_map_cam, np.eye(4))
        assert all(kf.map_segment == 1 for kf in vo.keyframes())


def test_a_lost_camera_carries_on_in_its_map_from_the_teams_local_map(room_sequence):
    """Server-assisted relocalization, client side: lost where its own keyframes do not place it
    (here: its own relocalizer finds nothing), the odometry gives its view, takes the local map
    the server sends (points in its map frame), relocalizes by PnP and carries on from a new
    keyframe there -- in the same map segment, at the true pose."""
    stamps, frames, gt = room_sequence
    gt_map = [invert(gt[0]) @ T for T in gt]
    black = np.zeros_like(frames[0][0])
    with VisualOdometry(
        sync_config(relocalization={"max_lost_frames": 3}), helpers_vo.CAMERA
    ) as vo:
        for s, (img, d) in zip(stamps[:20], frames[:20]):
            assert vo.track(s, img, d).ok
        kfs = vo.keyframes()
        assert vo.lost_view() is None  # tracking: nothing to ask
        points = np.concatenate([kf.map_points_xyz for kf in kfs])
        descriptors = np.concatenate([kf.descriptors[kf.map_point_ids > 0] for kf in kfs])
        vo._relocalizer.try_frame = lambda *a: None  # its own map cannot place it
        assert vo.track(stamps[20], black, np.zeros_like(frames[0][1])).state == STATE_LOST
        lost = vo.track(stamps[24], *frames[24])
        assert lost.state == STATE_LOST and vo.lost_view() is not None
        vo.expect_local_map()
        for i in (25, 26, 27):  # waiting for the server: no new segment yet
            assert vo.track(stamps[i], *frames[i]).state == STATE_LOST
        vo.offer_local_map(points, descriptors)
        back = vo.track(stamps[28], *frames[28])
        assert back.ok and back.state == STATE_RELOCALIZED and "team map" in back.message
        assert vo.map_segment == 0 and back.new_keyframe_id > kfs[-1].keyframe_id
        assert transform_error(back.T_map_cam, gt_map[28])[0] < 0.02
        nxt = vo.track(stamps[29], *frames[29])
        assert nxt.ok and transform_error(nxt.T_map_cam, gt_map[29])[0] < 0.02
        # The server found no place: the usual new segment after max_lost_frames.
        vo.track(stamps[30], black, np.zeros_like(frames[0][1]))
        vo.expect_local_map()
        vo.offer_local_map(None)
        noise = np.random.default_rng(1).integers(0, 256, black.shape, dtype=np.uint8)
        for i in range(5):
            vo.track(stamps[30] + 0.01 * (i + 1), noise, np.zeros_like(frames[0][1]))
        assert vo.map_segment == 1


# --- bad input ------------------------------------------------------------------------------------
def test_bad_input_raises_vo_error_or_returns_not_ok(room_sequence):
    _stamps, frames, _ = room_sequence
    img, depth = frames[0]
    with VisualOdometry(sync_config(), helpers_vo.CAMERA) as vo:
        with pytest.raises(VoError, match="empty image"):
            vo.track(1.0, np.zeros((0, 0, 3), np.uint8), depth)
        with pytest.raises(VoError, match="camera model"):
            vo.track(1.0, img[:240, :320], depth[:240, :320])
        with pytest.raises(VoError, match="no depth"):
            vo.track(1.0, img, None)
        with pytest.raises(VoError, match="shape"):
            vo.track(1.0, img, depth[:100])
        with pytest.raises(VoError, match="timestamp"):
            vo.track(float("nan"), img, depth)
        # A depth image without any valid pixel cannot start a map: not ok, no exception.
        res = vo.track(1.0, img, np.zeros_like(depth))
        assert not res.ok and res.state == STATE_INITIALIZING and "depth" in res.message
        nan_depth = np.full_like(depth, np.nan)
        assert not vo.track(1.01, img, nan_depth).ok
        with pytest.raises(VoError, match="duplicate"):
            vo.track(1.01, img, depth)
        assert vo.track(1.02, img, depth).ok
        # uint16 depth in sensor units is accepted.
        raw = (depth * helpers_vo.CAMERA.depth_scale).astype(np.uint16)
        assert vo.track(1.03, img, raw).ok


def test_backwards_timestamp_resets_with_warning(room_sequence):
    stamps, frames, _ = room_sequence
    with VisualOdometry(sync_config(), helpers_vo.CAMERA) as vo:
        for s, (img, d) in zip(stamps[:3], frames[:3]):
            assert vo.track(s, img, d).ok
        vo.drain_events()
        res = vo.track(stamps[0], *frames[5])
        events = vo.drain_events()
        kinds = [e.kind for e in events]
        assert EVENT_WARNING in kinds and EVENT_NEW_SEGMENT in kinds
        assert res.ok and res.state == STATE_NEW_SEGMENT and res.map_segment == 1
        assert "timestamp" in next(e.message for e in events if e.kind == EVENT_WARNING)
        # Keyframe ids keep increasing across segments (unique per robot).
        new_ids = [e.keyframe_id for e in events if e.kind == EVENT_KEYFRAME_NEW]
        assert new_ids and min(new_ids) > 1
        # Frames still going back in time: dropped, not one reset each (one reset per jump).
        for k in range(1, 4):
            with pytest.raises(VoError, match="time jumped back"):
                vo.track(stamps[0] - 0.01 * k, *frames[5])
        assert vo.track(stamps[1], *frames[6]).map_segment == 1
        assert vo.track(stamps[0] - 1.0, *frames[7]).map_segment == 2  # a new jump


# --- configuration --------------------------------------------------------------------------------
def test_vo_config_typos_and_bad_ranges_are_rejected():
    with pytest.raises(ConfigError, match="n_feature"):
        load_config(VoConfig, {"n_feature": 10})
    with pytest.raises(ConfigError, match="min_depth_m"):
        load_config(VoConfig, {"min_depth_m": 5.0, "max_depth_m": 1.0})
    # The extraction orients keypoints on the level image itself: a border narrower than the
    # orientation patch would read outside it.
    with pytest.raises(ConfigError, match="edge_threshold_px"):
        load_config(VoConfig, {"features": {"edge_threshold_px": 10}})


# --- real data ------------------------------------------------------------------------------------
@pytest.mark.skipif(
    not os.path.isdir(REDKITCHEN), reason=f"RedKitchen data not found at {REDKITCHEN}"
)
@pytest.mark.slow
def test_redkitchen_first_150_frames_accuracy():
    from coop_slam.datasets import read_tum

    seq = read_tum(REDKITCHEN).slice(0, 150)
    run = run_sequence(seq, sync_config())
    assert run.n_lost == 0 and run.n_segments == 1
    ate = keyframe_ate(run, seq)
    assert ate < 0.03, f"keyframe ATE {ate * 100:.2f} cm"
    assert len(run.keyframes) >= 3


def test_ignored_region_drops_its_keypoints_until_it_expires(room_sequence):
    """Another robot's body (here: a box in front of the camera) gives no keypoints while its
    region is active; the region expires and is dropped with the map; bad regions are refused."""
    stamps, frames, gt = room_sequence
    with VisualOdometry(sync_config(), helpers_vo.CAMERA) as vo:
        first = _track_all(vo, stamps[:3], frames[:3])
        box_cam = np.array(
            [[x, y, z] for x in (-0.3, 0.3) for y in (-0.3, 0.3) for z in (1.0, 4.0)]
        )
        corners_map = transform_points(first[-1].T_map_cam, box_cam)
        with pytest.raises(VoError, match="finite"):
            vo.ignore_region(np.full((8, 3), np.nan), stamps[4])
        with pytest.raises(VoError, match="corners"):
            vo.ignore_region(np.zeros((8, 2)), stamps[4])
        vo.ignore_region(corners_map, until_s=stamps[4])
        masked = _track_all(vo, stamps[3:5], frames[3:5])
        after = _track_all(vo, stamps[5:6], frames[5:6])
    with VisualOdometry(sync_config(), helpers_vo.CAMERA) as ref:
        plain = _track_all(ref, stamps[:6], frames[:6])
    assert all(r.ok for r in masked + after)
    for m, p in zip(masked, plain[3:5]):
        assert m.n_features < 0.9 * p.n_features
    assert after[0].n_features == plain[5].n_features
    vo2 = VisualOdometry(sync_config(), helpers_vo.CAMERA)
    vo2.ignore_region(corners_map, until_s=1e9)
    vo2.reset()
    assert vo2._ignored == []
    vo2.close()


def test_local_ba_announces_no_update_before_a_keyframes_new(room_sequence):
    """Threaded, tracking can insert a keyframe that lands in a running BA's window before local
    mapping announced it: that BA must not send an UPDATE for it (the server would then take the
    UPDATE as the keyframe and reject its NEW as a duplicate). Small moves wait until they add up.
    """
    stamps, frames, _ = room_sequence
    cfg = sync_config(
        keyframes={"ref_ratio": 1.0},
        mapping={"update_min_trans_m": 0.002, "update_min_rot_deg": 0.05},
    )
    with VisualOdometry(cfg, helpers_vo.CAMERA) as vo:
        _track_all(vo, stamps[:12], frames[:12])
        vo.drain_events()
        vmap, mapper = vo.vo_map, vo._mapper
        kf_ids = sorted(vmap.keyframes)
        assert len(kf_ids) >= 3
        mapper._sent_pose.pop(kf_ids[-1])  # as if tracking had just inserted it

        def move_all(step_m):
            nudge = se3(np.eye(3), [step_m, 0.0, 0.0])
            result = BaResult(
                segment=vmap.segment,
                ok=True,
                kf_ids=np.array(kf_ids),
                T_map_cam=np.array([vmap.keyframes[k].T_map_cam @ nudge for k in kf_ids]),
                point_ids=np.zeros(0, np.int64),
                points_map=np.zeros((0, 3)),
                outlier_obs=np.zeros(0, bool),
                obs_kf_ids=np.zeros(0, np.int64),
                obs_point_ids=np.zeros(0, np.int64),
            )
            with vmap.lock:
                mapper.apply_ba_result(vmap, result)
            assert np.allclose(vmap.keyframes[kf_ids[-1]].T_map_cam, result.T_map_cam[-1])
            return {e.keyframe_id for e in vo.drain_events() if e.kind == EVENT_KEYFRAME_UPDATE}

        assert move_all(0.005) == set(kf_ids[:-1])
        # Moves below update_min_trans_m (2 mm here) are not sent, until they add up to it.
        assert move_all(0.0015) == set()
        assert move_all(0.0015) == set(kf_ids[:-1])


def test_orb_keypoints_sit_where_the_pyramid_found_them():
    """A keypoint of pyramid level l is a FAST corner (x_l, y_l) of OpenCV's level-l image, placed
    at that pixel's centre in level 0, (x_l + 0.5) * s - 0.5, not at OpenCV's pt = x_l * s."""
    import cv2

    rng = np.random.default_rng(0)
    gray = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (0, 0), 1.5)
    cfg = VoConfig()
    feats = OrbExtractor(cfg, helpers_vo.CAMERA).extract(gray)
    h, w = gray.shape
    level_img = gray
    fast = cv2.FastFeatureDetector_create(cfg.features.fast_threshold, True)
    checked = 0
    for level in range(cfg.features.n_levels):
        s = float(np.float32(cfg.features.scale_factor) ** level)
        if level:  # OpenCV's pyramid: a cascade of resizes to its rounded level sizes
            size = (round(w / s), round(h / s))
            level_img = cv2.resize(level_img, size, interpolation=cv2.INTER_LINEAR_EXACT)
        corners = np.array([k.pt for k in fast.detect(level_img, None)])
        expected = (corners + 0.5) * s - 0.5
        uv = feats.uv_px[feats.octaves == level]
        dist = np.linalg.norm(uv[:, None, :] - expected[None, :, :], axis=2).min(axis=1)
        assert np.all(dist < 1e-3), (level, float(dist.max()))
        checked += len(uv) if level >= 3 else 0
    assert checked > 50  # the coarse levels, where pt was off most, were exercised


@pytest.mark.parametrize(
    "n_detect,threads,shape",
    [
        (2500, 2, (480, 640)),
        (9, 2, (480, 640)),
        (2500, 1, (480, 640)),
        (2500, 2, (540, 960)),  # 540 / 1.2**3 = 312.5: OpenCV rounds it in float32
        (2500, 3, (342, 597)),  # 597 / 1.2: rounds to 498 in float32, 497 in double
        (2500, 1, (483, 641)),
    ],
)
def test_orb_levels_extracted_on_threads_are_opencvs_whole_pyramid_orb(n_detect, threads, shape):
    """Each level detected and described by its own one-level ORB (levels shared by threads)
    finds exactly the keypoints and descriptors one OpenCV ORB over the pyramid finds, then
    bucketed: positions, sizes, angles, levels, bits, in OpenCV's order."""
    import cv2

    rng = np.random.default_rng(1)
    gray = cv2.GaussianBlur((rng.random(shape) * 255).astype(np.uint8), (0, 0), 1.2)
    cfg = with_values(
        VoConfig(), {"features": {"n_detect": n_detect, "n_features": min(n_detect, 1000)}}
    )
    f = cfg.features
    extractor = OrbExtractor(cfg, helpers_vo.CAMERA, threads)
    whole = cv2.ORB_create(
        nfeatures=n_detect, scaleFactor=f.scale_factor, nlevels=f.n_levels,
        edgeThreshold=f.edge_threshold_px, patchSize=31, fastThreshold=f.fast_threshold,
    )  # fmt: skip
    found = whole.detect(gray, None)
    table = np.array([(*k.pt, k.response, k.octave) for k in found])
    cell_px = f.grid_cell_px * level_scales(cfg)
    keep = round_robin(*table[:, :3].T, table[:, 3].astype(int), cell_px, f.n_features)
    kps, desc = whole.compute(gray, [found[i] for i in keep])
    got = extractor.extract(gray)
    assert len(got) == len(kps) > 0
    pt = np.array([k.pt for k in kps])
    octaves = np.array([k.octave for k in kps])
    assert np.array_equal(got.uv_px, orb_level0_uv(pt, octaves, f.scale_factor))
    assert np.array_equal(got.size_px, np.array([k.size for k in kps], np.float32))
    assert np.array_equal(got.angle_deg, np.array([k.angle for k in kps], np.float32))
    assert np.array_equal(got.octaves, octaves)
    assert np.array_equal(got.descriptors, desc)
    if n_detect == 2500:
        assert set(octaves) == set(range(f.n_levels))


def test_a_frames_images_extracted_together_are_each_extracted_alone():
    """A stereo pair's images share the threads level by level: each image's keypoints and
    pyramid are what it gets alone, on any number of threads."""
    import cv2

    rng = np.random.default_rng(4)
    images = [
        cv2.GaussianBlur((rng.random(shape) * 255).astype(np.uint8), (0, 0), 1.2)
        for shape in ((480, 640), (480, 640), (300, 500))
    ]
    alone = [OrbExtractor(VoConfig(), helpers_vo.CAMERA, 1).extract_with_levels(g) for g in images]
    for threads in (1, 2, 5):
        together = OrbExtractor(VoConfig(), helpers_vo.CAMERA, threads).extract_images(images)
        assert len(together) == len(images)
        for (got, got_levels), (want, want_levels) in zip(together, alone):
            assert _same_keypoints(got, want) and np.array_equal(got.uv_px, want.uv_px)
            assert len(got_levels) == len(want_levels) == VoConfig().features.n_levels
            assert all(np.array_equal(a, b) for a, b in zip(got_levels, want_levels))
        assert together[0][1][0] is images[0]  # level 0 is the caller's image


@pytest.mark.parametrize(
    "bad,what",
    [
        (np.zeros((48, 64), np.float32), "uint8"),
        (np.zeros((48, 64, 3), np.uint8), "2D"),
        (np.zeros((64, 48), np.uint8).T, "C-contiguous"),
        (np.zeros((0, 64), np.uint8), "non-empty"),
    ],
)
def test_an_image_the_extraction_cannot_take_is_a_clear_error(bad, what):
    """The compiled extraction checks its input (rather than read memory it does not own) and
    names the image; the extractor works afterwards."""
    gray = (np.random.default_rng(5).random((120, 160)) * 255).astype(np.uint8)
    extractor = OrbExtractor(VoConfig(), helpers_vo.CAMERA)
    want = extractor.extract(gray)
    with pytest.raises(VoError, match=f"image 1.*{what}"):
        extractor.extract_images([gray, bad])
    assert np.array_equal(extractor.extract(gray).descriptors, want.descriptors)


def _same_keypoints(a, b) -> bool:
    """The same keypoints (position, size, angle, level, bits), in any order (OpenCV's selection
    of a level's best reorders them by what else it was given)."""
    if len(a) != len(b):
        return False
    order_a, order_b = (np.lexsort((k.uv_px[:, 1], k.uv_px[:, 0], k.octaves)) for k in (a, b))
    return all(
        np.array_equal(getattr(a, name)[order_a], getattr(b, name)[order_b])
        for name in ("uv_px", "size_px", "angle_deg", "octaves", "descriptors")
    )


@pytest.mark.parametrize("gain", [3.0, 0.6, 0.3])
def test_a_level_is_detected_at_the_low_fast_threshold_only_when_the_first_finds_too_few(gain):
    """Detecting each level at FAST 20 first finds what FAST 7 alone finds when the level has
    plenty of strong corners (ORB keeps the 2n best FAST scores of a level: all of them >= 20), and
    falls back to FAST 7 where it finds fewer than the level wants: high contrast, every level
    strong; low contrast, every level falls back; in between, some levels keep fewer, stronger
    corners than FAST 7 alone would give. Every level's keypoints (all kept: no bucketing) are
    those of the pass its rule picks."""
    import cv2

    rng = np.random.default_rng(2)
    noise = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (0, 0), 1.2)
    gray = np.uint8(np.clip(128 + (noise.astype(float) - 128) * gain, 0, 255))
    cfg = with_values(
        VoConfig(),
        {"features": {"fast_threshold": 7, "fast_threshold_first": 20, "n_features": 2500}},
    )
    extractor = OrbExtractor(cfg, helpers_vo.CAMERA)
    one_pass = OrbExtractor(with_values(cfg, {"features": {"fast_threshold_first": 0}}), None)
    f = cfg.features
    levels = level_images(gray, orb_level_scales32(f.scale_factor, f.n_levels))
    wanted = _orb_level_split(f.n_detect, f.scale_factor, f.n_levels)

    def level_pass(n: int, threshold: int):
        return cv2.ORB_create(n, f.scale_factor, 1, f.edge_threshold_px, patchSize=31,
                              fastThreshold=threshold)  # fmt: skip

    strong = [
        len(level_pass(wanted[lv], 20).detect(image, None)) >= wanted[lv]
        for lv, image in enumerate(levels)
    ]
    got, alone = extractor.extract(gray), one_pass.extract(gray)
    assert len(got) == f.n_detect or not all(strong)
    scales32 = orb_level_scales32(f.scale_factor, f.n_levels)
    for lv, image in enumerate(levels):
        kps = level_pass(wanted[lv], 20 if strong[lv] else 7).detect(image, None)
        pt = np.float32([k.pt for k in kps]).reshape(-1, 2) * scales32[lv]
        want = orb_level0_uv(pt, np.full(len(pt), lv), f.scale_factor)
        have = got.uv_px[got.octaves == lv]
        assert len(have) == len(want) and np.array_equal(
            have[np.lexsort(have.T)], want[np.lexsort(want.T)]
        ), lv
    if gain == 3.0:
        assert all(strong)
        assert _same_keypoints(got, alone)
    elif gain == 0.3:
        assert not any(strong)
        assert _same_keypoints(got, alone)
    else:
        assert any(strong) and not all(strong), strong
        assert not _same_keypoints(got, alone)


def test_bucketing_takes_every_cells_best_first_then_the_second_best():
    """The bucketing's order against its definition written with lexicographic sorts, on tables
    with many equal responses and many keypoints in one cell (ties: by index)."""
    rng = np.random.default_rng(3)
    cell_px = 40.0 * 1.2 ** np.arange(8)
    for _ in range(40):
        n = int(rng.integers(2, 3000))
        u, v = rng.integers(0, 80, n) * 8.0, rng.integers(0, 60, n) * 8.0
        response = rng.integers(0, 5, n) * 1e-4
        octave = rng.integers(0, 8, n)
        n_keep = int(rng.integers(1, n + 1))
        cell = (octave * 4096 + np.floor(v / cell_px[octave])) * 4096 + np.floor(
            u / cell_px[octave]
        )
        by_cell = np.lexsort((-response, cell))
        rank = np.empty(n, np.int64)
        for i, k in enumerate(by_cell):
            rank[k] = 0 if i == 0 or cell[k] != cell[by_cell[i - 1]] else rank[by_cell[i - 1]] + 1
        expected = np.sort(np.lexsort((-response, rank))[:n_keep])
        got = round_robin(u, v, response, octave, cell_px, n_keep)
        assert np.array_equal(got, expected)
