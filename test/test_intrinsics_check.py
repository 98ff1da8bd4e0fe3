"""Colour focal-length check against ground-truth motion (coop_slam.vo.intrinsics_check) and the
ground-truth check's reference estimator."""

import os

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import helpers_vo
from coop_slam.geometry import se3
from coop_slam.vo.intrinsics_check import (
    FramePair,
    IntrinsicsCheckError,
    check_focal,
    match_pairs,
    sampson_errors,
)
from helpers import REDKITCHEN

CAM = helpers_vo.CAMERA  # the renderer's true intrinsics (fx = fy = 525 px)


@pytest.fixture(scope="module")
def panning_pairs():
    """Matched frame pairs of a camera panning 20 deg while moving sideways in the room."""
    planes = helpers_vo.room(np.random.default_rng(5))
    poses = np.array(
        [
            se3(
                Rotation.from_euler("yx", [0.9 * i, 0.2 * i], degrees=True).as_matrix(),
                [0.02 * i, 0.0, 0.01 * i],
            )
            for i in range(24)
        ]
    )
    grays = {}

    def load_gray(i):
        if i not in grays:
            grays[i] = cv2.cvtColor(helpers_vo.render(planes, poses[i])[0], cv2.COLOR_BGR2GRAY)
        return grays[i]

    return match_pairs(load_gray, poses, gap=6, min_rotation_deg=2.0, max_pairs=8)


def test_true_focal_length_fits_best(panning_pairs):
    res = check_focal(panning_pairs, CAM.fx, CAM.fy, CAM.cx, CAM.cy)
    assert res.pairs >= 5 and res.matches > 500
    assert res.best_focal_px == pytest.approx(CAM.fx, rel=0.02)
    assert res.best_error_px <= res.model_error_px + 1e-9


def test_a_model_with_the_depth_cameras_focal_length_is_found_out(panning_pairs):
    # 7-Scenes gives the depth camera's 585 px for colour images taken at ~525 px.
    res = check_focal(panning_pairs, 585.0, 585.0, CAM.cx, CAM.cy)
    assert res.best_focal_px == pytest.approx(CAM.fx, rel=0.02)
    assert res.ratio == pytest.approx(CAM.fx / 585.0, rel=0.02)
    assert res.model_error_px > 1.2 * res.best_error_px


def test_sampson_error_is_zero_for_exact_correspondences():
    K = CAM.K
    rng = np.random.default_rng(0)
    pts_a = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 4, 50)]
    T_b_a = se3(Rotation.from_euler("y", 5, degrees=True).as_matrix(), [0.1, 0.0, 0.02])
    pts_b = pts_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    uv = lambda p: (p[:, :2] / p[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]  # noqa: E731
    pair = FramePair(uv(pts_a), uv(pts_b), T_b_a)
    assert np.max(sampson_errors(pair, K)) < 1e-6
    moved = FramePair(uv(pts_a), uv(pts_b) + [0.0, 3.0], T_b_a)
    assert np.median(sampson_errors(moved, K)) > 0.5


def test_motion_without_rotation_is_refused():
    poses = np.array([se3(np.eye(3), [0.01 * i, 0.0, 0.0]) for i in range(20)])
    with pytest.raises(IntrinsicsCheckError, match="cannot be told"):
        match_pairs(lambda i: np.zeros((48, 64), np.uint8), poses, gap=5)


def test_command_refuses_a_missing_dataset(tmp_path, capsys):
    from coop_slam.tools.check_intrinsics import main

    assert main(["--dataset", str(tmp_path / "nothing")]) == 2
    assert "ERROR" in capsys.readouterr().err


@pytest.mark.skipif(
    not os.path.isdir(REDKITCHEN), reason=f"RedKitchen data not found at {REDKITCHEN}"
)
def test_command_finds_redkitchens_colour_focal_length(capsys):
    # camera.yaml gives the depth camera's 585 px; the colour images fit ~520 px.
    from coop_slam.tools.check_intrinsics import main

    assert main(["--dataset", REDKITCHEN, "--pairs", "30"]) == 0
    out = capsys.readouterr().out
    best = float(out.split("best fx ")[1].split(" px")[0])
    assert 500 < best < 540
    assert "do not fit" in out


def test_depth_icp_odometry_follows_a_rendered_room():
    """The reference estimator of scripts/check_ground_truth (OpenCV's depth-only ICP)."""
    from coop_slam.geometry import transform_error
    from coop_slam.tools.check_ground_truth import depth_icp_odometry

    _, frames, gt = helpers_vo.sequence(n_frames=15, step_m=0.02)

    class Seq:  # the slice of datasets.base.Sequence the estimator reads
        camera = CAM
        frames = list(range(15))

        def __len__(self):
            return 15

        def frame_poses(self):
            return gt

        def load_depth_m(self, i):
            return frames[i][1]

    poses = depth_icp_odometry(Seq())
    assert np.isfinite(poses).all()
    trans_m, rot_deg = transform_error(poses[-1], gt[-1])  # 24 cm, 4 deg from the start
    assert trans_m < 0.02 and rot_deg < 1.0


def test_ground_truth_check_refuses_a_missing_dataset(tmp_path, capsys):
    from coop_slam.tools.check_ground_truth import main

    assert main(["--dataset", str(tmp_path / "nothing")]) == 2
    assert "nothing" in capsys.readouterr().err
