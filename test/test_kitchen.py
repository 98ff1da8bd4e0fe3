"""Tests of the hand-held 'kitchen' scenario: its room, 6-DoF camera motion, overlap events and the
Kinect-like sensor model (depth lattice, holes, registration error, motion blur, exposure gain),
and that the other scenarios' sensor model is unchanged (all new effects off by default)."""

from __future__ import annotations

import dataclasses
import itertools

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import coop_slam.synthetic.generate as generate_mod
from coop_slam.camera import CameraModel
from coop_slam.datasets import read_synthetic
from coop_slam.geometry import se3
from coop_slam.synthetic.overlap import OverlapConfig, compute_overlap
from coop_slam.synthetic.render import (
    NoiseConfig,
    Renderer,
    apply_noise,
    exposure_gains,
    kinect_noise,
    motion_blur,
    projector_shadow,
)
from coop_slam.synthetic.scenarios import SCENARIOS, ScenarioError, make_scenario
from coop_slam.synthetic.world import HAND_HELD_T_BASE_CAM, KITCHEN_SIZE_M, build_world

SMALL_CAMERA = CameraModel(width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
MID_CAMERA = CameraModel(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5)
FAST_OVERLAP = OverlapConfig(rate_hz=2.5, depth_width_px=80)
# Only the effect under test: no Gaussian depth noise, blobs, image noise or blur.
QUIET = dict(
    image_sigma=0.0,
    blur_sigma_px=0.0,
    depth_sigma_base_m=0.0,
    depth_sigma_quad=0.0,
    hole_fraction=0.0,
    depth_min_m=0.0,
    depth_max_m=100.0,
)


@pytest.fixture(scope="module")
def kitchen_world():
    cv2.setNumThreads(1)
    return build_world("kitchen", seed=0)


@pytest.fixture(scope="module")
def scenario():
    return make_scenario("kitchen", seed=0)


def camera_motion(scenario, robot: int, frame: int):
    """(T_world_cam, pose_at) of a robot's frame, as the generator renders it."""
    traj = scenario.trajectories[robot]
    stamp = traj.stamps_s[frame]

    def pose_at(dt_s):
        return traj.poses_at(stamp + np.asarray(dt_s, float)) @ scenario.T_base_cam

    return traj.poses_se3[frame] @ scenario.T_base_cam, pose_at


def fastest_frame(scenario, robot: int = 0) -> int:
    """The frame where the camera turns fastest (strongest motion blur)."""
    R = Rotation.from_matrix(scenario.trajectories[robot].poses_se3[:, :3, :3])
    return int(np.argmax((R[1:] * R[:-1].inv()).magnitude())) + 1


# --- scenario and motion -----------------------------------------------------------------------
def test_kitchen_builds_for_two_and_three_robots():
    spec = SCENARIOS["kitchen"]
    assert spec.hand_held and (spec.min_robots, spec.max_robots) == (2, 3)
    default = make_scenario("kitchen")
    assert len(default.trajectories) == 2 and default.rate_hz == 30.0
    assert default.hand_held and default.layout == "kitchen" and default.noise == kinect_noise()
    assert np.allclose(default.T_base_cam, HAND_HELD_T_BASE_CAM)
    assert len(make_scenario("kitchen", robots=3).trajectories) == 3
    with pytest.raises(ScenarioError):
        make_scenario("kitchen", robots=4)
    # The ground robots keep their rate, sensor and robot bodies.
    team = make_scenario("team")
    assert team.rate_hz == 15.0 and not team.hand_held and team.noise == NoiseConfig()
    assert all(SCENARIOS[n].hand_held == make_scenario(n).hand_held for n in SCENARIOS)


@pytest.mark.parametrize("robots", [2, 3])
def test_kitchen_motion_is_hand_held(robots, kitchen_world):
    scenario = make_scenario("kitchen", seed=1, robots=robots)
    width, depth = KITCHEN_SIZE_M
    positions = []
    for traj in scenario.trajectories:
        poses = traj.poses_se3
        assert np.allclose(traj.stamps_s[0], 1.0) and np.allclose(np.diff(traj.stamps_s), 1 / 30)
        assert np.allclose(traj.poses_at(traj.stamps_s[::50]), poses[::50])  # exact in between
        p = poses[:, :3, 3]
        yaw, pitch, roll = Rotation.from_matrix(poses[:, :3, :3]).as_euler("ZYX", degrees=True).T
        pitch = -pitch  # base_link y points left: looking down is a positive rotation about it
        # 6-DoF: looks down at the counters (-10..-40 deg), rolls a little, height varies.
        assert -41 < pitch.min() < -30 and -20 < pitch.max() < -9
        assert np.abs(roll).max() < 6.0 and roll.std() > 1.5
        assert 1.2 < p[:, 2].min() < 1.4 and 1.5 < p[:, 2].max() < 1.7
        # Inside the room, clear of the furniture; walking at 0.2-0.5 m/s (over half seconds).
        assert (p[:, :2] > 0).all() and (p[:, :2] < [width, depth]).all()
        assert kitchen_world.is_free(p[:, :2], clearance_m=0.3).all(), f"{traj.name} hits things"
        speed = np.linalg.norm(p[15:] - p[:-15], axis=1) * 2.0
        assert 0.2 < speed.mean() < 0.4 and speed.max() < 0.5 and speed.min() > 0.1
        # Turns up to ~60 deg/s, smoothly: velocity changes little from frame to frame.
        R = Rotation.from_matrix(poses[:, :3, :3])
        rate_dps = np.degrees((R[1:] * R[:-1].inv()).magnitude()) * 30
        assert 12 < np.median(rate_dps) < 30 and rate_dps.max() < 65
        assert np.abs(np.diff(rate_dps)).max() < 10  # deg/s per frame: no jumps
        accel = np.linalg.norm(np.diff(p, 2, axis=0), axis=1) * 30**2
        assert accel.max() < 3.0  # m/s^2: hand shake, no jumps
        # Hand shake: the orientation wobbles by up to ~1 deg about its slow path (the 0.3 s mean).
        kernel = np.ones(9) / 9
        smooth_yaw = np.convolve(np.unwrap(np.radians(yaw)), kernel, mode="valid")
        wobble = np.degrees(np.unwrap(np.radians(yaw))[4:-4] - smooth_yaw)
        assert 0.1 < np.abs(wobble).max() < 1.5
        # It comes back to its own earlier views (a lap of the table, ~19 s).
        later = np.arange(len(p)) > 20 * 30
        gaps = np.linalg.norm(p[later, None, :2] - p[None, : 2 * 30, :2], axis=2)
        assert gaps.min() < 0.15
        positions.append(p)
    for a, b in itertools.combinations(positions, 2):
        assert np.linalg.norm(a - b, axis=1).min() > 0.5  # never close to another camera


def test_kitchen_is_deterministic():
    a = make_scenario("kitchen", seed=3, robots=3).trajectories[2].poses_se3
    assert np.array_equal(a, make_scenario("kitchen", seed=3, robots=3).trajectories[2].poses_se3)
    assert not np.allclose(a, make_scenario("kitchen", seed=4, robots=3).trajectories[2].poses_se3)


def test_kitchen_world_is_a_cluttered_room(kitchen_world):
    names = [s.name for s in kitchen_world.surfaces]
    for thing in ("worktop_s", "upper_s", "fridge", "shelf_board", "table_top", "microwave"):
        assert any(thing in n for n in names), thing
    assert kitchen_world.building_size_m == KITCHEN_SIZE_M
    assert len({s.seed for s in kitchen_world.surfaces}) == len(names)  # no repeated texture
    # The ring buildings still use their own footprint.
    assert build_world("ring", 0).building_size_m == (12.0, 8.0)


@pytest.mark.parametrize("robots", [2, 3])
def test_kitchen_overlap_events(robots, kitchen_world):
    """Every camera sees what each other one saw, within a lap: merge latency is measurable."""
    scenario = make_scenario("kitchen", seed=0, robots=robots)
    events = compute_overlap(scenario, kitchen_world, cfg=FAST_OVERLAP)
    assert events.marker_sightings == []  # nobody carries a marker
    for a, b in itertools.permutations(range(1, robots + 1), 2):
        t = events.revisit_time(a, b)
        assert t is not None and t < 20.0, f"robot {b} never sees what robot {a} saw"
        assert events.first_overlap_time(a, b) is not None


# --- sensor model ------------------------------------------------------------------------------
def test_projector_shadow_is_left_of_foreground_objects():
    """A 1 m square in front of a 2 m wall: the projector 7.5 cm to the right cannot light the
    fx b (1/1 - 1/2) pixels of wall left of the square, and nothing else."""
    depth = np.full((120, 160), 2.0, np.float32)
    depth[40:80, 60:100] = 1.0
    shadow = projector_shadow(depth, SMALL_CAMERA, 0.075)
    width = SMALL_CAMERA.fx * 0.075 * (1 / 1.0 - 1 / 2.0)  # 4.9 px
    cols = np.flatnonzero(shadow[60])
    assert cols.min() == 60 - int(width) and cols.max() == 59
    assert not shadow[:40].any() and not shadow[80:].any() and not shadow[:, 60:].any()


def test_depth_is_quantised_on_the_disparity_lattice(kitchen_world, scenario):
    cfg = kinect_noise()
    renderer = Renderer(kitchen_world, SMALL_CAMERA, cfg)
    T_world_cam, pose_at = camera_motion(scenario, 0, 100)
    _, depth = renderer.render(T_world_cam, noise_seed=3, pose_at=pose_at)
    z = depth[depth > 0].astype(float)
    steps = cfg.disparity_fx_px * cfg.disparity_baseline_m / z / cfg.disparity_step_px
    assert np.abs(steps - np.round(steps)).max() < 1e-3
    assert len(np.unique(depth)) < 0.2 * len(z)  # few distinct values
    assert z.min() >= cfg.depth_min_m and z.max() <= cfg.depth_max_m


def test_depth_holes_at_edges_and_grazing_angles(kitchen_world, scenario):
    cfg = NoiseConfig(**QUIET, edge_hole_px=2.0, projector_shadow=True, grazing_start_deg=75.0)
    ideal = Renderer(kitchen_world, MID_CAMERA, NoiseConfig(enabled=False))
    renderer = Renderer(kitchen_world, MID_CAMERA, cfg)
    T_world_cam, _ = camera_motion(scenario, 0, 400)
    _, exact = ideal.render(T_world_cam)
    _, depth = renderer.render(T_world_cam, noise_seed=1)
    holes = depth == 0
    # Depth edges: neighbours more than 3 % apart.
    jump = np.zeros(exact.shape, bool)
    jump[:, 1:] |= np.abs(np.diff(exact, axis=1)) > 0.03 * exact[:, 1:]
    jump[1:, :] |= np.abs(np.diff(exact, axis=0)) > 0.03 * exact[1:, :]
    near_edge = cv2.dilate(jump.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    far = cv2.dilate(jump.astype(np.uint8), np.ones((25, 25), np.uint8)) == 0
    assert jump.sum() > 200  # the view has objects in front of others
    assert holes[jump].mean() > 0.9 and holes[near_edge].mean() > 0.5
    assert holes[far].mean() < 0.1  # away from edges: only grazing surfaces lose depth
    # Where depth is kept it is exact (no noise configured).
    assert np.allclose(depth[~holes], exact[~holes])


def test_depth_is_offset_from_colour_in_space_and_time(kitchen_world, scenario):
    """The depth image is the depth camera's (a few mm away, 6 ms earlier), not the colour one's."""
    cfg = dataclasses.replace(
        kinect_noise(),
        **QUIET,
        disparity_step_px=0.0,
        edge_hole_px=0.0,
        projector_shadow=False,
        grazing_start_deg=90.0,
        grazing_max_deg=90.0,
        exposure_s=0.0,
    )
    frame = fastest_frame(scenario)
    T_world_cam, pose_at = camera_motion(scenario, 0, frame)
    renderer = Renderer(kitchen_world, MID_CAMERA, cfg)
    _, depth = renderer.render(T_world_cam, noise_seed=1, pose_at=pose_at)
    T_world_depth = pose_at([-cfg.depth_lag_s])[0] @ se3(t=cfg.depth_offset_m)
    assert np.array_equal(depth, renderer.render_depth(T_world_depth))
    colour_depth = renderer.render_depth(T_world_cam)
    moved = np.abs(depth - colour_depth) > 0.01
    assert moved.mean() > 0.005  # object edges do not line up
    offset = np.linalg.norm(np.linalg.inv(T_world_cam)[:3] @ np.append(T_world_depth[:3, 3], 1))
    assert 0.002 < offset < 0.02  # metres between the two cameras at the frame time


def test_motion_blur_follows_the_camera_motion(kitchen_world, scenario):
    cfg = NoiseConfig(**QUIET, exposure_s=0.016)
    renderer = Renderer(kitchen_world, MID_CAMERA, cfg)
    frame = fastest_frame(scenario)
    T_world_cam, pose_at = camera_motion(scenario, 0, frame)
    sharp, _ = renderer.render(T_world_cam, noise_seed=1)  # no motion given: a still camera
    blurred, _ = renderer.render(T_world_cam, noise_seed=1, pose_at=pose_at)

    def sharpness(bgr):
        return cv2.Laplacian(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var()

    assert sharpness(blurred) < 0.8 * sharpness(sharp)
    assert np.abs(blurred.astype(int) - sharp).mean() < 15  # the same picture, smeared
    # A camera that does not move during the exposure gives the sharp image.
    still = np.repeat(np.eye(4)[None], 2, axis=0)
    depth = renderer.render_depth(T_world_cam)
    assert motion_blur(sharp, depth, MID_CAMERA, still[0], still[1]) is sharp


def test_exposure_gain_drifts_and_steps():
    cfg = kinect_noise()
    t = np.arange(0, 60, 1 / 30)
    gains = exposure_gains(cfg, 7, t)
    assert 0.6 < gains.min() < 0.95 and 1.05 < gains.max() < 1.45
    assert np.abs(np.diff(gains)).max() < 0.1  # steps settle over a few frames, no flicker
    assert np.allclose(exposure_gains(cfg, 7, t[:300]), gains[:300])  # depends on time only
    assert not np.allclose(exposure_gains(cfg, 8, t), gains)
    assert np.array_equal(exposure_gains(NoiseConfig(), 7, t), np.ones(len(t)))
    bgr = np.full((8, 8, 3), 100, np.uint8)
    depth = np.ones((8, 8), np.float32)
    quiet = NoiseConfig(**QUIET)
    assert (apply_noise(bgr, depth, quiet, 1, gain=1.2)[0] == 120).all()


def test_default_noise_has_no_new_effects(kitchen_world, scenario):
    """Other scenarios render as before: the default profile ignores motion, gain and camera."""
    cfg = NoiseConfig()
    assert not cfg.needs_motion and cfg.disparity_step_px == 0 and not cfg.projector_shadow
    assert cfg.edge_hole_px == 0 and cfg.grazing_start_deg == 90 and cfg.gain_drift == 0
    assert not np.any(cfg.depth_offset_m)
    renderer = Renderer(kitchen_world, SMALL_CAMERA, cfg)
    T_world_cam, pose_at = camera_motion(scenario, 0, fastest_frame(scenario))
    plain = renderer.render(T_world_cam, noise_seed=4)
    extra = renderer.render(T_world_cam, noise_seed=4, pose_at=pose_at, gain=1.0)
    assert np.array_equal(plain[0], extra[0]) and np.array_equal(plain[1], extra[1])
    bgr, depth = Renderer(kitchen_world, SMALL_CAMERA, NoiseConfig(enabled=False)).render(
        T_world_cam
    )
    a = apply_noise(bgr, depth, cfg, 9)
    b = apply_noise(bgr, depth, cfg, 9, camera=SMALL_CAMERA, gain=1.0, shadow=None)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_noise_profile_is_validated():
    with pytest.raises(Exception, match="grazing"):
        NoiseConfig(grazing_start_deg=80.0, grazing_max_deg=70.0).validate()
    with pytest.raises(Exception, match="disparity"):
        NoiseConfig(disparity_step_px=-0.1).validate()
    kinect_noise().validate()


# --- generation --------------------------------------------------------------------------------
def test_cache_key_covers_the_noise_profile():
    sc = make_scenario("kitchen", duration_s=1.0)
    cam = generate_mod.DEFAULT_CAMERA
    params = generate_mod._params(sc, True, cam)
    assert params["rate_hz"] == 30.0 and params["noise_profile"]["disparity_step_px"] == 0.125
    key = generate_mod.params_hash(params)
    sc.noise = dataclasses.replace(sc.noise, exposure_s=0.02)
    assert generate_mod.params_hash(generate_mod._params(sc, True, cam)) != key
    # Scenarios with the default sensor keep the keys (and cached worlds) they had.
    assert "noise_profile" not in generate_mod._params(make_scenario("team"), True, cam)


def test_generate_a_short_kitchen(tmp_path, kitchen_world):
    folder = generate_mod.generate(
        "kitchen",
        seed=0,
        duration_s=0.2,
        out_dir=str(tmp_path / "kitchen"),
        camera=SMALL_CAMERA,
        overlap_config=FAST_OVERLAP,
    )
    world = read_synthetic(folder)
    scenario = make_scenario("kitchen", seed=0, duration_s=0.2)
    assert world.meta["hand_held"] is True and world.meta["rate_hz"] == 30.0
    assert world.meta["noise"] == dataclasses.asdict(kinect_noise())
    assert world.meta["overlap_config"]["max_range_m"] == kinect_noise().depth_max_m
    assert np.allclose(world.T_base_cam, HAND_HELD_T_BASE_CAM)
    cfg = kinect_noise()
    fb = cfg.disparity_fx_px * cfg.disparity_baseline_m
    ideal = Renderer(kitchen_world, SMALL_CAMERA, NoiseConfig(enabled=False))
    for traj in scenario.trajectories:
        seq = world.sequences[traj.robot_id]
        assert len(seq) == 6 and np.allclose(np.diff(seq.stamps_s), 1 / 30, atol=1e-5)
        # Ground truth is the colour camera's optical frame (what the evaluation compares with).
        assert np.allclose(seq.frame_poses(), traj.poses_se3 @ HAND_HELD_T_BASE_CAM, atol=1e-6)
        depth = seq.load_depth_m(seq.frames[3])
        z = depth[depth > 0].astype(float)
        steps = fb / z / cfg.disparity_step_px
        # On the lattice, up to the PNG's 0.2 mm rounding.
        assert np.all(np.abs(steps - np.round(steps)) < 1e-3 + steps * 1.01e-4 / z)
        assert 0.01 < (depth == 0).mean() < 0.5
        colour = seq.load_color(seq.frames[3])
        exact, _ = ideal.render(traj.poses_se3[3] @ HAND_HELD_T_BASE_CAM)
        assert np.abs(colour.astype(int) - exact).mean() < 30  # the same view, with its sensor
