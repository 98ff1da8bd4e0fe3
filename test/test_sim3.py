"""Tests of coop_slam.registration.sim3 and its sim3_* modules (similarity registration for
monocular maps).

Synthetic scene: points 2-8 m in front of keyframe A, seen by keyframe B whose map is scaled:
``p_a = scale * R p_b + t`` with a 30 deg rotation and |t| = 1 (A's units). Each keyframe observes
its points with 1 px pixel noise and holds them as map points on the noisy pixel's ray with 0.5 %
depth noise (a triangulated monocular map point); 30 % of the correspondences are wrong matches
(B's side shuffled among them).
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_slam.config import load_config
from coop_slam.errors import ConfigError, CoopSlamError
from coop_slam.geometry import rotation_angle_deg
from coop_slam.registration import RegistrationError, backproject, umeyama
from coop_slam.registration.camera import project
from coop_slam.registration.sim3 import (
    Sim3Config,
    estimate_sim3,
    sim3_inverse,
    sim3_matrix,
    sim3_transform_points,
)
from coop_slam.registration.sim3_data import Sim3Error
from coop_slam.registration.sim3_ransac import ransac_sim3
from coop_slam.registration.sim3_refine import refine_sim3

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
WIDTH, HEIGHT = 640, 480
AXIS = np.array([0.2, -0.95, 0.24])
R_A_B = Rotation.from_rotvec(np.radians(30.0) * AXIS / np.linalg.norm(AXIS)).as_matrix()
T_A_B = np.eye(4)
T_A_B[:3, :3] = R_A_B
T_A_B[:3, 3] = np.array([0.8, 0.1, 0.59]) / np.linalg.norm([0.8, 0.1, 0.59])  # |t| = 1


def make_pair(scale, n=200, outlier_frac=0.3, px_noise=1.0, depth_noise=0.005, seed=0):
    """(points_a_cam, uv_a_px, points_b_cam, uv_b_px, is_inlier) of n correspondences."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [WIDTH, HEIGHT], (20 * n, 2))
    points_a = backproject(uv, rng.uniform(2.0, 8.0, len(uv)), K)
    points_b = sim3_transform_points(*sim3_inverse(T_A_B, scale), points_a)
    uv_b = project(points_b, K)
    seen = (points_b[:, 2] > 0.1) & np.all((uv_b > 0) & (uv_b < [WIDTH, HEIGHT]), axis=1)
    points_a, points_b = points_a[seen][:n], points_b[seen][:n]
    assert len(points_a) == n

    def observe(points_cam):
        uv_px = project(points_cam, K) + rng.normal(0.0, px_noise, (len(points_cam), 2))
        depth = points_cam[:, 2] * (1.0 + depth_noise * rng.normal(size=len(points_cam)))
        return backproject(uv_px, depth, K), uv_px

    points_a, uv_a = observe(points_a)
    points_b, uv_b = observe(points_b)
    outliers = rng.choice(n, round(outlier_frac * n), replace=False)
    points_b[outliers] = points_b[np.roll(outliers, 1)]
    uv_b[outliers] = uv_b[np.roll(outliers, 1)]
    is_inlier = np.ones(n, dtype=bool)
    is_inlier[outliers] = False
    return points_a, uv_a, points_b, uv_b, is_inlier


def errors(T_a_b, scale, scale_true):
    """(rotation [deg], translation error / |t|, relative scale error)."""
    rot = rotation_angle_deg(T_a_b[:3, :3].T @ T_A_B[:3, :3])
    trans = np.linalg.norm(T_a_b[:3, 3] - T_A_B[:3, 3]) / np.linalg.norm(T_A_B[:3, 3])
    return rot, trans, abs(scale / scale_true - 1.0)


def ransac(points_a, uv_a, points_b, uv_b, **kwargs):
    return ransac_sim3(
        points_b, points_a, uv_src_px=uv_b, uv_dst_px=uv_a, K_src=K, K_dst=K, **kwargs
    )


# --- accuracy -------------------------------------------------------------------------------------
@pytest.mark.parametrize("scale", [0.3, 2.5])
def test_recovers_known_similarity_with_outliers(scale):
    points_a, uv_a, points_b, uv_b, is_inlier = make_pair(scale)
    res = estimate_sim3(points_a, uv_a, K, points_b, uv_b, K)
    assert res.accepted, res.reason
    rot, trans, scale_err = errors(res.T_a_b, res.scale, scale)
    assert rot < 0.2 and trans < 0.01 and scale_err < 0.01, (rot, trans, scale_err)
    # the gate separates wrong matches and keeps nearly all right ones
    assert (res.inliers & ~is_inlier).sum() == 0
    assert res.n_inliers >= 0.9 * is_inlier.sum()
    assert res.residual_px < 2.5  # ~2 px: each residual carries both keyframes' 1 px noise
    # the similarity matrix maps B's inlier points onto A's within the depth noise
    moved = res.sim3_a_b[:3, :3] @ points_b[is_inlier].T + res.sim3_a_b[:3, 3:]
    rel = np.linalg.norm(moved.T - points_a[is_inlier], axis=1) / points_a[is_inlier, 2]
    assert np.median(rel) < 0.01


def test_refinement_improves_on_ransac():
    # With 1 % depth noise (a map point seen from a short baseline) the 3D fit of RANSAC suffers
    # from the depths; the refinement weighs the points as their pixels warrant.
    before, after = [], []
    for seed in range(5):
        points_a, uv_a, points_b, uv_b, _ = make_pair(0.3, depth_noise=0.01, seed=seed)
        rs = ransac(points_a, uv_a, points_b, uv_b, seed=seed)
        ref = refine_sim3(
            rs.T_dst_src, rs.scale, points_b, uv_b, K, points_a, uv_a, K, active=rs.inliers
        )
        assert ref.rms_px < ref.initial_rms_px
        before.append(errors(rs.T_dst_src, rs.scale, 0.3))
        after.append(errors(ref.T_dst_src, ref.scale, 0.3))
    before, after = np.mean(before, axis=0), np.mean(after, axis=0)
    assert after[0] < 0.8 * before[0] and after[1] < 0.8 * before[1], (before, after)
    assert after[2] < 0.01


def test_refinement_converges_from_a_perturbed_start():
    points_a, uv_a, points_b, uv_b, is_inlier = make_pair(2.5, outlier_frac=0.0)
    T0 = T_A_B.copy()
    T0[:3, :3] = Rotation.from_rotvec(np.radians([2.0, -1.0, 1.5])).as_matrix() @ T0[:3, :3]
    T0[:3, 3] += [0.05, -0.03, 0.04]
    ref = refine_sim3(T0, 2.5 * 1.05, points_b, uv_b, K, points_a, uv_a, K)
    rot, trans, scale_err = errors(ref.T_dst_src, ref.scale, 2.5)
    assert rot < 0.2 and trans < 0.01 and scale_err < 0.01, (rot, trans, scale_err)
    assert ref.n_inliers >= 0.9 * len(points_a)
    assert ref.rms_px < 0.2 * ref.initial_rms_px


def test_covariance_matches_the_actual_errors():
    # Normalised estimation error squared over 7 parameters: 7 on average if the covariance is
    # right; a covariance off by 2x in sigma would give ~28 or ~2.
    nees = []
    for seed in range(8):
        points_a, uv_a, points_b, uv_b, _ = make_pair(0.3, seed=seed)
        res = estimate_sim3(points_a, uv_a, K, points_b, uv_b, K, Sim3Config(seed=seed))
        e = np.r_[
            Rotation.from_matrix(res.T_a_b[:3, :3] @ R_A_B.T).as_rotvec(),
            res.T_a_b[:3, 3] - T_A_B[:3, 3],
            np.log(res.scale / 0.3),
        ]
        nees.append(e @ np.linalg.solve(res.covariance, e))
        assert res.sigma_rot_deg < 0.2 and res.sigma_scale_rel < 0.01 and res.sigma_trans < 0.01
    assert 3.5 < np.mean(nees) < 10.5, nees


def test_ransac_3d_gate_relative_to_depth():
    points_a, _, points_b, _, is_inlier = make_pair(2.5)
    rs = ransac_sim3(points_b, points_a, relative_threshold=0.05)
    rot, trans, scale_err = errors(rs.T_dst_src, rs.scale, 2.5)
    assert rot < 1.0 and trans < 0.05 and scale_err < 0.02, (rot, trans, scale_err)
    assert (rs.inliers & ~is_inlier).sum() <= 2
    assert rs.n_inliers >= 0.9 * is_inlier.sum()


# --- rigid case -----------------------------------------------------------------------------------
def test_scale_one_reduces_to_rigid_umeyama():
    points_a, uv_a, points_b, uv_b, _ = make_pair(
        1.0, outlier_frac=0.0, px_noise=0.0, depth_noise=0
    )
    T_rigid, _ = umeyama(points_b, points_a)
    for fix_scale in (False, True):
        rs = ransac(points_a, uv_a, points_b, uv_b, fix_scale=fix_scale)
        assert rs.n_inliers == len(points_a)
        np.testing.assert_allclose(rs.T_dst_src, T_rigid, atol=1e-9)
        assert abs(rs.scale - 1.0) < 1e-9
    # with noise, free scale stays near 1 and agrees with the rigid fit; fixed scale is exactly 1
    points_a, uv_a, points_b, uv_b, _ = make_pair(1.0, outlier_frac=0.0)
    T_rigid, _ = umeyama(points_b, points_a)
    for fix_scale in (False, True):
        rs = ransac(points_a, uv_a, points_b, uv_b, fix_scale=fix_scale)
        ref = refine_sim3(
            rs.T_dst_src, rs.scale, points_b, uv_b, K, points_a, uv_a, K, fix_scale=fix_scale
        )
        assert rotation_angle_deg(ref.T_dst_src[:3, :3].T @ T_rigid[:3, :3]) < 0.1
        assert np.linalg.norm(ref.T_dst_src[:3, 3] - T_rigid[:3, 3]) < 0.01
        assert abs(ref.scale - 1.0) < (1e-12 if fix_scale else 0.005)
        assert (ref.covariance[6, 6] == 0.0) == fix_scale


# --- degenerate and invalid input -----------------------------------------------------------------
def test_collinear_points_give_no_hypothesis_and_a_rejection():
    points_a = np.c_[np.linspace(-1, 1, 50), np.linspace(-0.5, 0.5, 50), np.full(50, 4.0)]
    points_b = sim3_transform_points(*sim3_inverse(T_A_B, 0.5), points_a)
    uv_a, uv_b = project(points_a, K), project(points_b, K)
    rs = ransac(points_a, uv_a, points_b, uv_b)
    assert rs.T_dst_src is None and rs.n_inliers == 0 and np.isnan(rs.scale)
    res = estimate_sim3(points_a, uv_a, K, points_b, uv_b, K)
    assert not res.accepted and "collinear" in res.reason and res.T_a_b is None


def test_points_clustered_within_the_noise_give_no_hypothesis():
    # 50 points within 2 cm at 4 m: the 3 px gate there is ~2.4 cm, so no triple fixes a rotation
    rng = np.random.default_rng(2)
    points_a = np.array([0.1, -0.2, 4.0]) + rng.uniform(-0.01, 0.01, (50, 3))
    points_b = sim3_transform_points(*sim3_inverse(T_A_B, 0.5), points_a)
    uv_a, uv_b = project(points_a, K), project(points_b, K)
    assert ransac(points_a, uv_a, points_b, uv_b).T_dst_src is None
    res = estimate_sim3(points_a, uv_a, K, points_b, uv_b, K)
    assert not res.accepted and "too close together" in res.reason


def test_random_matches_are_rejected():
    points_a, uv_a, points_b, uv_b, _ = make_pair(0.3, outlier_frac=0.0, seed=3)
    perm = np.random.default_rng(0).permutation(len(points_b))
    res = estimate_sim3(points_a, uv_a, K, points_b[perm], uv_b[perm], K)
    assert not res.accepted, res.reason


def test_fewer_than_three_points():
    points_a, uv_a, points_b, uv_b, _ = make_pair(0.3, outlier_frac=0.0)
    with pytest.raises(Sim3Error, match="at least 3"):
        ransac(points_a[:2], uv_a[:2], points_b[:2], uv_b[:2])
    with pytest.raises(Sim3Error, match="at least 3"):
        refine_sim3(T_A_B, 0.3, points_b[:2], uv_b[:2], K, points_a[:2], uv_a[:2], K)
    res = estimate_sim3(points_a[:2], uv_a[:2], K, points_b[:2], uv_b[:2], K)
    assert not res.accepted and "too few correspondences" in res.reason


def test_invalid_input_raises_sim3_error():
    points_a, uv_a, points_b, uv_b, _ = make_pair(0.3, n=30, outlier_frac=0.0)
    assert issubclass(Sim3Error, RegistrationError) and issubclass(Sim3Error, CoopSlamError)
    bad_nan = points_a.copy()
    bad_nan[3, 1] = np.nan
    behind = points_a.copy()
    behind[5, 2] = -1.0
    cases = [
        ((points_a[:, :2], uv_a, K, points_b, uv_b, K), "expected \\(N, 3\\)"),
        ((points_a, uv_a, K, points_b[:-1], uv_b, K), "rows"),
        ((bad_nan, uv_a, K, points_b, uv_b, K), "NaN"),
        ((behind, uv_a, K, points_b, uv_b, K), "z <= 0"),
        ((points_a, uv_a[:-1], K, points_b, uv_b, K), "one pixel per point"),
        ((points_a, uv_a, K[:2], points_b, uv_b, K), "3x3"),
    ]
    for args, message in cases:
        with pytest.raises(Sim3Error, match=message):
            estimate_sim3(*args)
    with pytest.raises(Sim3Error, match="sigma_a_px"):
        estimate_sim3(points_a, uv_a, K, points_b, uv_b, K, sigma_a_px=np.ones(3))
    with pytest.raises(Sim3Error, match="all four"):
        ransac_sim3(points_b, points_a, uv_src_px=uv_b, K_src=K)
    with pytest.raises(Sim3Error, match="rotation"):
        refine_sim3(2 * T_A_B, 0.3, points_b, uv_b, K, points_a, uv_a, K)
    with pytest.raises(Sim3Error, match="scale"):
        refine_sim3(T_A_B, -1.0, points_b, uv_b, K, points_a, uv_a, K)


def test_config_validation():
    Sim3Config().validate()
    with pytest.raises(ConfigError, match="chi2_threshold"):
        Sim3Config(chi2_threshold=0.0).validate()
    with pytest.raises(ConfigError, match="accept_min_inliers"):
        Sim3Config(accept_min_inliers=2).validate()
    with pytest.raises(ConfigError, match="unknown config key"):
        load_config(Sim3Config, {"chi2": 5.99})
    assert load_config(Sim3Config, {"fix_scale": True}).fix_scale


# --- determinism and helpers ----------------------------------------------------------------------
def test_deterministic_with_a_seed():
    points_a, uv_a, points_b, uv_b, _ = make_pair(2.5, outlier_frac=0.6, seed=4)
    cfg = Sim3Config(seed=7, accept_min_inlier_ratio=0.1)
    first = estimate_sim3(points_a, uv_a, K, points_b, uv_b, K, cfg)
    second = estimate_sim3(points_a, uv_a, K, points_b, uv_b, K, cfg)
    assert first.accepted, first.reason
    np.testing.assert_array_equal(first.T_a_b, second.T_a_b)
    np.testing.assert_array_equal(first.inliers, second.inliers)
    assert first.scale == second.scale and first.ransac_iterations == second.ransac_iterations
    rs = [ransac(points_a, uv_a, points_b, uv_b, seed=7, batch_size=16) for _ in range(2)]
    np.testing.assert_array_equal(rs[0].T_dst_src, rs[1].T_dst_src)
    assert rs[0].n_iterations == rs[1].n_iterations


def test_sim3_helpers_and_gtsam_convention():
    points_b = np.random.default_rng(1).normal(size=(5, 3))
    points_a = sim3_transform_points(T_A_B, 2.5, points_b)
    np.testing.assert_allclose(
        points_a, points_b @ sim3_matrix(T_A_B, 2.5)[:3, :3].T + T_A_B[:3, 3]
    )
    np.testing.assert_allclose(sim3_transform_points(*sim3_inverse(T_A_B, 2.5), points_a), points_b)
    # GTSAM's Similarity3(R, t, s) maps p -> s (R p + t): ours is Similarity3(R, t / s, s)
    S = gtsam.Similarity3(gtsam.Rot3(R_A_B), T_A_B[:3, 3] / 2.5, 2.5)
    np.testing.assert_allclose(S.transformFrom(points_b[0]), points_a[0], atol=1e-12)
