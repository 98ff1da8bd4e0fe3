"""Tests of the monocular two-view initialization (coop_slam.vo.initialization).

Synthetic ground truth: points in the reference camera frame, a known T_cur_ref, projections with
Gaussian pixel noise and a share of random (outlier) matches; and, as the acceptance test, two views
of the synthetic world rendered and matched with ORB features.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_slam.camera import CameraModel
from coop_slam.config import ConfigError, load_config
from coop_slam.errors import CoopSlamError
from coop_slam.geometry import invert, rotation_angle_deg, se3
from coop_slam.vo.initialization import (
    MODEL_ESSENTIAL,
    MODEL_HOMOGRAPHY,
    REASON_AMBIGUOUS,
    REASON_PARALLAX,
    MonoInitConfig,
    MonoInitError,
    initialize_two_view,
    match_for_initialization,
    scale_to_median_depth,
)

CAMERA = CameraModel(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
K = CAMERA.K


def motion(baseline_m: float, yaw_deg: float = 5.0, direction=(1.0, 0.1, 0.2)) -> np.ndarray:
    """T_cur_ref of a camera that moved ``baseline_m`` along ``direction`` (reference frame) and
    turned ``yaw_deg`` about an axis close to its y (down) axis."""
    axis = np.array([0.1, 1.0, 0.05]) / np.linalg.norm([0.1, 1.0, 0.05])
    R_ref_cur = Rotation.from_rotvec(np.radians(yaw_deg) * axis).as_matrix()
    centre = baseline_m * np.asarray(direction, float) / np.linalg.norm(direction)
    return invert(se3(R_ref_cur, centre))


def project(points_cam: np.ndarray) -> np.ndarray:
    return points_cam[:, :2] / points_cam[:, 2:] * [CAMERA.fx, CAMERA.fy] + [CAMERA.cx, CAMERA.cy]


def synthetic_matches(
    T_cur_ref: np.ndarray,
    planar: bool,
    n: int = 400,
    noise_px: float = 0.5,
    outlier_share: float = 0.1,
    far_share: float = 0.0,
    seed: int = 0,
):
    """(uv_ref, uv_cur, points_ref, is_outlier): ``n`` points seen by both cameras.

    General scene: depths uniform in 2-6 m over the whole reference image, but ``far_share`` of the
    points at 40-80 m. Planar scene: a wall 4 m ahead, turned 30 deg about the vertical. The first
    ``outlier_share`` of the matches get a random current position.
    """
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (8 * n, 2))
    rays = np.column_stack([(uv - K[:2, 2]) / [CAMERA.fx, CAMERA.fy], np.ones(len(uv))])
    if planar:
        normal = Rotation.from_euler("y", -30, degrees=True).apply([0.0, 0.0, 1.0])
        depth = 4.0 * normal[2] / (rays @ normal)  # n . (z ray) = n . (0, 0, 4)
    else:
        depth = rng.uniform(2.0, 6.0, len(uv))
        far = rng.random(len(uv)) < far_share
        depth[far] = rng.uniform(40.0, 80.0, far.sum())
    points_ref = rays * depth[:, None]
    points_cur = points_ref @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
    uv_cur = project(points_cur)
    visible = (points_cur[:, 2] > 0.1) & np.all(
        (uv_cur >= 0) & (uv_cur < [CAMERA.width, CAMERA.height]), axis=1
    )
    idx = np.flatnonzero(visible)[:n]
    assert len(idx) == n
    points_ref = points_ref[idx]
    uv_ref = uv[idx] + rng.normal(0.0, noise_px, (n, 2))
    uv_cur = uv_cur[idx] + rng.normal(0.0, noise_px, (n, 2))
    n_out = int(round(outlier_share * n))
    uv_cur[:n_out] = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (n_out, 2))
    return uv_ref, uv_cur, points_ref, np.arange(n) < n_out


def pose_errors_deg(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error, translation direction error) in degrees."""
    rot = rotation_angle_deg(T_est[:3, :3].T @ T_true[:3, :3])
    t_est = T_est[:3, 3] / np.linalg.norm(T_est[:3, 3])
    t_true = T_true[:3, 3] / np.linalg.norm(T_true[:3, 3])
    return rot, float(np.degrees(np.arccos(np.clip(t_est @ t_true, -1.0, 1.0))))


def median_point_error(result, points_true_ref: np.ndarray) -> float:
    """Median distance of the triangulated points to the truth, both scaled to median depth 1,
    relative to the true point's distance from the reference camera."""
    scaled = scale_to_median_depth(result)
    truth = points_true_ref[scaled.match_index]
    truth = truth / np.median(truth[:, 2])
    return float(
        np.median(np.linalg.norm(scaled.points_ref - truth, axis=1) / np.linalg.norm(truth, axis=1))
    )


# --- synthetic matches ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "planar, model", [(False, MODEL_ESSENTIAL), (True, MODEL_HOMOGRAPHY)], ids=["3d", "planar"]
)
def test_two_view_recovers_motion_and_structure(planar, model):
    T_cur_ref = motion(0.3)
    uv_ref, uv_cur, points_ref, outlier = synthetic_matches(T_cur_ref, planar)
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert result.success, result.reason
    assert result.model == model
    rot_deg, trans_deg = pose_errors_deg(result.T_cur_ref, T_cur_ref)
    assert rot_deg < 0.5
    assert trans_deg < 2.0
    assert abs(np.linalg.norm(result.T_cur_ref[:3, 3]) - 1.0) < 1e-9  # no metric scale
    # Points from nearly all true matches, hardly any outlier (one that falls within the gates of
    # the epipolar line cannot be told from a true match), and right up to the scale.
    assert outlier[result.match_index].sum() <= 0.01 * result.n_points
    assert result.n_points >= 0.9 * (~outlier).sum()
    assert median_point_error(result, points_ref) < 0.02
    assert np.all(result.parallax_deg >= MonoInitConfig().min_point_parallax_deg)


def test_far_points_are_not_mapped():
    # A fifth of the points 40-80 m away: seen under less than 0.5 deg of parallax, their depth is
    # noise. They fit the motion, so initialization succeeds, but they do not enter the map.
    T_cur_ref = motion(0.3)
    uv_ref, uv_cur, points_ref, outlier = synthetic_matches(T_cur_ref, False, far_share=0.2)
    far = points_ref[:, 2] > 30.0
    assert 0.15 < far.mean() < 0.25
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert result.success, result.reason
    rot_deg, trans_deg = pose_errors_deg(result.T_cur_ref, T_cur_ref)
    assert rot_deg < 0.5 and trans_deg < 2.0
    assert np.all(result.parallax_deg >= 1.0)
    assert not far[result.match_index].any()
    assert result.n_points >= 0.9 * (~outlier & ~far).sum()


@pytest.mark.parametrize("planar", [False, True], ids=["3d", "planar"])
def test_model_selection_follows_the_score_ratio(planar):
    # R_H = S_H / (S_H + S_F) against the threshold decides, as in ORB-SLAM: a 3D scene scores far
    # below 0.45, a plane just above (S_F gates the 1-dof epipolar distance, so it scores a little
    # more than S_H on the same matches). Moving the threshold across R_H flips the model.
    uv_ref, uv_cur, _, _ = synthetic_matches(motion(0.3), planar)
    result = initialize_two_view(uv_ref, uv_cur, K)
    if planar:
        assert result.model == MODEL_HOMOGRAPHY and 0.45 < result.ratio_h < 0.5
    else:
        assert result.model == MODEL_ESSENTIAL and 0.0 < result.ratio_h < 0.3
    flipped = initialize_two_view(
        uv_ref, uv_cur, K, MonoInitConfig(h_ratio_threshold=0.99 if planar else 0.01)
    )
    assert flipped.ratio_h == pytest.approx(result.ratio_h)
    assert flipped.model == (MODEL_ESSENTIAL if planar else MODEL_HOMOGRAPHY)


def test_scale_to_median_depth():
    T_cur_ref = motion(0.3)
    uv_ref, uv_cur, points_ref, _ = synthetic_matches(T_cur_ref, planar=False)
    result = initialize_two_view(uv_ref, uv_cur, K)
    scaled = scale_to_median_depth(result)
    assert np.median(scaled.points_ref[:, 2]) == pytest.approx(1.0)
    # Pose and points scale together: the true baseline over the true median depth.
    truth = points_ref[result.match_index]
    expected = 0.3 / np.median(truth[:, 2])
    assert np.linalg.norm(scaled.T_cur_ref[:3, 3]) == pytest.approx(expected, rel=0.03)
    np.testing.assert_allclose(scaled.T_cur_ref[:3, :3], result.T_cur_ref[:3, :3])
    assert scaled.scale == pytest.approx(1.0 / np.median(result.points_ref[:, 2]))
    rejected = initialize_two_view(uv_ref[:50], uv_cur[:50], K)
    with pytest.raises(MonoInitError, match="successful"):
        scale_to_median_depth(rejected)


@pytest.mark.parametrize(
    "baseline_m, planar", [(0.0, False), (0.01, False), (0.0, True), (0.01, True)]
)
def test_too_little_parallax_is_rejected(baseline_m, planar):
    # Pure rotation (baseline 0) or 1 cm at 2-6 m: rays meet at well under 1 deg.
    uv_ref, uv_cur, _, _ = synthetic_matches(motion(baseline_m), planar)
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert not result.success
    assert result.reason.startswith(REASON_PARALLAX), result.reason
    assert result.median_parallax_deg < 1.0
    assert result.T_cur_ref is None and result.n_points == 0


def test_exact_pure_rotation_is_rejected():
    # Noise-free rotation: the homography decomposes with t = 0, no motion to triangulate with.
    uv_ref, uv_cur, _, _ = synthetic_matches(motion(0.0), False, noise_px=0.0, outlier_share=0.0)
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert not result.success and result.reason.startswith(REASON_PARALLAX), result.reason


def test_planar_twofold_ambiguity_is_rejected():
    # Moving towards the wall, the homography's second decomposition (normal and translation
    # roughly swapped) also puts nearly every point in front of both cameras: two views cannot
    # tell them apart, so no winner is clear and initialization waits (as ORB-SLAM's).
    uv_ref, uv_cur, _, _ = synthetic_matches(motion(0.3, direction=(0.5, 0.0, 1.0)), planar=True)
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert not result.success
    assert result.reason.startswith(REASON_AMBIGUOUS), result.reason
    assert result.model == MODEL_HOMOGRAPHY
    votes = result.candidate_votes
    assert votes[1] > MonoInitConfig().max_second_share * votes[0]


def test_too_few_matches_are_rejected():
    uv_ref, uv_cur, _, _ = synthetic_matches(motion(0.3), planar=False, n=60)
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert not result.success and "too few matches" in result.reason


def test_random_matches_are_rejected():
    rng = np.random.default_rng(3)
    uv_ref = rng.uniform([0, 0], [640, 480], (300, 2))
    uv_cur = rng.uniform([0, 0], [640, 480], (300, 2))
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert not result.success and result.T_cur_ref is None


# --- bad input ------------------------------------------------------------------------------------
def _good_input():
    uv_ref, uv_cur, _, _ = synthetic_matches(motion(0.3), planar=False, n=120)
    return uv_ref, uv_cur


@pytest.mark.parametrize(
    "case, message",
    [
        ("ref_shape", "uv_ref_px has shape"),
        ("cur_3_columns", "uv_cur_px has shape"),
        ("row_count", "same match"),
        ("nan", "NaN"),
        ("K_shape", "K has shape"),
        ("K_nan", "K contains NaN"),
        ("K_not_pinhole", "not a pinhole matrix"),
        ("text", "numeric"),
    ],
)
def test_bad_input_raises(case, message):
    uv_ref, uv_cur = _good_input()
    K_in = K.copy()
    if case == "ref_shape":
        uv_ref = uv_ref.ravel()
    elif case == "cur_3_columns":
        uv_cur = np.column_stack([uv_cur, np.ones(len(uv_cur))])
    elif case == "row_count":
        uv_cur = uv_cur[:-1]
    elif case == "nan":
        uv_ref[5, 1] = np.nan
    elif case == "K_shape":
        K_in = K[:2]
    elif case == "K_nan":
        K_in[0, 2] = np.nan
    elif case == "K_not_pinhole":
        K_in[0, 0] = -K_in[0, 0]
    elif case == "text":
        uv_ref = [["a", "b"]] * len(uv_cur)
    with pytest.raises(MonoInitError, match=message) as info:
        initialize_two_view(uv_ref, uv_cur, K_in)
    assert isinstance(info.value, CoopSlamError)


def test_config_validation():
    cfg = load_config(MonoInitConfig, {"min_median_parallax_deg": 2, "refine": False})
    assert cfg.min_median_parallax_deg == 2.0 and cfg.refine is False
    with pytest.raises(ConfigError, match="h_ratio_threshold"):
        load_config(MonoInitConfig, {"h_ratio_threshold": 1.5})
    with pytest.raises(ConfigError, match="min_matches"):
        load_config(MonoInitConfig, {"min_matches": 5})
    with pytest.raises(ConfigError, match="unknown config key"):
        load_config(MonoInitConfig, {"min_paralax_deg": 2.0})
    with pytest.raises(ConfigError, match="ransac_h_px"):
        initialize_two_view(*_good_input(), K, MonoInitConfig(ransac_h_px=0.0))


# --- rendered views (acceptance) ----------------------------------------------------------------
@pytest.fixture(scope="module")
def ring_renderer():
    from coop_slam.synthetic.render import NoiseConfig, Renderer
    from coop_slam.synthetic.world import build_world

    cv2.setNumThreads(1)
    return Renderer(build_world("ring", seed=0), CAMERA, NoiseConfig())  # with sensor noise


@pytest.mark.parametrize(
    "base_xy_yaw, model",
    [((2.0, 1.0, 0.0), MODEL_ESSENTIAL), ((6.0, 1.0, -90.0), MODEL_HOMOGRAPHY)],
    ids=["corridor", "wall"],
)
def test_two_view_on_rendered_views(ring_renderer, base_xy_yaw, model):
    """Two rendered views, ORB features, matching and initialization: the issue's acceptance test
    (rotation under 0.5 deg, translation direction under 2 deg)."""
    from coop_slam.synthetic.world import DEFAULT_T_BASE_CAM
    from coop_slam.vo.config import VoConfig
    from coop_slam.vo.features import OrbExtractor

    x, y, yaw = base_xy_yaw
    T_world_ref = se3(Rotation.from_euler("z", yaw, degrees=True).as_matrix(), [x, y, 0.0])
    T_world_ref = T_world_ref @ DEFAULT_T_BASE_CAM
    # The current camera: 0.3 m to the right of the reference one, turned 5 deg to the right.
    T_ref_cur = se3(Rotation.from_euler("y", 5.0, degrees=True).as_matrix(), [0.3, 0.0, 0.0])
    extractor = OrbExtractor(VoConfig(), CAMERA)
    keypoints = []
    for seed, T_world_cam in enumerate((T_world_ref, T_world_ref @ T_ref_cur)):
        bgr, _ = ring_renderer.render(T_world_cam, noise_seed=seed)
        keypoints.append(extractor.extract(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)))
    pairs = match_for_initialization(*keypoints)
    uv_ref = keypoints[0].uv_px[pairs[:, 0]]
    uv_cur = keypoints[1].uv_px[pairs[:, 1]]
    result = initialize_two_view(uv_ref, uv_cur, K)
    assert result.success, result.reason
    assert result.model == model
    rot_deg, trans_deg = pose_errors_deg(result.T_cur_ref, invert(T_ref_cur))
    assert rot_deg < 0.5
    assert trans_deg < 2.0
    assert result.n_points >= 50
