"""Monocular cameras in the odometry: the sensor, two-view initialization in the pipeline, new
points from triangulation, the scale gauge of local BA, loss and a new map segment, playback, and a
monocular run on a synthetic world (initialized within 1 s of moving, never lost, Sim(3)-aligned
ATE at most 1 % of the path)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import helpers_vo
from coop_slam.config import load_config, merge_overrides
from coop_slam.datasets import Frame, Sequence, read_synthetic
from coop_slam.evaluation.vo_run import run_sequence
from coop_slam.geometry import invert, path_length, se3, transform_error, transform_points
from coop_slam.optim.bundle import BaProblem, reprojection_chi2, run_local_ba
from coop_slam.vo import (
    EVENT_KEYFRAME_NEW,
    EVENT_NEW_SEGMENT,
    STATE_INITIALIZING,
    STATE_LOST,
    STATE_NEW_SEGMENT,
    STATE_OK,
    STATE_RELOCALIZED,
    VisualOdometry,
    VoConfig,
    VoError,
)
from coop_slam.vo.features import OrbExtractor
from coop_slam.vo.local_mapping import LocalMapper
from coop_slam.vo.map import Map, MapKeyframe
from coop_slam.vo.sensor import MonoSensor, make_sensor

MONO = dataclasses.replace(helpers_vo.CAMERA, sensor="mono")
K = MONO.K


def sync_config(**kw) -> VoConfig:
    """Deterministic configuration: local mapping runs synchronously inside track()."""
    return load_config(VoConfig, merge_overrides({"threaded": False}, kw))


def sim3_ate(stamps_s, poses_est, poses_gt) -> tuple[float, float]:
    """(ATE RMSE [m], scale) after a Sim(3) Umeyama alignment of the estimate onto the ground truth
    (evo's ``align(correct_scale=True)``): the measure of a map without metric scale.
    coop_slam.evaluation.ate aligns SE(3) only."""
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    ref = PoseTrajectory3D(poses_se3=list(poses_gt), timestamps=np.asarray(stamps_s, float))
    est = PoseTrajectory3D(poses_se3=list(poses_est), timestamps=np.asarray(stamps_s, float))
    _, _, scale = est.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse)), float(scale)


def scale_of(poses_est, poses_gt, step: int = 10) -> float:
    """Metres per map unit over a stretch of trajectory: ground-truth over estimated distance
    travelled between every ``step``-th pose (the steps average out pose jitter)."""
    d_gt = np.linalg.norm(np.diff(poses_gt[::step, :3, 3], axis=0), axis=1).sum()
    d_est = np.linalg.norm(np.diff(poses_est[::step, :3, 3], axis=0), axis=1).sum()
    return float(d_gt / d_est)


@pytest.fixture(scope="module")
def room():
    """The rendered room of helpers_vo: (stamps, BGR images, ground truth T_world_cam)."""
    stamps, frames, gt = helpers_vo.sequence(n_frames=45, seed=3, step_m=0.012)
    return stamps, [bgr for bgr, _ in frames], gt


# --- the sensor -----------------------------------------------------------------------------------
def test_mono_sensor_measures_no_depth(room):
    _, images, _ = room
    cfg = VoConfig()
    sensor = make_sensor(cfg, MONO)
    assert isinstance(sensor, MonoSensor) and sensor.monocular and sensor.bf == 0.0
    gray, second = sensor.check_input(images[0], None)
    assert gray.ndim == 2 and second is None
    # A second image (the depth of an RGB-D recording played as a monocular camera) is ignored.
    assert sensor.check_input(images[0], np.ones((480, 640), np.float32))[1] is None
    feats = sensor.features(OrbExtractor(cfg, MONO).extract(gray), gray, None)
    assert len(feats) > 500
    assert not feats.has_depth.any() and np.isnan(feats.u_right_px).all()
    assert np.isnan(feats.points_cam).all()
    with pytest.raises(VoError, match="image is 320x240"):
        sensor.check_input(images[0][::2, ::2], None)
    with VisualOdometry(sync_config(), MONO) as vo:
        assert vo.metric_scale is False
        with pytest.raises(VoError, match="image is 320x240"):
            vo.track(1.0, images[0][::2, ::2])
    with VisualOdometry(sync_config(), helpers_vo.CAMERA) as vo:
        assert vo.metric_scale is True


# --- initialization in the pipeline ---------------------------------------------------------------
def test_initialization_waits_then_builds_a_two_view_map(room):
    stamps, images, gt = room
    with VisualOdometry(sync_config(), MONO) as vo:
        res = vo.track(stamps[0], images[0])
        assert res.state == STATE_INITIALIZING and not res.ok
        assert res.message.startswith("initializing: reference frame set")
        # The same view again: no parallax, keep waiting.
        res = vo.track(stamps[0] + 0.01, images[0])
        assert res.state == STATE_INITIALIZING
        assert res.message.startswith("initializing: not enough parallax"), res.message
        # A frame without texture matches nothing: it cannot even become the reference.
        res = vo.track(stamps[0] + 0.02, np.full_like(images[0], 128))
        assert res.message == "initializing: 0 keypoints, 100 needed", res.message
        assert vo._init_ref is None
        res = vo.track(stamps[0] + 0.03, images[0])
        assert "reference frame set" in res.message
        # A reference older than mono_init_max_age_s is replaced.
        res = vo.track(stamps[0] + 5.0, images[0])
        assert "new reference frame" in res.message and vo._init_ref[0] == stamps[0] + 5.0
        # Moving on: the two-view map.
        t0 = stamps[0] + 5.0
        k = 1
        while res.state == STATE_INITIALIZING:
            res = vo.track(t0 + stamps[k] - stamps[0], images[k])
            k += 1
        assert res.ok and res.state == STATE_OK and res.message.startswith("map initialized")
        assert "no metric scale" in res.message
        # The room is mostly its back wall: a homography, which needs 1.5 deg of parallax.
        assert "homography" in res.message and k - 1 < 20, res.message
        events = [e for e in vo.drain_events() if e.kind == EVENT_KEYFRAME_NEW]
        assert [e.keyframe_id for e in events] == [1, 2]
        kf1, kf2 = vo.keyframe(1), vo.keyframe(2)
        assert kf1.stamp_s == t0 and np.allclose(kf1.T_map_cam, np.eye(4), atol=1e-9)
        # The second keyframe is the frame tracked, then moved a little by local BA (the map's
        # unit is the first keyframe's median depth).
        moved_m, moved_deg = transform_error(kf2.T_map_cam, res.T_map_cam)
        assert res.new_keyframe_id == 2 and moved_m < 0.01 and moved_deg < 0.5
        # Every point is seen by both keyframes, in front of both, and the median depth in the
        # first keyframe is about 1 (the map's unit; local BA moved it a little).
        shared = np.intersect1d(kf1.map_point_ids, kf2.map_point_ids)
        shared = shared[shared > 0]
        assert len(shared) >= VoConfig().keyframes.min_init_points
        xyz = np.array([vo.map_points()[int(p)] for p in shared])
        assert 0.9 < np.median(xyz[:, 2]) < 1.1
        assert (transform_points(invert(kf2.T_map_cam), xyz)[:, 2] > 0).all()
        assert vo.vo_map.check_consistency() == []
        # The motion up to the scale: rotation and direction of the baseline as the truth (a
        # 15 cm baseline at 2-4 m: the direction is known to a few degrees).
        T_true = invert(gt[0]) @ gt[k - 1]
        t_est, t_true = kf2.T_map_cam[:3, 3], T_true[:3, 3]
        cos = t_est @ t_true / np.linalg.norm(t_est) / np.linalg.norm(t_true)
        assert np.degrees(np.arccos(min(cos, 1.0))) < 10.0
        rot = Rotation.from_matrix(kf2.T_map_cam[:3, :3].T @ T_true[:3, :3]).magnitude()
        assert np.degrees(rot) < 0.3
        # Tracking goes on in the two-view map.
        for j in range(k, k + 5):
            res = vo.track(t0 + stamps[j] - stamps[0], images[j])
            assert res.ok and res.state == STATE_OK and res.n_tracked > 100


def test_lost_monocular_camera_relocalizes_then_starts_a_new_segment(room):
    stamps, images, _ = room
    blank = np.full_like(images[0], 128)
    cfg = sync_config()
    with VisualOdometry(cfg, MONO) as vo:
        for k in range(20):
            res = vo.track(stamps[k], images[k])
        assert res.state == STATE_OK and res.map_segment == 0
        for k in range(20, 23):  # the lens covered
            assert vo.track(stamps[k], blank).state == STATE_LOST
        res = vo.track(stamps[23], images[23])
        assert res.state == STATE_RELOCALIZED and res.ok, res.message
        t = stamps[24]
        for _ in range(
            cfg.relocalization.max_lost_frames + 1
        ):  # a covered lens does not end the map ...
            res = vo.track(t, blank)
            t += 0.1
        assert res.state == STATE_LOST and res.map_segment == 0
        noise = np.random.default_rng(0).integers(0, 256, blank.shape, dtype=np.uint8)
        messages = []
        for _ in range(cfg.relocalization.max_lost_frames + 2):  # ... views the map cannot place do
            res = vo.track(t, noise)
            messages.append(res.message)
            t += 0.1
        assert not res.ok and res.map_segment == 1
        assert any(m.startswith("new map segment started; initializing:") for m in messages)
        assert EVENT_NEW_SEGMENT in [e.kind for e in vo.drain_events()]
        assert vo.keyframes() == []
        # A new two-view map, in segment 1.
        for k in range(24, 45):
            res = vo.track(t, images[k])
            t += 1 / 30
            if res.ok:
                break
        assert res.ok and res.state == STATE_NEW_SEGMENT and res.map_segment == 1
        assert [kf.map_segment for kf in vo.keyframes()] == [1, 1]


# --- new points from triangulation ----------------------------------------------------------------
def _keyframe(kf_id, T_map_cam, uv, desc, octaves, point_ids) -> MapKeyframe:
    n = len(uv)
    return MapKeyframe(
        keyframe_id=kf_id,
        stamp_s=float(kf_id),
        map_segment=0,
        T_map_cam=T_map_cam,
        uv_px=uv.astype(np.float32),
        size_px=np.full(n, 31.0, np.float32),
        angle_deg=np.full(n, 45.0, np.float32),
        octaves=octaves.astype(np.uint8),
        descriptors=desc,
        depths_m=np.zeros(n, np.float32),
        map_point_ids=point_ids.astype(np.uint32),
    )


def test_local_mapping_triangulates_new_points_of_a_monocular_keyframe():
    """Two keyframes 0.3 m apart that share 60 points (so they are covisible) and see 400 more
    points with keypoints of no point yet: local mapping makes those points, at the right place,
    observed by both keyframes; distant points seen under too little parallax are left out."""
    rng = np.random.default_rng(0)
    n_shared, n_new, n_far = 60, 400, 40
    depth = np.r_[rng.uniform(2.0, 5.0, n_shared + n_new), rng.uniform(200, 300, n_far)]
    uv0 = rng.uniform([40, 40], [600, 440], (len(depth), 2))
    rays = np.column_stack([(uv0 - K[:2, 2]) / K[0, 0], np.ones(len(uv0))])
    xyz = rays * depth[:, None]  # map frame = the first camera
    T2 = se3(Rotation.from_euler("y", -3, degrees=True).as_matrix(), [0.3, 0.02, 0.05])
    pc2 = transform_points(invert(T2), xyz)
    uv1 = pc2[:, :2] / pc2[:, 2:] * K[0, 0] + K[:2, 2]
    noise = rng.normal(0, 0.3, (2, len(xyz), 2))
    desc = rng.integers(0, 256, (len(xyz), 32), dtype=np.uint8)
    octaves = rng.integers(0, 3, len(xyz))
    vmap = Map(0)
    shared = vmap.points.add(
        xyz[:n_shared],
        desc[:n_shared],
        np.full(n_shared, 45.0, np.float32),
        rays[:n_shared] / np.linalg.norm(rays[:n_shared], axis=1, keepdims=True),
        np.linalg.norm(xyz[:n_shared], axis=1) * 2.0,
        1,
    )
    mp = np.zeros(len(xyz), np.int64)
    mp[:n_shared] = shared
    # Keyframe 2 lists its keypoints in another order.
    order = rng.permutation(len(xyz))
    vmap.add_keyframe(_keyframe(1, np.eye(4), uv0 + noise[0], desc, octaves, mp))
    vmap.add_keyframe(
        _keyframe(2, T2, (uv1 + noise[1])[order], desc[order], octaves[order], mp[order])
    )
    vmap.update_covisibility(2)
    mapper = LocalMapper(sync_config(), make_sensor(VoConfig(), MONO), lambda: vmap, lambda e: 0)
    created = mapper.triangulate_new_points(vmap, 2)
    assert vmap.check_consistency() == []
    assert len(created) >= 0.95 * n_new and mapper.stats["triangulated"] == len(created)
    kf1, kf2 = vmap.keyframes[1], vmap.keyframes[2]
    errors, far = [], 0
    for pid in created:
        obs = vmap.points.obs[pid]
        assert set(obs) == {1, 2}
        i = obs[1]
        assert order[obs[2]] == i, "matched the keypoint of the same point"
        far += i >= n_shared + n_new
        errors.append(np.linalg.norm(vmap.points.xyz[pid] - xyz[i]) / depth[i])
    assert far == 0, "points at 200-300 m meet at under 0.1 deg: no depth to triangulate"
    assert np.median(errors) < 0.01
    assert (kf1.map_point_ids > 0).sum() == (kf2.map_point_ids > 0).sum() == n_shared + len(created)
    # Nothing left to triangulate: a second pass adds no point.
    assert mapper.triangulate_new_points(vmap, 2) == set()


def test_local_ba_holds_the_scale_of_a_monocular_map():
    """Projection factors only and one fixed keyframe: the problem's scale is free. The range
    factor of ``scale_anchor`` holds it; the window still converges."""
    rng = np.random.default_rng(1)
    points = rng.uniform([-2, -1.5, 2], [2, 1.5, 5], (300, 3))
    poses = [se3(Rotation.from_euler("y", 2 * k, degrees=True).as_matrix(), [0.1 * k, 0, 0])
             for k in range(4)]  # fmt: skip
    obs_kf, obs_pt, uv = [], [], []
    for k, T in enumerate(poses):
        pc = transform_points(invert(T), points)
        obs_kf.append(np.full(len(points), k))
        obs_pt.append(np.arange(len(points)))
        uv.append(pc[:, :2] / pc[:, 2:] * K[0, 0] + K[:2, 2] + rng.normal(0, 0.5, (len(pc), 2)))
    noisy = [poses[0]] + [
        T @ se3(Rotation.from_rotvec(rng.normal(0, 0.003, 3)).as_matrix(), rng.normal(0, 0.005, 3))
        for T in poses[1:]
    ]
    n_obs = 4 * len(points)
    problem = BaProblem(
        segment=0,
        kf_ids=np.arange(1, 5),
        T_map_cam=np.array(noisy),
        fixed=np.array([True, False, False, False]),
        point_ids=np.arange(1, len(points) + 1),
        points_map=points + rng.normal(0, 0.02, points.shape),
        obs_kf=np.concatenate(obs_kf),
        obs_pt=np.concatenate(obs_pt),
        obs_kp=np.concatenate(obs_pt),
        obs_uv=np.concatenate(uv),
        obs_u_right=np.full(n_obs, np.nan),
        obs_octave=np.zeros(n_obs, int),
        fx=K[0, 0],
        fy=K[1, 1],
        cx=K[0, 2],
        cy=K[1, 2],
        baseline_m=0.0,
        scale_factor=1.2,
        n_levels=8,
        iterations=10,
        scale_anchor=(0, 3),
    )
    result = run_local_ba(problem)
    assert result.ok, result.message
    span = np.linalg.norm(noisy[3][:3, 3] - noisy[0][:3, 3])
    assert np.linalg.norm(result.T_map_cam[3][:3, 3] - result.T_map_cam[0][:3, 3]) == (
        pytest.approx(span, rel=1e-3)
    )
    chi2 = reprojection_chi2(problem, result.T_map_cam, result.points_map)
    assert np.sqrt(np.median(chi2)) < 1.0 < np.sqrt(np.median(reprojection_chi2(
        problem, problem.T_map_cam, problem.points_map)))  # fmt: skip


@pytest.mark.parametrize(
    "sensor, planar, window, fixed",
    [("mono", False, 16, 16), ("mono", True, 8, 8), ("rgbd", False, 8, 8)],
)
def test_a_free_monocular_camera_gets_the_wider_local_ba_window(sensor, planar, window, fixed):
    """40 keyframes that all see the same 200 points: local BA of the newest optimizes
    ba_window_mono keyframes and holds ba_max_fixed_mono fixed for a free-moving monocular camera
    (its scale lives in shared points only), ba_window / ba_max_fixed otherwise (a ground robot's
    height prior holds a monocular scale; depth measures it)."""
    rng = np.random.default_rng(2)
    xyz = rng.uniform([-2, -1.5, 3], [2, 1.5, 6], (200, 3))
    vmap = Map(0)
    pids = vmap.points.add(
        xyz,
        rng.integers(0, 256, (len(xyz), 32), dtype=np.uint8),
        np.full(len(xyz), 45.0, np.float32),
        np.tile([0.0, 0.0, 1.0], (len(xyz), 1)),
        np.full(len(xyz), 20.0),
        1,
    )
    for k in range(1, 41):
        T = se3(np.eye(3), [0.05 * k, 0, 0])
        pc = transform_points(invert(T), xyz)
        uv = pc[:, :2] / pc[:, 2:] * K[0, 0] + K[:2, 2]
        kf = _keyframe(k, T, uv, vmap.points.desc[pids], np.zeros(len(xyz)), pids)
        if sensor == "rgbd":
            kf.depths_m = pc[:, 2].astype(np.float32)
        vmap.add_keyframe(kf)
    for k in range(1, 41):
        vmap.update_covisibility(k, propagate=False)
    cfg = sync_config(planar={"enabled": planar})
    camera = dataclasses.replace(MONO, sensor=sensor)
    mapper = LocalMapper(cfg, make_sensor(cfg, camera), lambda: vmap, lambda e: 0)
    problem = mapper.build_ba_problem(vmap, 40)
    # (the map's first keyframe, when in the window, is held fixed there: the gauge)
    assert len(problem.kf_ids) == window + fixed
    assert int((~problem.fixed).sum()) in (window, window - 1)


# --- playback -------------------------------------------------------------------------------------
def test_playback_plays_a_monocular_camera_from_any_data(tmp_path):
    from coop_slam.playback import (
        PLAYABLE_SENSORS,
        RobotStream,
        _with_sensor,
        camera_topics,
        parse_sensors,
    )

    assert "mono" in PLAYABLE_SENSORS
    assert parse_sensors("mono,rgbd") == ["mono", "rgbd"]
    topics = camera_topics(3, "mono")
    assert topics["image"] == "/robot_3/camera/color/image_raw" and "second" not in topics
    assert list(topics["infos"]) == ["color"]
    # A stereo recording (no depth) plays as a monocular camera: its left image, no baseline.
    stereo = dataclasses.replace(MONO, sensor="stereo", baseline_m=0.12)
    images = []
    for k in range(3):
        path = str(tmp_path / f"left_{k}.png")
        cv2.imwrite(path, np.full((480, 640), 100 + k, np.uint8))
        images.append(Frame(k, 10.0 + k / 30, path, None, path))
    stream = _with_sensor(RobotStream(1, Sequence("pair", stereo, images)), "mono")
    assert stream.sequence.camera.sensor == "mono" and stream.sequence.camera.baseline_m == 0.0
    run = run_sequence(stream.sequence, sync_config())  # left images only, no depth needed
    assert run.states == [STATE_INITIALIZING] * 3


# --- a monocular run on a synthetic world -------------------------------------------------------
@pytest.fixture(scope="module")
def revisit_run():
    """The first 10 s of robot 2 of the synthetic ``revisit`` world (a ground robot driving down a
    corridor and turning) as a monocular camera."""
    from coop_slam.synthetic.generate import generate

    # In the worlds' cache, as the demos' worlds: rendered once per machine, not once per run.
    folder = generate("revisit", seed=0, duration_s=10.0)
    seq = read_synthetic(folder).sequences[2]
    seq = dataclasses.replace(seq, camera=dataclasses.replace(seq.camera, sensor="mono"))
    messages = []
    run = run_sequence(seq, sync_config(), progress=lambda i, n, r: messages.append(r.message))
    return seq, run, messages


@pytest.mark.slow
def test_monocular_odometry_on_a_synthetic_world(revisit_run):
    seq, run, messages = revisit_run
    gt = seq.frame_poses()
    # Initialized within 1 s of moving, then never lost, in one map segment.
    moved = np.linalg.norm(gt[:, :3, 3] - gt[0, :3, 3], axis=1) > 1e-3
    t_move = seq.stamps_s[np.argmax(moved)]
    first = int(np.argmax(run.ok))
    t_init = seq.stamps_s[first] - t_move
    assert run.ok[first:].all() and run.n_segments == 1, "never lost"
    assert t_init <= 1.0, f"initialized {t_init:.2f} s after moving"
    assert messages[first].startswith("map initialized") and "no metric scale" in messages[first]
    assert all(m.startswith("initializing: ") for m in messages[:first])
    # Sim(3)-aligned ATE at most 1 % of the path; the scale holds along it.
    ok = run.ok
    ate, scale = sim3_ate(run.stamps_s[ok], run.poses_se3[ok], gt[ok])
    length = path_length(gt[ok])
    half = first + (len(gt) - first) // 2
    drift = scale_of(run.poses_se3[half:], gt[half:]) / scale_of(run.poses_se3[first:half],
                                                                 gt[first:half]) - 1  # fmt: skip
    print(
        f"monocular revisit robot 2: initialized {t_init:.2f} s after moving, ATE "
        f"{100 * ate:.2f} cm = {100 * ate / length:.2f} % of {length:.2f} m, "
        f"{scale:.3f} m per map unit, scale drift {100 * drift:+.1f} % (second vs first half)"
    )
    assert ate <= 0.01 * length
    assert abs(drift) < 0.03
    # The map grew by triangulation: far more points than the two views gave, all keyframes
    # keep their points seen twice at least, and keyframes kept coming.
    assert run.mapping_stats["triangulated"] > 5000
    assert run.keyframes_created > 10 and len(run.keyframes) > 5
    # Local mapping runs inside track() here, so it is always free: keyframes still come at
    # most every keyframe_min_frames_mono frames (every other frame became one without it).
    frames = len(run.stamps_s) - first
    assert run.keyframes_created <= 2 + frames / VoConfig().for_sensor("mono").keyframes.min_frames
    assert all(kf.depths_m.max() == 0 for kf in run.keyframes)
    assert sum((kf.map_point_ids > 0).sum() for kf in run.keyframes) > 100 * len(run.keyframes)


def test_a_monocular_maps_ate_is_taken_after_a_similarity():
    """A map at half the true scale: its SE(3) ATE is its scale error, its Sim(3) ATE none."""
    from coop_slam.evaluation.vo_run import ate_rmse
    from coop_slam.geometry import se3

    angles = np.linspace(0, np.pi, 20)
    gt = np.stack([se3(t=[2 * np.cos(a), 2 * np.sin(a), 0.1 * a]) for a in angles])
    half = gt.copy()
    half[:, :3, 3] *= 0.5
    stamps = np.arange(20) * 0.1
    assert ate_rmse(stamps, half, gt) > 0.3
    assert ate_rmse(stamps, half, gt, correct_scale=True) < 1e-6
