"""ATE/RPE wrappers around evo, team ATE with one alignment, merge error."""

import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_slam.evaluation import (
    EvaluationError,
    ate,
    merge_error,
    noise_split,
    rotation_gain,
    rpe_rmse,
    team_ate,
)
from coop_slam.geometry import invert, se3, se3_from_quat
from coop_slam.timestamps import associate

FIXTURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fixtures")


def _circle(n=50, r=2.0):
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        poses.append(
            se3_from_quat([r * np.cos(a), r * np.sin(a), 0.5], [0, 0, np.sin(a / 2), np.cos(a / 2)])
        )
    return np.arange(n) * 0.1 + 1.0, np.array(poses)


def test_ate_is_zero_for_a_rigidly_moved_copy_and_sees_noise():
    stamps, gt = _circle()
    T = se3_from_quat([1, -2, 3], [0.2, 0.1, 0.4, 0.9])
    moved = np.array([T @ p for p in gt])
    res = ate(stamps + 0.005, moved, stamps, gt)
    assert res.rmse_m < 1e-6 and res.count == 50
    noisy = moved.copy()
    noisy[:, :3, 3] += np.random.default_rng(0).normal(0, 0.01, (50, 3))
    assert 0.005 < ate(stamps, noisy, stamps, gt).rmse_m < 0.02
    assert rpe_rmse(stamps, moved, stamps, gt) < 1e-6
    with pytest.raises(EvaluationError, match="match ground truth"):
        ate(stamps + 5.0, moved, stamps, gt)


def test_team_ate_uses_one_alignment():
    stamps, gt = _circle()
    est = {1: (stamps, gt.copy()), 2: (stamps, gt.copy())}
    gts = {1: (stamps, gt), 2: (stamps, gt)}
    assert team_ate(est, gts).rmse_m < 1e-6
    # Robot 2 expressed in a wrongly placed frame: per-robot alignment would hide it, team ATE not.
    off = se3(t=[0.5, 0, 0])
    est[2] = (stamps, np.array([off @ p for p in gt]))
    assert ate(*est[2], *gts[2]).rmse_m < 1e-6
    team = team_ate(est, gts)
    assert team.rmse_m > 0.2
    # Each robot's share: its keyframes' errors under the one alignment, on its own timeline.
    shares = team.robot_rmse()
    assert set(shares) == {1, 2} and min(shares.values()) > 0.1
    n = np.bincount(team.robot_ids)[1:]
    assert team.rmse_m**2 * n.sum() == pytest.approx(shares[1] ** 2 * n[0] + shares[2] ** 2 * n[1])
    np.testing.assert_allclose(team.robot_stamps_s[team.robot_ids == 2], stamps)
    # A third robot with a small error of its own keeps a small share.
    bumpy = gt.copy()
    bumpy[:, 2, 3] += 0.01
    est, gts = {1: (stamps, gt), 3: (stamps + 7.0, bumpy)}, {1: (stamps, gt), 3: (stamps + 7, gt)}
    shares = team_ate(est, gts).robot_rmse()
    assert shares[3] < 0.011 and shares[1] < 0.011


def test_associate_pairs_nearest_stamps_within_the_tolerance():
    i, j = associate([1.0, 2.0, 3.5], [0.99, 2.01, 3.0], 0.02)
    assert list(i) == [0, 1] and list(j) == [0, 1]
    # An unsorted reference; a tie goes to the earlier reference stamp.
    i, j = associate([2.0, 1.0], [3.0, 1.5, 0.99, 2.5], 0.6)
    assert list(i) == [0, 1] and list(j) == [1, 2]
    # One to one: a reference stamp serves its first query only (TUM colour/depth pairs).
    i, j = associate([1.0, 1.01, 2.0], [1.005, 2.0], 0.02, one_to_one=True)
    assert list(i) == [0, 2] and list(j) == [0, 1]
    assert [len(a) for a in associate([], [1.0], 0.1)] == [0, 0]


def test_merge_error():
    A = se3_from_quat([1, 0, 0], [0, 0, 0, 1])
    B = se3_from_quat([0, 1, 0], [0, 0, 0.1, 1])
    dt, dr = merge_error(invert(A) @ B, A, B)
    assert dt < 1e-9 and dr < 1e-6


def test_straight_line_falls_back_to_origin_alignment():
    stamps = np.arange(5) + 1.0
    line = np.array([se3(t=[0.5 * k, 0, 0]) for k in range(5)])
    moved = np.array([se3_from_quat([1, 2, 3], [0, 0, 0.3, 1]) @ p for p in line])
    assert ate(stamps, moved, stamps, line).rmse_m < 1e-6
    # ... and a monocular map of a straight drive: its scale and error are the line's (evo's
    # Umeyama refuses the degenerate covariance).
    scaled = line.copy()
    scaled[:, :3, 3] *= 0.25
    scaled[2, 1, 3] += 0.01  # 4 cm in metres
    res = ate(stamps, scaled, stamps, line, correct_scale=True)
    assert res.scale == pytest.approx(4.0, rel=0.01) and 0.01 < res.rmse_m < 0.04
    for still in ((np.array([np.eye(4)] * 5), line), (line, np.array([np.eye(4)] * 5))):
        with pytest.raises(EvaluationError, match="stands still"):
            ate(stamps, still[0], stamps, still[1], correct_scale=True)


def test_a_run_recorded_before_packed_messages_still_reads(tmp_path):
    """A bag's keyframe messages are read with the bag's own definition: a run recorded before
    the message gained fields (packed arrays, moves in steps, signature counts) still reads, and
    so does one recorded before each kind had its own message (test/fixtures/legacy_keyframes)."""
    import genpy.dynamic
    import rosbag
    import rospy

    from coop_slam.ros.run_recorder import run_data_from_bag

    with rosbag.Bag(os.path.join(FIXTURES, "legacy_keyframes.bag")) as bag:
        (legacy_text,) = {c.msg_def for c in bag._get_connections()}
    run = run_data_from_bag(os.path.join(FIXTURES, "legacy_keyframes.bag"), [1, 2])
    assert len(run.robots[2].keyframes) == 7 and len(run.robots[2].keyframe_points[1]) > 500
    KeyFrame = genpy.dynamic.generate_dynamic("coop_slam/KeyFrame", legacy_text)[
        "coop_slam/KeyFrame"
    ]
    new_fields = ("int16[] moves_q", "uint8[] bow_counts", "uint8[] packed")
    main, _, deps = KeyFrame._full_text.partition("\n" + "=" * 80 + "\n")
    old_main = "\n".join(f for f in main.splitlines() if not f.startswith(new_fields))
    old_text = old_main + "\n" + "=" * 80 + "\n" + deps
    OldKeyFrame = genpy.dynamic.generate_dynamic("coop_slam/KeyFrame", old_text)[
        "coop_slam/KeyFrame"
    ]
    assert OldKeyFrame._md5sum != KeyFrame._md5sum and not hasattr(OldKeyFrame(), "packed")
    bag_path = str(tmp_path / "run.bag")
    with rosbag.Bag(bag_path, "w") as bag:
        for k in range(1, 4):
            msg = OldKeyFrame(robot_id=1, keyframe_id=k, action=0)
            msg.header.frame_id, msg.header.stamp = "robot_1/map", rospy.Time.from_sec(k)
            msg.pose.orientation.w = 1.0
            msg.pose.position.x = 0.1 * k
            msg.keypoints, msg.depths_m, msg.octaves = [320.0, 240.0], [2.0], b"\x00"
            msg.camera.fx = msg.camera.fy = 500.0
            msg.camera.cx, msg.camera.cy = 320.0, 240.0
            bag.write("/robot_1/keyframes", msg, rospy.Time.from_sec(k))
    run = run_data_from_bag(bag_path, [1])
    assert sorted(run.robots[1].keyframes) == [1, 2, 3]
    np.testing.assert_allclose(run.robots[1].keyframes[3][1][0, 3], 0.3)
    np.testing.assert_allclose(run.robots[1].keyframe_points[2], [[0.0, 0.0, 2.0]])


def test_bag_of_a_run_gives_keyframes_merges_team_paths_and_topic_sizes(tmp_path):
    """RunRecorder fed from a bag (what scripts/evaluate reads): a malformed pose is skipped; a
    merge's registration error is its cameras' relative pose against the truth, unchanged when
    local BA moves a matched keyframe after the merge, and known when the client culled a matched
    keyframe before the merge event arrived."""
    pytest.importorskip("coop_slam.msg", reason="the catkin workspace is not sourced")
    import rosbag
    import rospy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path

    from coop_slam.evaluation.merge_accuracy import local_merge_error
    from coop_slam.msg import FrameStats, MergeEvent
    from coop_slam.ros.convert import pose_to_msg, transform_to_msg
    from coop_slam.ros.run_recorder import run_data_from_bag
    from coop_slam.ros.wire_bridge import to_ros
    from coop_slam.wire.codec import encode

    def keyframe_to_msg(rec, frame_id):
        return to_ros(encode(rec, frame_id=frame_id))

    from coop_slam.wire.record import ACTION_REMOVE, ACTION_UPDATE
    from helpers import make_keyframe

    bag_path = str(tmp_path / "run.bag")
    stamps, gt = _circle(5)
    with rosbag.Bag(bag_path, "w") as bag:
        for k in range(5):
            kf = make_keyframe(robot_id=2, keyframe_id=k + 1, seed=k)
            kf.T_map_cam, kf.stamp_s = gt[k], stamps[k]
            bag.write(
                "/robot_2/keyframes",
                keyframe_to_msg(kf, "robot_2/map"),
                rospy.Time.from_sec(stamps[k]),
            )
        kf_a = make_keyframe(robot_id=1, keyframe_id=3, seed=9)
        kf_a.T_map_cam, kf_a.stamp_s = gt[0], stamps[0]
        bag.write("/robot_1/keyframes", keyframe_to_msg(kf_a, "robot_1/map"), rospy.Time(1.0))
        culled = make_keyframe(robot_id=1, keyframe_id=3, seed=9)
        culled.action, culled.stamp_s = ACTION_REMOVE, 0.0
        bag.write("/robot_1/keyframes", keyframe_to_msg(culled, "robot_1/map"), rospy.Time(1.2))
        path = Path()
        path.header.frame_id = "world"
        for k in range(5):
            ps = PoseStamped(pose=pose_to_msg(gt[k]))
            ps.header.stamp, ps.header.seq = rospy.Time.from_sec(stamps[k]), k + 1
            path.poses.append(ps)
        path.poses[2].pose.orientation.w = float("nan")
        bag.write("/team_map/robot_2/path", path, rospy.Time.from_sec(2.0))
        path.header.frame_id = "robot_2/map"  # the client's own (its latest counts)
        bag.write("/robot_2/path", path, rospy.Time.from_sec(2.0))
        path.poses = path.poses[:2]
        bag.write("/robot_2/path", path, rospy.Time.from_sec(2.1))
        merge = MergeEvent(
            type="rendezvous",
            robot_a=1,
            robot_b=2,
            keyframe_a=3,
            keyframe_b=4,
            T_mapA_mapB=transform_to_msg(np.eye(4)),
            T_camA_camB=transform_to_msg(invert(gt[0]) @ gt[3]),
            inliers=50,
            group=[1, 2],
        )
        merge.header.stamp = rospy.Time.from_sec(1.5)
        stats = FrameStats(robot_id=2, tracking_ok=True)
        stats.header.stamp = rospy.Time.from_sec(2.5)  # the newest frame when it was published
        bag.write("/robot_2/frame_stats", stats, rospy.Time.from_sec(2.5))
        bag.write("/merge_events", merge, rospy.Time.from_sec(2.6))
        moved = make_keyframe(robot_id=2, keyframe_id=4, seed=3)
        moved.T_map_cam, moved.stamp_s = se3(t=[0.05, 0, 0]) @ gt[3], stamps[3]
        moved.action = ACTION_UPDATE
        bag.write("/robot_2/keyframes", keyframe_to_msg(moved, "robot_2/map"), rospy.Time(1.6))
    run = run_data_from_bag(bag_path, [1, 2])
    gts = {1: (stamps, gt), 2: (stamps, gt)}
    dt, dr = local_merge_error(run.merges[0], run, gts)
    assert dt < 1e-6 and dr < 1e-4
    assert 3 not in run.robots[1].keyframes  # culled before the merge event came
    del gts[1]
    assert local_merge_error(run.merges[0], run, gts) is None  # no truth for robot 1
    r = run.robots[2]
    assert sorted(r.keyframes) == [1, 2, 3, 4, 5] and len(r.kf_bytes) == 6  # with the update
    assert list(r.kf_kinds) == ["whole"] and r.kf_kinds["whole"][0] == 6
    assert r.kf_kinds["whole"][1] == sum(n for _, n in r.kf_bytes)
    assert np.allclose(r.keyframes[4][1], moved.T_map_cam)
    # Each keyframe's 3D from depth (the report's overlap agreement), one point per keypoint.
    assert all(len(r.keyframe_points[k]) == 50 for k in (1, 2, 3, 5))
    assert sorted(r.team_keyframes) == [1, 2, 4, 5]  # the NaN pose is dropped, not stored
    assert [(k, t) for k, t, _ in r.path] == [(1, stamps[0]), (2, stamps[1])]
    assert np.allclose(r.path[1][2], gt[1])
    assert run.merges[0]["type"] == "rendezvous" and run.merges[0]["stamp_s"] == 1.5
    assert run.merges[0]["published_s"] == 2.5
    assert len(run.topic_bytes["/robot_2/keyframes"]) == 6
    with pytest.raises(EvaluationError, match="bag not found"):
        run_data_from_bag(str(tmp_path / "missing.bag"), [1])


def test_sensor_bag_gives_robots_and_ground_truth_and_evaluates_without_it(tmp_path):
    """read_bag_input (scripts/demo --bag): robots from their colour topics, ground truth from
    robot_k/ground_truth/pose where present (a NaN sample skipped); a robot without ground truth
    gets null accuracy fields and its keyframes are still written and plotted."""
    import rosbag
    import rospy
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Image

    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.evaluation.run_report import evaluate_run
    from coop_slam.ros.convert import pose_to_msg
    from coop_slam.ros.run_recorder import read_bag_input

    bag_path = str(tmp_path / "sensors.bag")
    stamps, gt = _circle(6)
    with rosbag.Bag(bag_path, "w") as bag:
        for k in range(6):
            t = rospy.Time.from_sec(stamps[k])
            for rid in (1, 3):
                img = Image(height=1, width=1, encoding="mono8", step=1, data=b"\x00")
                img.header.stamp = t
                bag.write(f"/robot_{rid}/camera/color/image_raw", img, t)
            ps = PoseStamped(pose=pose_to_msg(gt[k]))
            ps.header.stamp = t
            if k == 2:
                ps.pose.position.x = float("nan")
            bag.write("/robot_1/ground_truth/pose", ps, t)
    inputs = read_bag_input(bag_path)
    assert inputs.robot_ids == [1, 3] and inputs.frames == 12
    assert len(inputs.gts[1][0]) == 5 and len(inputs.gts[3][0]) == 0
    assert inputs.end_s - inputs.start_s == pytest.approx(stamps[-1] - stamps[0], abs=1e-6)

    run = RunData()
    for rid in (1, 3):
        run.robots[rid] = RobotRun(frames=6, keyframes={k: (stamps[k], gt[k]) for k in range(6)})
    report = evaluate_run(run, inputs.gts, out_dir=str(tmp_path / "out"))
    by_id = {r["id"]: r for r in report["robots"]}
    assert by_id[1]["ate_rmse_m"] == pytest.approx(0.0, abs=1e-6)
    assert by_id[3]["ate_rmse_m"] is None and by_id[3]["path_length_m"] is None
    assert by_id[3]["keyframes"] == 6
    assert (tmp_path / "out" / "trajectories" / "robot_3_keyframes.txt").exists()
    assert (tmp_path / "out" / "trajectories.png").exists()

    with rosbag.Bag(str(tmp_path / "other.bag"), "w") as bag:
        bag.write("/camera/rgb/image_color", Image(), rospy.Time.from_sec(1.0))
    with pytest.raises(EvaluationError, match="no camera topics.*/camera/rgb/image_color"):
        read_bag_input(str(tmp_path / "other.bag"))


def test_report_pools_the_single_robot_ates_as_a_perfect_stitching_would_score():
    pytest.importorskip("rosbag")
    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.evaluation.run_report import evaluate_run

    stamps, gt = _circle(40)
    rng = np.random.default_rng(3)
    run, gts, sizes = RunData(), {}, {1: 0.002, 2: 0.01}
    for rid, sigma in sizes.items():
        est = gt.copy()
        est[:, :3, 3] += rng.normal(0, sigma, (40, 3))
        kfs = {k: (stamps[k], est[k]) for k in range(40)}
        run.robots[rid] = RobotRun(frames=40, keyframes=kfs, team_keyframes=dict(kfs))
        gts[rid] = (stamps, gt)
    report = evaluate_run(run, gts)
    e = [r["ate_rmse_m"] for r in report["robots"]]
    assert report["single_ate_pooled_m"] == pytest.approx(np.sqrt((e[0] ** 2 + e[1] ** 2) / 2))
    assert report["single_ate_pooled_m"] > np.mean(e)  # the mean of the two weighs them alike
    # Only robots the team ATE covers are pooled: one with no place in world is left out.
    run.robots[2].team_keyframes = {}
    report = evaluate_run(run, gts)
    assert report["single_ate_pooled_m"] is None and report["team_ate_rmse_m"] is None


def test_low_bandwidth_team_ate_is_over_the_same_keyframes_as_the_robots_own():
    """The server holds whole (and optimizes) only the keyframes it asked for: the team ATE places
    the others as the server placed their nearest whole keyframe, so it is over every keyframe,
    as the pooled ATE is (over the two the server holds it read as if the team map were far
    better than its parts)."""
    pytest.importorskip("rosbag")
    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.evaluation.run_report import evaluate_run

    stamps, gt = _circle(40)
    rng = np.random.default_rng(5)
    run, gts = RunData(server_stats={"pull": {"held": {"1": 2, "2": 2}}}), {}
    for rid in (1, 2):
        est = gt.copy()
        est[:, :3, 3] += rng.normal(0, 0.01, (40, 3))
        kfs = {k: (stamps[k], est[k]) for k in range(40)}
        held = {k: (stamps[k], gt[k]) for k in (5, 30)}  # exact, as if optimized perfectly
        run.robots[rid] = RobotRun(frames=40, keyframes=kfs, team_keyframes=held)
        run.robots[rid].T_world_map = np.eye(4)
        gts[rid] = (stamps, gt)
    report = evaluate_run(run, gts)
    assert [r["team_keyframes_optimized"] for r in report["robots"]] == [2, 2]
    # over all 80 keyframes: about the robots' own error, not the two exact ones' zero
    assert report["team_ate_rmse_m"] > 0.5 * report["single_ate_pooled_m"]
    run.server_stats = {}  # the default mode: the server's poses alone
    assert evaluate_run(run, gts)["team_ate_rmse_m"] < 1e-6


@pytest.mark.parametrize("units_per_m", [None, 2.5])
def test_keyframes_of_a_map_segment_the_team_map_does_not_hold_are_not_placed_in_world(
    units_per_m,
):
    """A robot lost tracking and started a new map segment, which merged: the team map holds
    that segment's keyframes (some of them whole); the lost segment's keyframes, in a map frame
    of their own, are not placed in world by the new segment's (they were, 1.3 m off); the
    others are, a monocular map's offsets (``units_per_m``) in the team's metres (the sensor as
    the run says it, not as the recording did)."""
    pytest.importorskip("rosbag")
    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.evaluation.run_report import evaluate_run
    from coop_slam.team.map_scale import scale_translation

    stamps, gt = _circle(40)
    run, gts = RunData(server_stats={"pull": {"held": {"1": 40, "2": 4}}}), {}
    T_map1_map0 = se3_from_quat([3.0, -2.0, 0.0], [0, 0, 0.6, 0.8])  # the lost map's frame
    for rid in (1, 2):
        kfs = {k: (stamps[k], gt[k]) for k in range(40)}
        team = dict(kfs)
        if rid == 2:
            kfs = {k: (t, T_map1_map0 @ T if k < 20 else T) for k, (t, T) in kfs.items()}
            team = {k: kfs[k] for k in (22, 28, 34, 39)}
            if units_per_m:
                kfs = {k: (t, scale_translation(T, units_per_m)) for k, (t, T) in kfs.items()}
            run.robots[rid] = RobotRun(frames=40, keyframes=kfs, team_keyframes=team)
            run.robots[rid].keyframe_segments = {k: int(k >= 20) for k in kfs}
            run.robots[rid].map_scale = 1.0 / units_per_m if units_per_m else 1.0
        else:
            run.robots[rid] = RobotRun(frames=40, keyframes=kfs, team_keyframes=team)
        run.robots[rid].T_world_map = np.eye(4)
        gts[rid] = (stamps, gt)
    sensors = {1: "rgbd", 2: "mono" if units_per_m else "rgbd"}
    report = evaluate_run(run, gts, sensors=sensors)
    assert report["team_ate_rmse_m"] < 1e-6


def test_report_judges_the_clients_published_path_against_the_truth_and_the_team_map(tmp_path):
    """path_ate_rmse_m: the client's last /robot_k/path (base_link poses, placed at the camera
    by the mount); path_team_gap_m: its keyframes in world against the server's, by stamp."""
    pytest.importorskip("rosbag")
    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.evaluation.run_report import evaluate_run
    from coop_slam.team.map_scale import scale_translation

    stamps, gt = _circle(30)
    T_base_cam = se3(
        Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix(), [0.1, 0, 0.5]
    )
    T_world_map = se3(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [1.0, -2.0, 0.0])
    rng = np.random.default_rng(4)
    odom = gt.copy()
    odom[:, :3, 3] += rng.normal(0, 0.01, (30, 3))  # the client's odometry
    team = gt.copy()
    team[:, :3, 3] += rng.normal(0, 0.002, (30, 3))  # the server's optimized poses (world)
    kfs = {k: (stamps[k], invert(T_world_map) @ odom[k]) for k in range(30)}

    def report_with(path_cam, map_scale=1.0, segments=None, first=0, out_dir=None):
        run = RunData()
        run.robots[1] = RobotRun(
            frames=30,
            keyframes=kfs,
            team_keyframes={k + 1: (stamps[k], team[k]) for k in range(30)},  # by keyframe id
            T_world_map=T_world_map,
            map_scale=map_scale,
            keyframe_segments=segments or {},
            path=[
                (k + 1, stamps[k], P @ invert(T_base_cam))
                for k, P in enumerate(path_cam, start=first)
            ],
        )
        return evaluate_run(run, {1: (stamps, gt)}, out_dir=out_dir, T_base_cam=T_base_cam)[
            "robots"
        ][0]

    # A client showing the team map's poses: as accurate as the server, no gap.
    shared = report_with([invert(T_world_map) @ T for T in team])
    assert shared["path_ate_rmse_m"] == pytest.approx(shared["server_ate_rmse_m"], rel=1e-6)
    assert shared["path_team_gap_m"] < 1e-9
    # Two map segments (keyframes 1-20, 21-30): the latest T_world_map places the second; the
    # first, in another frame, is judged alone, as the robot's own ATE is.
    apart = se3(t=[1.0, 0.0, 0.0])
    two = report_with(
        [invert(T_world_map) @ (apart if k < 20 else np.eye(4)) @ T for k, T in enumerate(team)],
        segments={k + 1: int(k >= 20) for k in range(30)},
    )
    assert two["path_team_gap_m"] < 1e-9 and two["path_ate_rmse_m"] < 0.005
    # A restarted client: its path holds its second segment only (no ATE of the first).
    later = report_with(
        [invert(T_world_map) @ T for T in team[20:]],
        segments={k + 1: int(k >= 20) for k in range(30)},
        first=20,
        out_dir=str(tmp_path),  # its picture too
    )
    assert later["path_ate_rmse_m"] is None and later["path_team_gap_m"] < 1e-9
    # A monocular map: the path in its own units, placed in metres by the map's scale.
    halved = report_with([scale_translation(invert(T_world_map) @ T, 0.5) for T in team], 2.0)
    assert halved["path_team_gap_m"] < 1e-9
    # One showing its odometry: as accurate as that, centimetres from the team map.
    own = report_with(list(kfs[k][1] for k in range(30)))
    assert own["path_ate_rmse_m"] == pytest.approx(own["ate_rmse_m"], rel=1e-6)
    assert own["path_team_gap_m"] > 0.005
    run = RunData()
    run.robots[1] = RobotRun(frames=30, keyframes=kfs)
    entry = evaluate_run(run, {1: (stamps, gt)}, T_base_cam=T_base_cam)["robots"][0]
    assert entry["path_ate_rmse_m"] is None and entry["path_team_gap_m"] is None  # no path


def test_keyframe_errors_are_each_poses_distance_after_the_ates_alignment(tmp_path):
    from coop_slam.evaluation.plots import keyframe_errors, plot_path_errors

    stamps, gt = _circle(20)
    est = gt.copy()
    est[5, :3, 3] += [0.05, 0.0, 0.0]
    moved = np.einsum("ij,njk->nik", se3(t=[1.0, 2.0, 0.0]), est)
    t, err, res = keyframe_errors(stamps, moved, stamps, gt)
    assert np.array_equal(t, stamps) and int(np.argmax(err)) == 5 and err[5] > 0.04
    assert np.sqrt(np.mean(err**2)) == pytest.approx(res.rmse_m)
    assert keyframe_errors(stamps[:2], moved[:2], stamps, gt) is None  # too few to align
    assert keyframe_errors(np.zeros(0), np.zeros(0), stamps, gt) is None  # none at all
    with pytest.raises(EvaluationError, match="need at least 3"):
        ate([], [], stamps, gt)
    series = {1: [("odometry", stamps, moved), ("short", stamps[:2], moved[:2])], 2: []}
    plot_path_errors(str(tmp_path), series, {1: (stamps, gt), 2: (stamps, gt)})
    assert (tmp_path / "path_errors.png").stat().st_size > 0


def test_merge_latency_counts_from_the_first_shared_view_of_its_kind():
    """Rendezvous latency from the first co-observation, place recognition from the first revisit
    (either direction); a marker sighting without a shared scene is no start."""
    from coop_slam.evaluation.run_report import _first_evidence

    overlap = {
        "rendezvous": [{"robots": [2, 1], "stamp_s": 19.6}],
        "revisit": [
            {"robot": 2, "of_robot": 1, "stamp_s": 21.6, "earlier_stamp_s": 19.6},
            {"robot": 1, "of_robot": 2, "stamp_s": 18.6, "earlier_stamp_s": 15.8},
        ],
        "marker_sightings": [{"observer": 1, "target": 2, "stamp_s": 4.8}],
        "first_overlap": [{"robots": [1, 2], "stamp_s": 4.8, "kind": "marker"}],
    }
    assert _first_evidence(overlap, "rendezvous", 1, 2) == 19.6
    assert _first_evidence(overlap, "place_recognition", 2, 1) == 18.6
    only_revisit = dict(overlap, rendezvous=[])
    assert _first_evidence(only_revisit, "rendezvous", 1, 2) == 18.6
    assert _first_evidence(overlap, "rendezvous", 1, 3) is None
    assert _first_evidence(None, "rendezvous", 1, 2) is None


def test_noise_split_tells_each_trajectory_its_own_error():
    _, truth = _circle(n=2000, r=2.0)
    rng = np.random.default_rng(1)

    def perturbed(sigma_m, sigma_rad):
        out = truth.copy()
        for k in range(len(out)):
            rvec = rng.normal(0, sigma_rad, 3)
            out[k] = out[k] @ se3(Rotation.from_rotvec(rvec).as_matrix(), rng.normal(0, sigma_m, 3))
        return out

    sigmas = {"a": (0.002, 0.002), "b": (0.003, 0.003), "gt": (0.005, 0.004)}
    trajs = {n: perturbed(*s) for n, s in sigmas.items()}
    trajs["b"][100] = np.nan  # a lost frame is left out, not an error
    split = noise_split(trajs, step=5)
    assert split.pairs == 2000 - 5 - 2
    for n, (s_m, s_rad) in sigmas.items():
        # Relative motion over two independently perturbed poses: sqrt(2) x per pose, 3 axes.
        assert split.trans_m[n] == pytest.approx(np.sqrt(6) * s_m, rel=0.2)
        assert split.rot_deg[n] == pytest.approx(np.degrees(np.sqrt(6) * s_rad), rel=0.2)
    with pytest.raises(EvaluationError, match="exactly 3"):
        noise_split({"a": truth, "b": truth}, step=5)
    with pytest.raises(EvaluationError, match="same frames"):
        noise_split({"a": truth, "b": truth, "c": truth[:-1]}, step=5)


def test_rotation_gain_finds_rotations_scaled_about_the_image_axes():
    # A camera turning about all three of its axes; the "estimate" turns 20 % less about x and y
    # between frames (what a too-long focal length does) and exactly as much about z.
    rng = np.random.default_rng(2)
    gain = np.array([0.8, 0.8, 1.0])
    truth, est = [np.eye(4)], [np.eye(4)]
    for _ in range(300):
        w = rng.normal(0, np.radians(1.0), 3)
        t = rng.normal(0, 0.01, 3)
        truth.append(truth[-1] @ se3(Rotation.from_rotvec(w).as_matrix(), t))
        est.append(est[-1] @ se3(Rotation.from_rotvec(gain * w).as_matrix(), t))
    truth, est = np.array(truth), np.array(est)
    assert rotation_gain(est, truth, step=1) == pytest.approx(gain, abs=1e-3)
    assert rotation_gain(truth, truth, step=5) == pytest.approx([1, 1, 1], abs=1e-9)
    est[10] = np.nan  # a lost frame is left out
    assert rotation_gain(est, truth, step=1) == pytest.approx(gain, abs=1e-3)
    # Ground truth that never turns about an axis says nothing about its gain.
    planar = truth.copy()
    planar[:, :3, :3] = np.eye(3)
    assert np.isnan(rotation_gain(planar, planar, step=1)).all()
    with pytest.raises(EvaluationError, match="same frames"):
        rotation_gain(est[:-1], truth, step=1)
    with pytest.raises(EvaluationError, match="at least 1 frame"):
        rotation_gain(est, truth, step=0)


def test_a_robots_new_map_segment_merging_with_its_old_one_is_judged_at_both_keyframes():
    """A merge of a robot with itself (a restarted client's new map segment with its old one):
    each side's keyframe stamp is its own."""
    from coop_slam.evaluation.merge_accuracy import local_merge_error

    stamps = np.arange(0.0, 10.0, 0.5)
    gt = (stamps, np.array([se3_from_quat([0.3 * t, 0.0, 0.0], [0, 0, 0, 1]) for t in stamps]))
    true = invert(gt[1][2]) @ gt[1][14]
    m = {
        "robot_a": 2,
        "robot_b": 2,
        "keyframe_a": 3,
        "keyframe_b": 15,
        "keyframe_stamps": {"a": 1.0, "b": 7.0},
        "T_camA_camB": true,
    }
    t_err, r_err = local_merge_error(m, None, {2: gt})
    assert t_err < 1e-9 and r_err < 1e-6


def test_frame_stats_count_dropped_frames_and_a_mapper_behind_the_camera():
    """Per robot: frames tracked, frames a busy client skipped, and frames tracked while local
    mapping held more than one keyframe (the mapper falling behind), with its largest backlog.
    Stats without a frame (stamp 0: keyframes the uplink sent after the last frame) count the
    keyframes sent, not a frame."""
    pytest.importorskip("coop_slam.msg", reason="the catkin workspace is not sourced")
    import rospy

    from coop_slam.msg import FrameStats
    from coop_slam.ros.run_recorder import RunRecorder

    rec = RunRecorder([1])
    for k, (dropped, backlog) in enumerate(
        [(False, 0), (True, 0), (False, 1), (False, 3), (False, 2)]
    ):
        msg = FrameStats(robot_id=1, tracking_ok=True, track_ms=10.0, dropped=dropped)
        msg.header.stamp = rospy.Time.from_sec(1.0 + 0.1 * k)
        msg.mapping_backlog, msg.keyframes_sent = backlog, k
        rec.feed("/robot_1/frame_stats", msg, 0.1 * k, 40)
    rec.feed("/robot_1/frame_stats", FrameStats(robot_id=1, keyframes_sent=6), 0.6, 40)
    r = rec.run.robots[1]
    assert (r.frames, r.frames_dropped) == (4, 1)
    assert (r.mapping_backlog_max, r.frames_mapping_behind) == (3, 2)
    assert r.keyframes_sent_sessions == [6] and rec.newest_frame_s == pytest.approx(1.4)


def test_bandwidth_gives_uplink_and_downlink_per_robot():
    """Uplink = a robot's keyframe messages; downlink = the server's corrections and acks to it."""
    from coop_slam.evaluation.bandwidth import bandwidth, downlink_kBps, uplink_by_kind
    from coop_slam.evaluation.report import _fmt
    from coop_slam.evaluation.run_data import RobotRun, RunData

    run = RunData(robots={1: RobotRun(), 2: RobotRun()}, duration_s=10.0)
    run.robots[1].kf_bytes = [(0.5, 40_000), (1.5, 60_000)]
    run.robots[2].kf_bytes = [(2.0, 20_000)]
    run.robots[1].kf_kinds = {"whole": (1, 40_000), "signature": (1, 60_000)}
    run.topic_bytes["/robot_1/correction"] = [(3.0, 5_000), (4.0, 4_000)]
    run.topic_bytes["/robot_1/keyframe_ack"] = [(3.0, 1_000)]
    bw = bandwidth(run)
    assert bw["per_robot_kBps"] == pytest.approx((10.0 + 2.0) / 2)
    assert downlink_kBps(run, 1) == pytest.approx(1.0)
    assert downlink_kBps(run, 2) is None  # nothing recorded: unknown, not zero
    assert bw["downlink_per_robot_kBps"] == pytest.approx(1.0)
    by_kind = uplink_by_kind(run, run.robots[1])
    assert by_kind == {
        "signature": {"messages": 1, "kBps": pytest.approx(6.0)},
        "whole": {"messages": 1, "kBps": pytest.approx(4.0)},
    }
    assert uplink_by_kind(run, run.robots[2]) is None  # (a run recorded before kinds were)
    assert _fmt(by_kind) == "signature 1 (6.0 kB/s), whole 1 (4.0 kB/s)"


def test_a_similarity_merge_is_judged_against_the_maps_scale_around_its_keyframes():
    """Two monocular maps: robot 1's unit is 2 m; robot 2's scale drifts from 1 to 1.5 m per unit
    along its path. A merge whose scale is the true ratio at the matched keyframes is right
    there (local_scale_err), while the whole paths' ratio holds robot 2's drift (scale_err)."""
    pytest.importorskip("rosbag")
    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.evaluation.run_report import evaluate_run

    stamps, gt = _circle(40)
    metres_per_unit = {1: np.full(40, 2.0), 2: np.linspace(1.0, 1.5, 40)}
    run, gts = RunData(), {}
    for rid, unit in metres_per_unit.items():
        est = gt.copy()
        est[:, :3, 3] /= unit[:, None]
        kfs = {k: (stamps[k], est[k]) for k in range(40)}
        run.robots[rid] = RobotRun(
            frames=40, keyframes=kfs, keyframe_stamps=dict(enumerate(stamps)), sensor="mono"
        )
        gts[rid] = (stamps, gt)
    k1, k2 = 5, 30
    run.merges.append(
        {
            "type": "place_recognition",
            "robot_a": 1,
            "robot_b": 2,
            "keyframe_a": k1,
            "keyframe_b": k2,
            "keyframe_stamps": {"a": stamps[k1], "b": stamps[k2]},
            "stamp_s": stamps[k2],
            "T_mapA_mapB": np.eye(4),
            "T_camA_camB": np.eye(4),
            "scale": metres_per_unit[2][k2] / metres_per_unit[1][k1],
        }
    )
    merge = evaluate_run(run, gts)["merges"][0]
    assert abs(merge["local_scale_err"]) < 0.01, merge
    assert merge["scale_err"] > 0.05, merge  # robot 2's whole path is on average smaller
    # A merge off by 4 % at its keyframes is seen as such.
    run.merges[0]["scale"] *= 1.04
    merge = evaluate_run(run, gts)["merges"][0]
    assert merge["local_scale_err"] == pytest.approx(0.04, abs=0.01)


def test_a_link_of_monocular_maps_is_judged_in_metres():
    """Two monocular maps in their own units (robot 1's unit is 2 m, robot 2's 1.6 m), merged: the
    second map is in the first's units, and so is a link between them. A link that is exact in
    those units has no error in metres (it had the unit's share of its length before: issue
    #47), and one off by 1 cm in metres is seen as such."""
    pytest.importorskip("rosbag")
    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.evaluation.run_report import evaluate_run

    stamps, gt = _circle(40)
    metres_per_unit = {1: 2.0, 2: 1.6}
    run, gts = RunData(), {}
    for rid, unit in metres_per_unit.items():
        est = gt.copy()
        est[:, :3, 3] /= unit
        kfs = {k: (stamps[k], est[k]) for k in range(40)}
        run.robots[rid] = RobotRun(
            frames=40, keyframes=kfs, keyframe_stamps=dict(enumerate(stamps)), sensor="mono"
        )
        gts[rid] = (stamps, gt)
    run.merges.append(
        {
            "type": "place_recognition",
            "robot_a": 1,
            "robot_b": 2,
            "keyframe_a": 5,
            "keyframe_b": 30,
            "keyframe_stamps": {"a": stamps[5], "b": stamps[30]},
            "stamp_s": stamps[30],
            "T_mapA_mapB": np.eye(4),
            "T_camA_camB": np.eye(4),
            "scale": metres_per_unit[2] / metres_per_unit[1],
        }
    )
    run.server_stats["groups"] = [[1, 2]]
    T_camA_camB = invert(gt[8]) @ gt[9]
    T_camA_camB[:3, 3] /= metres_per_unit[1]  # in the group's units: robot 1's
    run.links.append(
        {
            "type": "link",
            "robots": [1, 2],
            "keyframe_stamps": [stamps[8], stamps[9]],
            "stamp_s": stamps[35],
            "T_camA_camB": T_camA_camB,
        }
    )
    link = evaluate_run(run, gts)["links"][0]
    assert link["count"] == 1 and link["trans_err_m"] < 1e-3, link
    run.links[0]["T_camA_camB"] = T_camA_camB @ se3(np.eye(3), [0.01 / metres_per_unit[1], 0, 0])
    link = evaluate_run(run, gts)["links"][0]
    assert link["trans_err_m"] == pytest.approx(0.01, abs=1e-3), link


def test_a_link_is_judged_in_the_units_of_its_time():
    """Robots 1 and 2 (monocular) merge at 5 s, a link between them at 10 s is in robot 1's
    units; an RGB-D robot joins at 15 s and the group is metric from then on. The link is judged
    in the units it was made in (read in metres, an exact link was 0.16 m off), and a link made
    after 15 s in metres."""
    from coop_slam.evaluation.merge_accuracy import link_errors, map_units
    from coop_slam.evaluation.run_data import RobotRun, RunData
    from coop_slam.team.map_scale import scale_translation

    stamps = np.arange(40) * 0.5
    gt = np.array([se3(np.eye(3), [0.3 * k, 0.1 * k, 0.0]) for k in range(40)])
    sensors = {1: "mono", 2: "mono", 3: "rgbd"}
    run = RunData()
    for rid, sensor in sensors.items():
        run.robots[rid] = RobotRun(frames=40, sensor=sensor)
    run.merges += [
        {"robot_a": 1, "robot_b": 2, "stamp_s": 5.0},
        {"robot_a": 1, "robot_b": 3, "stamp_s": 15.0},
    ]
    metres_per_unit = 2.0  # robot 1's
    T_camA_camB = invert(gt[8]) @ gt[9]
    in_units = scale_translation(T_camA_camB, 1.0 / metres_per_unit)
    for made_s, T in ((10.0, in_units), (16.0, T_camA_camB)):
        run.links = [
            {
                "type": "link",
                "robots": [1, 2],
                "keyframe_stamps": [stamps[8], stamps[9]],
                "stamp_s": made_s,
                "T_camA_camB": T,
            }
        ]
        gts = {r: (stamps, gt) for r in sensors}
        timeline = map_units(run, sensors)[1]
        pair = link_errors(run, gts, [[1, 2, 3]], timeline, {1: metres_per_unit, 2: 1.6})[0]
        assert pair["count"] == 1 and pair["trans_err_m"] < 1e-6, (made_s, pair)


def test_plots_align_a_monocular_map_with_its_scale():
    """A map in its own units (here 0.4 of a metre) aligned by a similarity, as its ATE is: the
    drawn keyframes lie on the ground truth (drawn without the scale they did not)."""
    from coop_slam.evaluation.metrics import ate
    from coop_slam.evaluation.plots import aligned

    stamps = np.arange(20, dtype=float)
    gt = np.array([se3(np.eye(3), [np.cos(0.3 * k), np.sin(0.3 * k), 0.1 * k]) for k in range(20)])
    T_est_gt = se3(Rotation.from_euler("z", 40, degrees=True).as_matrix(), [1.0, -2.0, 0.5])
    est = np.einsum("ij,njk->nik", T_est_gt, gt)
    est[:, :3, 3] *= 0.4
    res = ate(stamps, est, stamps, gt, correct_scale=True)
    np.testing.assert_allclose(aligned(res, est)[:, :3, 3], gt[:, :3, 3], atol=1e-6)


def test_top_views_draw_the_ground_plane_whatever_the_frame():
    """A z-up world's robots drive on x-y; a KITTI car, in its first camera's frame (y down),
    on x-z, even on a straight road that spreads less sideways than up and down: its plot is no
    longer a side view."""
    from coop_slam.evaluation.plots import top_view_axes

    # optical frame of a camera looking along +x of a z-up world: its y (image down) is -z
    R_forward_x = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    ground = np.tile(np.eye(4), (20, 1, 1))
    ground[:, :3, :3] = R_forward_x
    ground[:, :3, 3] = np.stack([np.linspace(0, 5, 20), np.zeros(20), np.full(20, 0.5)], 1)
    car = np.tile(np.eye(4), (20, 1, 1))  # KITTI: the camera's own frame, y down
    car[:, :3, 3] = np.stack([np.full(20, 0.3), np.linspace(0, 1.0, 20), np.linspace(0, 60, 20)], 1)
    assert top_view_axes(ground) == (0, 1)
    assert top_view_axes(car) == (0, 2)
