"""Map agreement without ground truth: point-to-plane gaps between two robots' maps where they
overlap (inter) and of each robot's map with itself where it revisits (intra), on a synthetic room
of planes seen through noisy depth, and the overlap picture."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_slam.errors import CoopSlamError
from coop_slam.evaluation.agreement import (
    AgreementConfig,
    AgreementError,
    KeyframeCloud,
    overlap_agreement,
    self_agreement,
    team_agreement,
)
from coop_slam.evaluation.overlap_view import guess_up_axis, parse_up_axis, plot_overlap
from coop_slam.geometry import se3
from helpers import looking_out_pose, room_hit_distance

NOISE_M = 0.005


def room_keyframes(centre, seed, t0_s=0.0, n=60, period_s=0.5, laps=1.5, rays=2500):
    """A robot circling (radius 0.6 m, camera 1.2 m high looking outwards) ``laps`` times: n
    keyframes of ``rays`` depth pixels each, with NOISE_M noise per coordinate. 1.5 laps: the last
    third of the run revisits the first."""
    rng = np.random.default_rng(seed)
    f, width, height = 525.0, 640, 480
    keyframes = []
    for k in range(n):
        angle = 2 * np.pi * laps * k / n
        T_group_cam = looking_out_pose(
            angle + 0.3, (centre[0] + 0.6 * np.cos(angle), centre[1] + 0.6 * np.sin(angle))
        )
        uv = rng.uniform([0, 0], [width, height], (rays, 2))
        rays_cam = np.column_stack(
            [(uv[:, 0] - (width - 1) / 2) / f, (uv[:, 1] - (height - 1) / 2) / f, np.ones(rays)]
        )
        depth = room_hit_distance(T_group_cam[:3, 3], rays_cam @ T_group_cam[:3, :3].T)  # z = 1
        points_cam = rays_cam * depth[:, None] + rng.normal(0, NOISE_M, (rays, 3))
        keyframes.append(KeyframeCloud(t0_s + k * period_s, T_group_cam, points_cam))
    return keyframes


def _moved(keyframes, T_new_group):
    """The same map placed differently in the group frame (a wrong stitch)."""
    return [
        KeyframeCloud(kf.stamp_s, T_new_group @ kf.T_group_cam, kf.points_cam) for kf in keyframes
    ]


def _yaw_about(deg, pivot):
    R = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    return se3(R, np.asarray(pivot) - R @ np.asarray(pivot))


@pytest.fixture(scope="module")
def room():
    """Two robots in one room, circling side by side: they see the same walls."""
    return {1: room_keyframes((1.8, 2.0), seed=1), 2: room_keyframes((3.2, 2.0), seed=2, t0_s=0.2)}


@pytest.fixture(scope="module")
def aligned(room):
    (pair,) = overlap_agreement(room)
    return pair


def test_aligned_maps_agree_as_well_as_each_robot_with_itself(aligned):
    assert aligned["robots"] == [1, 2]
    # Both are noise only: ~0.8 x the 5 mm per-point noise, and alike.
    assert 0.6 * NOISE_M < aligned["intra_m"] < 1.2 * NOISE_M
    assert abs(aligned["inter_m"] / aligned["intra_m"] - 1) < 0.2
    assert aligned["inter_points"] > 2000 and aligned["intra_points"] > 2000


@pytest.mark.parametrize(
    "T_wrong_group",
    [
        _yaw_about(2.0, [5.2, 2.0, 1.2]),  # 2 deg yaw about a point 2 m from robot 2's circle
        # 3 cm along x moves only the x walls (fewer than half of the overlap's points): the
        # median would barely move (3.4 -> 6.5 mm), the trimmed RMS does (4 -> 16 mm).
        se3(t=[0.03, 0.0, 0.0]),
    ],
    ids=["yaw_2deg", "shift_3cm_x"],
)
def test_a_misaligned_stitch_shows_as_a_larger_inter_gap(room, aligned, T_wrong_group):
    (pair,) = overlap_agreement({1: room[1], 2: _moved(room[2], T_wrong_group)})
    assert pair["inter_m"] > 2 * aligned["inter_m"]
    assert pair["inter_m"] > 2 * pair["intra_m"]
    # Each robot's own map is untouched by a wrong stitch.
    assert pair["intra_m"] == pytest.approx(aligned["intra_m"], rel=0.1)


def _wall(offset_m, clutter: bool, seed: int, n=20000):
    """One keyframe (identity camera) of a noise-free 1 x 1 m wall x = 0, moved by ``offset_m``;
    with ``clutter``, a 1 m cube densely filled with random points (a bush) half a metre away."""
    rng = np.random.default_rng(seed)
    points = [np.column_stack([np.zeros(n), rng.uniform(0, 1, (n, 2))])]
    if clutter:
        points.append(rng.uniform([0.5, 0.0, 0.0], [1.5, 1.0, 1.0], (100000, 3)))
    return [KeyframeCloud(0.0, se3(t=offset_m), np.vstack(points))]


def test_gap_is_point_to_plane_on_planar_surfaces_only():
    def inter(offset_m, clutter=False):
        (pair,) = overlap_agreement(
            {1: _wall([0, 0, 0], clutter, 1), 2: _wall(offset_m, clutter, 2)}
        )
        return pair

    # 2 cm across the wall reads 2 cm: distance to the other's plane, not to its nearest point.
    assert inter([0.02, 0, 0])["inter_m"] == pytest.approx(0.02, abs=1e-6)
    # Sliding along the wall cannot be seen (the metric's known blind spot).
    assert inter([0, 0.03, 0.01])["inter_m"] < 1e-6
    # Clutter has no planes: it stays out of the figure (but for the odd patch of the bush's outer
    # faces, which a half-empty ball can make look flat); with it, ~10000 distances of ~1 cm.
    cluttered = inter([0.02, 0, 0], clutter=True)
    assert cluttered["inter_m"] == pytest.approx(0.02, rel=0.1)
    assert 400 < cluttered["inter_points"] < 1000  # the wall's ~570 of the 2 x 5000 queries


def test_maps_that_do_not_overlap_have_no_inter_figure(room):
    result = team_agreement({1: room[1], 2: _moved(room[2], se3(t=[20.0, 0.0, 0.0]))})
    (pair,) = result.pairs
    assert pair["inter_m"] is None and pair["inter_points"] == 0
    assert pair["intra_m"] is not None  # each robot still revisits its own room
    assert set(result.self_m) == {1, 2} and all(v is not None for v in result.self_m.values())


def test_self_agreement_sees_drift_at_revisits_but_never_compares_temporal_neighbours(room):
    clean = self_agreement(room[1])
    # The second half of the run drifted 3 cm: where it revisits the first half, walls double.
    drift = se3(t=0.03 * np.array([1.0, 1.0, 0.0]) / np.sqrt(2))
    drifted = [
        KeyframeCloud(kf.stamp_s, drift @ kf.T_group_cam, kf.points_cam) if kf.stamp_s > 15 else kf
        for kf in room[1]
    ]
    assert self_agreement(drifted) > 2 * clean
    # A 2.5 s run never revisits: consecutive keyframes overlap, but they are temporal neighbours.
    short = room[1][:6]
    assert self_agreement(short) is None
    assert self_agreement(short, AgreementConfig(min_revisit_s=0.0)) is not None


def test_results_are_deterministic_and_take_tuples_and_missing_depth(room):
    first = overlap_agreement(room)
    assert overlap_agreement({2: room[2], 1: room[1]}) == first
    # (stamp, T, points) tuples, with NaN rows where a keypoint had no depth: same figures.
    nan_rows = np.full((5, 3), np.nan)
    as_tuples = {
        rid: [(kf.stamp_s, kf.T_group_cam, np.vstack([kf.points_cam, nan_rows])) for kf in kfs]
        for rid, kfs in room.items()
    }
    assert overlap_agreement(as_tuples) == first


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(radius_m=0.0), "radius_m"),
        (dict(voxel_m=0.04), "voxel_m"),
        (dict(min_neighbours=2), "min_neighbours"),
        (dict(min_revisit_s=-1.0), "min_revisit_s"),
        (dict(min_points=0), "min_points"),
        (dict(max_planarity=1.5), "max_planarity"),
        (dict(max_queries=10), "max_queries"),
        (dict(trim_fraction=0.8), "trim_fraction"),
        (dict(radius_m="5 cm"), "radius_m must be a number"),
    ],
)
def test_bad_config_is_refused_naming_the_field(changes, message):
    with pytest.raises(AgreementError, match=message):
        AgreementConfig(**changes).validate()
    with pytest.raises(AgreementError, match=message):
        overlap_agreement({}, AgreementConfig(**changes))
    assert issubclass(AgreementError, CoopSlamError)
    assert AgreementConfig().validate() == AgreementConfig()


def test_bad_keyframes_are_refused_naming_robot_and_keyframe():
    good = (1.0, np.eye(4), np.zeros((10, 3)))
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    cases = [
        (
            (1.0, np.eye(4), np.zeros((10, 2))),
            r"robot 2, keyframe 1: points_cam has shape \(10, 2\)",
        ),
        ((1.0, nan_pose, np.zeros((10, 3))), "robot 2, keyframe 1: T_group_cam contains NaN"),
        ((1.0, np.eye(4)[:3], np.zeros((10, 3))), r"T_group_cam has shape \(3, 4\)"),
        ((1.0, 2 * np.eye(4), np.zeros((10, 3))), "not orthonormal"),
        ((float("nan"), np.eye(4), np.zeros((10, 3))), "stamp_s is nan"),
        ((1.0, np.eye(4)), "expected a KeyframeCloud"),
    ]
    for bad, message in cases:
        with pytest.raises(AgreementError, match=message):
            overlap_agreement({1: [good], 2: [good, bad]})
    with pytest.raises(AgreementError, match="dict robot id"):
        overlap_agreement([[good]])
    with pytest.raises(AgreementError, match="robot ids must be integers"):
        overlap_agreement({"robot_1": [good]})


def test_up_axis_is_parsed_or_guessed_from_the_cameras():
    assert parse_up_axis("-y") == (1, -1.0) and parse_up_axis("z") == (2, 1.0)
    with pytest.raises(AgreementError, match="up_axis"):
        parse_up_axis("up")
    # Camera-optical map frame (y down): cameras spread over x and z, hardly in y.
    positions = np.column_stack([np.linspace(0, 3, 20), np.full(20, -0.02), np.linspace(0, 2, 20)])
    assert guess_up_axis(positions) == (1, -1.0)


def test_overlap_picture_is_written(room, aligned, tmp_path):
    path = plot_overlap(
        str(tmp_path / "overlap.png"), room, pairs=[aligned], max_points_per_robot=5000
    )
    with open(path, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
