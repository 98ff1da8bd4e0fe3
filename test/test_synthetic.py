"""Tests of the synthetic multi-robot world: geometry, rendering, markers, scenarios, generation."""

from __future__ import annotations

import itertools
import os

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

import coop_slam.synthetic.generate as generate_mod
from coop_slam.camera import CameraModel
from coop_slam.datasets import DatasetError, read_synthetic
from coop_slam.geometry import invert, se3, transform_points
from coop_slam.synthetic.bodies import body_faces, body_model
from coop_slam.synthetic.overlap import OverlapConfig, compute_overlap
from coop_slam.synthetic.render import DynamicObject, NoiseConfig, Renderer, apply_noise
from coop_slam.synthetic.scenarios import SCENARIOS, ScenarioError, make_scenario
from coop_slam.synthetic.world import DEFAULT_T_BASE_CAM, WorldError, build_world

SMALL_CAMERA = CameraModel(width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
FAST_OVERLAP = OverlapConfig(rate_hz=2.5, depth_width_px=80)


def T_world_base(x, y, yaw_deg):
    return se3(Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix(), [x, y, 0.0])


@pytest.fixture(scope="module")
def ring():
    cv2.setNumThreads(1)
    return build_world("ring", seed=0)


@pytest.fixture(scope="module")
def ideal(ring):
    return Renderer(ring, noise=NoiseConfig(enabled=False))


def backproject(depth_m, camera):
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u].astype(float)
    return np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], axis=1)


def detect_markers(bgr):
    aruco = cv2.aruco
    dictionary = aruco.getPredefinedDictionary(aruco.DICT_4X4_50)
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    if hasattr(aruco, "ArucoDetector"):  # OpenCV >= 4.7
        params = aruco.DetectorParameters()
        params.cornerRefinementMethod = aruco.CORNER_REFINE_SUBPIX
        corners, ids, _ = aruco.ArucoDetector(dictionary, params).detectMarkers(grey)
    else:
        params = aruco.DetectorParameters_create()
        params.cornerRefinementMethod = aruco.CORNER_REFINE_SUBPIX
        corners, ids, _ = aruco.detectMarkers(grey, dictionary, parameters=params)
    return (
        []
        if ids is None
        else list(zip(ids.ravel().tolist(), [c.reshape(4, 2) for c in corners], strict=True))
    )


# --- rendering ---------------------------------------------------------------------------------
def test_plane_backprojection_is_exact(ring, ideal):
    # Looking obliquely at the east end of the south corridor: walls, floor, pillar, cabinet.
    T_world_cam = T_world_base(9.5, 1.0, 20.0) @ DEFAULT_T_BASE_CAM
    bgr, depth = ideal.render(T_world_cam)
    assert bgr.shape == (480, 640, 3) and bgr.dtype == np.uint8
    assert depth.dtype == np.float32 and (depth > 0).all()  # closed building: every pixel hits
    points_world = transform_points(T_world_cam, backproject(depth, ideal.camera))[::3]
    # Every back-projected pixel lies on (the plane of) a surface it is inside of, to 0.1 mm.
    best = np.full(len(points_world), np.inf)
    for s in ring.surfaces:
        n = np.cross(s.edge_v_world, s.edge_u_world)
        n /= np.linalg.norm(n)
        rel = points_world - s.origin_world
        su = rel @ s.edge_u_world / (s.edge_u_world @ s.edge_u_world)
        sv = rel @ s.edge_v_world / (s.edge_v_world @ s.edge_v_world)
        margin_u, margin_v = 0.02 / s.size_m[0], 0.02 / s.size_m[1]  # edge pixels: 2 cm slack
        inside = (su > -margin_u) & (su < 1 + margin_u) & (sv > -margin_v) & (sv < 1 + margin_v)
        best = np.where(inside, np.minimum(best, np.abs(rel @ n)), best)
    assert np.max(best) < 1e-4
    east_wall = np.abs(points_world[:, 0] - 12.0) < 1e-4
    floor = np.abs(points_world[:, 2]) < 1e-4
    assert east_wall.mean() > 0.1 and floor.mean() > 0.1


def test_noise_model(ideal):
    T_world_cam = T_world_base(2.0, 1.0, 0.0) @ DEFAULT_T_BASE_CAM
    bgr, depth = ideal.render(T_world_cam)
    cfg = NoiseConfig()
    noisy_bgr, noisy_depth = apply_noise(bgr, depth, cfg, seed=3)
    diff = noisy_bgr.astype(float) - cv2.GaussianBlur(bgr, (0, 0), cfg.blur_sigma_px)
    assert 1.5 < diff.std() < 2.5
    in_range = (depth > cfg.depth_min_m) & (depth < cfg.depth_max_m)
    assert not noisy_depth[depth > cfg.depth_max_m + 0.6].any()  # 0.6 m: > 5 sigma at 8 m
    holes = in_range & (noisy_depth == 0)
    assert 0.01 < holes.sum() / in_range.sum() < 0.04
    near = in_range & (noisy_depth > 0) & (np.abs(depth - 2.0) < 0.1)
    expected = cfg.depth_sigma_m(2.0)
    assert 0.7 * expected < (noisy_depth - depth)[near].std() < 1.3 * expected


def test_marker_detected_with_right_id_and_location(ring):
    renderer = Renderer(ring)  # with noise, as in generated data
    T_world_obs = T_world_base(3.0, 1.0, 0.0)
    T_world_other = T_world_base(4.6, 1.1, 180.0)  # robot 3 faces the observer 1.6 m ahead
    T_world_cam = T_world_obs @ DEFAULT_T_BASE_CAM
    bgr, _ = renderer.render(
        T_world_cam, [DynamicObject(T_world_other, body_model(3))], noise_seed=5
    )
    found = detect_markers(bgr)
    assert [i for i, _ in found] == [3]
    front = body_faces()[0].marker_corners_base
    points_cam = transform_points(invert(T_world_cam) @ T_world_other, front)
    uv = points_cam @ renderer.camera.K.T
    uv = uv[:, :2] / uv[:, 2:]
    assert np.abs(found[0][1] - uv).max() < 1.0  # same corners, same order (TL, TR, BR, BL)
    # The marker is the robot's: no robot, no marker.
    bgr_empty, _ = renderer.render(T_world_cam, noise_seed=5)
    assert detect_markers(bgr_empty) == []


def test_marker_size_is_validated():
    with pytest.raises(WorldError):
        body_faces(0.5)


def test_determinism():
    T_world_cam = T_world_base(4.0, 1.0, 10.0) @ DEFAULT_T_BASE_CAM
    a = Renderer(build_world("ring", 7), SMALL_CAMERA).render(T_world_cam, noise_seed=1)
    b = Renderer(build_world("ring", 7), SMALL_CAMERA).render(T_world_cam, noise_seed=1)
    c = Renderer(build_world("ring", 8), SMALL_CAMERA).render(T_world_cam, noise_seed=1)
    d = Renderer(build_world("ring", 7), SMALL_CAMERA).render(T_world_cam, noise_seed=2)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert np.abs(a[0].astype(int) - c[0]).mean() > 20  # other seed: other textures
    assert not np.array_equal(a[0], d[0])  # other frame: other sensor noise ...
    assert np.abs(a[0].astype(int) - d[0]).mean() < 4  # ... of the same scene
    traj_a = make_scenario("revisit", seed=3).trajectories[1].poses_se3
    assert np.array_equal(traj_a, make_scenario("revisit", seed=3).trajectories[1].poses_se3)
    assert not np.allclose(traj_a, make_scenario("revisit", seed=4).trajectories[1].poses_se3)


def test_orb_finds_many_well_spread_keypoints(ring):
    renderer = Renderer(ring)
    orb = cv2.ORB_create(1000)
    scenario = make_scenario("team", seed=0, robots=3)
    for traj in scenario.trajectories:
        for k in np.linspace(0, len(traj.stamps_s) - 1, 4).astype(int):
            bgr, _ = renderer.render(traj.poses_se3[k] @ scenario.T_base_cam, noise_seed=int(k))
            keypoints = orb.detect(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), None)
            cells = {(int(p.pt[0] // 160), int(p.pt[1] // 120)) for p in keypoints}
            assert len(keypoints) >= 500, f"{traj.name} frame {k}: {len(keypoints)} ORB keypoints"
            assert (
                len(cells) >= 10
            ), f"{traj.name} frame {k}: keypoints in only {len(cells)}/16 cells"


def test_bench_render_leaves_opencv_threads_as_it_found_them():
    from coop_slam.tools.bench import render_fps

    """The render benchmark measures one core (cv2.setNumThreads(1)); the rest of the process
    must get its threads back."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        render_fps(frames=2, camera=SMALL_CAMERA)
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(threads)


# --- scenarios and overlap ---------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(n for n, spec in SCENARIOS.items() if not spec.hand_held))
def test_trajectories_are_robot_like(name):
    spec = SCENARIOS[name]
    scenario = make_scenario(name, seed=1, robots=spec.max_robots)
    world = build_world(scenario.layout, seed=1)
    xy = []
    for traj in scenario.trajectories:
        poses = traj.poses_se3
        assert np.allclose(traj.stamps_s[0], 1.0) and np.allclose(np.diff(traj.stamps_s), 1 / 15)
        assert np.allclose(poses[:, 2, 3], 0.0) and np.allclose(
            poses[:, 2, :3], [0, 0, 1]
        )  # planar
        speed = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1) * scenario.rate_hz
        yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
        yaw_rate = np.degrees(np.abs(np.diff(yaw))) * scenario.rate_hz
        assert speed.max() < 0.5 and speed.max() > 0.3
        assert yaw_rate.max() < 40.0
        assert world.is_free(poses[:, :2, 3], clearance_m=0.2).all(), f"{traj.name} hits a wall"
        xy.append(poses[:, :2, 3])
    for a, b in itertools.combinations(xy, 2):
        assert np.linalg.norm(a - b, axis=1).min() > 0.6  # bodies never touch


def test_scenario_arguments_are_checked():
    with pytest.raises(ScenarioError):
        make_scenario("nowhere")
    with pytest.raises(ScenarioError):
        make_scenario("rendezvous", robots=3)
    with pytest.raises(ScenarioError):
        make_scenario("multi", robots=9)


def test_rendezvous_overlap():
    scenario = make_scenario("rendezvous", seed=0)
    events = compute_overlap(scenario, build_world(scenario.layout, 0), cfg=FAST_OVERLAP)
    meet = events.rendezvous_time(1, 2)
    assert meet is not None and meet >= scenario.meta["meet_time_s"] - 1.0
    assert events.sighting_time(1, 2) is not None and events.sighting_time(2, 1) is not None
    assert events.first_overlap_time(1, 2) <= meet


def test_revisit_overlap():
    scenario = make_scenario("revisit", seed=0)
    events = compute_overlap(scenario, build_world(scenario.layout, 0), cfg=FAST_OVERLAP)
    assert events.rendezvous == [] and events.marker_sightings == []
    revisit = [e for e in events.revisit if e["robot"] == 2 and e["of_robot"] == 1]
    assert revisit and revisit[0]["earlier_stamp_s"] < revisit[0]["stamp_s"] - 10.0


@pytest.mark.parametrize("name", ["disjoint", "aliasing"])
def test_no_overlap_between_buildings(name):
    scenario = make_scenario(name, seed=0)
    events = compute_overlap(scenario, build_world(scenario.layout, 0), cfg=FAST_OVERLAP)
    assert events.to_dict() == {
        "rendezvous": [],
        "revisit": [],
        "marker_sightings": [],
        "first_overlap": [],
    }


def test_aliasing_world_shares_posters_only():
    aliased = build_world("two_buildings_aliased", seed=0)
    distinct = build_world("two_buildings", seed=0)
    # Surface 2 is the east outer wall: it carries the poster at the end of the south corridor.
    name0, name1 = aliased.surfaces[2].name, aliased.surfaces[2 + len(aliased.surfaces) // 2].name
    assert name0 == "b0.east" and name1 == "b1.east"
    half = len(aliased.surfaces) // 2
    tex0, tex1 = aliased.surface_texture(2), aliased.surface_texture(2 + half)
    poster = aliased.surfaces[2].posters[0]
    sx = tex0.shape[1] / aliased.surfaces[2].size_m[0]  # texels per metre along the wall
    sy = tex0.shape[0] / aliased.surfaces[2].size_m[1]
    x0, y0 = int(poster.u_m * sx) + 2, int(poster.v_m * sy) + 2
    x1, y1 = x0 + int(poster.width_m * sx) - 4, y0 + int(poster.height_m * sy) - 4
    assert np.array_equal(tex0[y0:y1, x0:x1], tex1[y0:y1, x0:x1])  # identical poster ...
    assert not np.array_equal(tex0[:, : x0 - 50], tex1[:, : x0 - 50])  # ... on different walls
    d0, d1 = distinct.surface_texture(2), distinct.surface_texture(2 + half)
    assert not np.array_equal(d0[y0:y1, x0:x1], d1[y0:y1, x0:x1])


# --- generation, reading and cache -------------------------------------------------------------
def test_generate_and_read_round_trip(tmp_path):
    out = tmp_path / "world"
    calls = []
    folder = generate_mod.generate(
        "rendezvous",
        seed=0,
        duration_s=1.0,
        rate_hz=5.0,
        noise=False,
        out_dir=str(out),
        camera=SMALL_CAMERA,
        progress=lambda done, total: calls.append((done, total)),
        overlap_config=FAST_OVERLAP,
    )
    assert folder == str(out) and calls[-1] == (10, 10)
    world = read_synthetic(folder)
    scenario = make_scenario("rendezvous", seed=0, duration_s=1.0, rate_hz=5.0)
    assert world.robot_ids == [1, 2] and world.scenario == "rendezvous"
    assert [r["name"] for r in world.meta["robots"]] == ["robot_1", "robot_2"]
    assert np.allclose(world.T_base_cam, DEFAULT_T_BASE_CAM)
    assert world.meta["markers"]["size_m"] == 0.25 and "overlap" in world.meta
    for traj in scenario.trajectories:
        seq = world.sequences[traj.robot_id]
        assert len(seq) == 5 and seq.camera == SMALL_CAMERA
        assert np.allclose(seq.stamps_s, traj.stamps_s)
        assert np.allclose(seq.frame_poses(), traj.poses_se3 @ scenario.T_base_cam, atol=1e-6)
        frame = seq.frames[2]
        color = seq.load_color(frame)
        depth = seq.load_depth_m(frame)
        assert color.shape == (120, 160, 3) and depth.shape == (120, 160)
        # Stored depth is the exact render, quantized to 1/5000 m.
        others = [
            DynamicObject(o.poses_se3[2], body_model(o.robot_id))
            for o in scenario.trajectories
            if o is not traj
        ]
        _, expected = Renderer(
            build_world("ring", 0), SMALL_CAMERA, NoiseConfig(enabled=False)
        ).render(traj.poses_se3[2] @ scenario.T_base_cam, others)
        assert np.abs(depth - expected).max() <= 1.01 / 5000 * 0.5 + 1e-6


def test_generate_uses_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("COOP_SLAM_CACHE", str(tmp_path))
    kwargs = {
        "duration_s": 0.4,
        "rate_hz": 5.0,
        "camera": SMALL_CAMERA,
        "overlap_config": FAST_OVERLAP,
    }
    first = generate_mod.generate("disjoint", seed=2, **kwargs)
    assert first.startswith(str(tmp_path / "worlds" / "disjoint-"))
    assert os.path.isfile(os.path.join(first, ".complete"))

    def no_render(job):
        raise AssertionError("a cached world was rendered again")

    monkeypatch.setattr(generate_mod, "_render_chunk", no_render)
    assert generate_mod.generate("disjoint", seed=2, **kwargs) == first
    # Any parameter change is another world (another folder).
    with pytest.raises(AssertionError, match="rendered again"):
        generate_mod.generate("disjoint", seed=3, **kwargs)
    assert sorted(os.listdir(tmp_path / "worlds")) == [os.path.basename(first)]  # no temp left


def test_reader_rejects_bad_folders(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        read_synthetic(str(tmp_path / "missing"))
    with pytest.raises(DatasetError, match="world.yaml"):
        read_synthetic(str(tmp_path))
    (tmp_path / "world.yaml").write_text("robots: [")
    with pytest.raises(DatasetError, match="incomplete"):
        read_synthetic(str(tmp_path))
    (tmp_path / ".complete").write_text("")
    with pytest.raises(DatasetError, match="YAML"):
        read_synthetic(str(tmp_path))
    T = DEFAULT_T_BASE_CAM.tolist()
    (tmp_path / "world.yaml").write_text(
        yaml.safe_dump({"robots": [{"id": 1, "name": "robot_1"}], "T_base_cam": T})
    )
    with pytest.raises(DatasetError, match="robot_1"):
        read_synthetic(str(tmp_path))
    (tmp_path / "world.yaml").write_text(
        yaml.safe_dump({"robots": [{"id": 1, "name": "robot_1"}], "T_base_cam": [1]})
    )
    with pytest.raises(DatasetError, match="T_base_cam"):
        read_synthetic(str(tmp_path))


def test_world_cache_key_covers_the_routes():
    """A scenario whose routes change (same name, seed, robots) never reuses a cached world."""
    sc = make_scenario("team", seed=0, robots=4)
    cam = generate_mod.DEFAULT_CAMERA
    key = generate_mod.params_hash(generate_mod._params(sc, True, cam))
    assert key == generate_mod.params_hash(generate_mod._params(sc, True, cam))
    sc.trajectories[3].poses_se3[:, 0, 3] += 0.01  # robot 4 drives 1 cm further east
    assert key != generate_mod.params_hash(generate_mod._params(sc, True, cam))


def test_stereo_world_renders_the_right_camera_of_a_rectified_pair(tmp_path):
    """With a baseline, each robot folder also holds the right camera's images, 0.12 m to the
    right of the left one: a left pixel's depth z reappears fx * b / z pixels to the left, on the
    same row. Played as stereo it has what that needs; a plain world refuses to be."""
    import cv2

    from coop_slam.playback import PlaybackError, RobotStream, _with_sensor

    def small_world(name, **kwargs):
        return read_synthetic(
            generate_mod.generate(
                "rendezvous",
                seed=0,
                duration_s=1.0,
                rate_hz=5.0,
                noise=False,
                out_dir=str(tmp_path / name),
                camera=SMALL_CAMERA,
                overlap_config=FAST_OVERLAP,
                **kwargs,
            )
        )

    seq = small_world("stereo", stereo_baseline_m=0.12).sequences[1]
    assert seq.camera.baseline_m == 0.12 and seq.frames[0].right_path is not None
    frame = seq.frames[2]
    left, right = seq.load_color(frame), seq.load_right(frame)
    depth = seq.load_depth_m(frame)
    gray_l = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY).astype(float)
    gray_r = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY).astype(float)
    v, u = np.mgrid[0 : gray_l.shape[0], 0 : gray_l.shape[1]].astype(np.float32)
    with np.errstate(divide="ignore"):
        disparity = np.where(depth > 0, SMALL_CAMERA.fx * 0.12 / depth, 0).astype(np.float32)
    warped = cv2.remap(gray_r, u - disparity, v, cv2.INTER_LINEAR)
    seen = (depth > 0) & (u - disparity > 2)
    shifted = cv2.remap(gray_r, u, v, cv2.INTER_LINEAR)  # as if the pair had no baseline
    assert np.abs(warped - gray_l)[seen].mean() < 0.5 * np.abs(shifted - gray_l)[seen].mean()
    stream = RobotStream(1, seq)
    assert _with_sensor(stream, "stereo").sequence.camera.sensor == "stereo"
    plain = small_world("plain")
    with pytest.raises(PlaybackError, match="no right images"):
        _with_sensor(RobotStream(1, plain.sequences[1]), "stereo")


def test_a_world_of_robots_with_their_own_camera_mounts(tmp_path):
    """``mounts``: each robot's frames are rendered from its own camera mount, world.yaml carries
    each robot's, and reading the world gives them back."""
    from coop_slam.synthetic.scenarios import MOUNTS_HEIGHT_M

    folder = generate_mod.generate(
        "mounts",
        duration_s=0.6,
        rate_hz=5.0,
        noise=False,
        out_dir=str(tmp_path / "w"),
        camera=SMALL_CAMERA,
        overlap_config=FAST_OVERLAP,
    )
    world = read_synthetic(folder)
    scenario = make_scenario("mounts", duration_s=0.6, rate_hz=5.0)
    heights = [world.mount(r)[2, 3] for r in world.robot_ids]
    assert heights == pytest.approx(list(MOUNTS_HEIGHT_M))
    for traj in scenario.trajectories:
        T_base_cam = scenario.mount(traj.robot_id)
        np.testing.assert_allclose(world.mount(traj.robot_id), T_base_cam, atol=1e-9)
        np.testing.assert_allclose(
            world.sequences[traj.robot_id].frame_poses(), traj.poses_se3 @ T_base_cam, atol=1e-6
        )
