"""Pose-graph sharing on the client (coop_slam.vo.shared_poses): the team map's poses of a robot's
keyframes laid over its odometry."""

import numpy as np

from coop_slam.geometry import exp_so3, invert, se3, transform_error, transform_points
from coop_slam.vo.shared_poses import SharedPoses


def _odometry(n: int, rng) -> dict[int, np.ndarray]:
    return {
        k: se3(exp_so3(rng.normal(0, 0.05, 3)), np.array([0.3 * k, 0.02 * k, 0.0]))
        for k in range(1, n + 1)
    }


def test_corrected_keyframes_take_the_team_pose_and_follow_local_refinement():
    rng = np.random.default_rng(3)
    odom = _odometry(6, rng)
    team = {k: se3(exp_so3(rng.normal(0, 0.01, 3)), rng.normal(0, 0.02, 3)) @ odom[k] for k in odom}
    shared = SharedPoses()
    # Keyframes 2 and 4 corrected; 7 is unknown to the robot (culled meanwhile) and ignored.
    assert shared.receive({2: team[2], 4: team[4], 7: np.eye(4)}, odom) == 2 and shared.corrected
    poses = shared.keyframe_poses(odom)
    for k in (2, 4):
        assert transform_error(poses[k], team[k])[0] < 1e-12
    for k in (1, 3):  # not sent: the server agrees with the odometry within its thresholds
        assert transform_error(poses[k], odom[k])[0] < 1e-12
    C4 = team[4] @ invert(odom[4])
    for k in (5, 6):  # newer than the newest corrected: not seen by the server, move with it
        assert transform_error(poses[k], C4 @ odom[k])[0] < 1e-12
    assert transform_error(shared.T_map_odom, C4)[0] < 1e-12
    # Local BA refines keyframe 2 afterwards: its correction goes with it (an offset).
    delta = se3(exp_so3(np.array([0.0, 0.0, 0.01])), np.array([0.01, 0.0, 0.0]))
    odom2 = dict(odom) | {2: odom[2] @ delta}
    assert transform_error(shared.keyframe_poses(odom2)[2], team[2] @ delta)[0] < 1e-12
    # Culling the newest corrected keyframe: the next newest anchors where the robot is.
    shared.forget(4)
    C2 = team[2] @ invert(odom[2])
    assert transform_error(shared.T_map_odom, C2)[0] < 1e-12
    assert transform_error(shared.keyframe_poses(odom)[5], C2 @ odom[5])[0] < 1e-12


def test_points_move_with_their_reference_keyframe():
    rng = np.random.default_rng(4)
    odom = _odometry(3, rng)
    C = {k: se3(exp_so3(rng.normal(0, 0.02, 3)), rng.normal(0, 0.05, 3)) for k in odom}
    shared = SharedPoses()
    shared.receive({k: C[k] @ odom[k] for k in (1, 2)}, odom)
    xyz = rng.normal(0, 2.0, (30, 3))
    ref = np.repeat([1, 2, 3], 10)
    out = shared.points(xyz, ref)
    assert np.allclose(out[:10], transform_points(C[1], xyz[:10]))
    assert np.allclose(out[10:20], transform_points(C[2], xyz[10:20]))
    assert np.allclose(out[20:], transform_points(C[2], xyz[20:]))  # 3: newer, moves with 2
    assert SharedPoses().points(np.zeros((0, 3)), np.zeros(0)).shape == (0, 3)


def test_a_new_map_segment_stays_in_its_own_frame_until_corrected():
    rng = np.random.default_rng(6)
    odom = _odometry(6, rng)
    C = se3(exp_so3(np.array([0.0, 0.0, 0.1])), np.array([0.2, 0.0, 0.0]))
    shared = SharedPoses()
    shared.receive({k: C @ odom[k] for k in (1, 2, 3)}, odom)
    shared.start_segment(5)  # keyframes 5, 6: another odometry frame
    poses = shared.keyframe_poses(odom)
    assert transform_error(poses[4], C @ odom[4])[0] < 1e-12  # still the old segment's
    for k in (5, 6):
        assert np.array_equal(poses[k], odom[k])
    assert np.array_equal(shared.T_map_odom, np.eye(4))
    # A point with no reference (id beyond all) goes with where the robot is now.
    big = np.iinfo(np.int64).max
    assert np.allclose(shared.points(np.ones((1, 3)), [big]), np.ones((1, 3)))
    C5 = se3(t=np.array([0.0, 0.1, 0.0]))
    shared.receive({5: C5 @ odom[5]}, odom)
    assert transform_error(shared.keyframe_poses(odom)[6], C5 @ odom[6])[0] < 1e-12
    assert transform_error(shared.T_map_odom, C5)[0] < 1e-12
    # A late correction of old keyframes does not take "where the robot is" back to them.
    shared.receive({2: C @ odom[2]}, odom)
    assert transform_error(shared.T_map_odom, C5)[0] < 1e-12


def test_nothing_received_leaves_the_odometry_as_it_is():
    rng = np.random.default_rng(5)
    odom = _odometry(3, rng)
    shared = SharedPoses()
    assert shared.receive({9: np.eye(4)}, odom) == 0 and not shared.corrected
    assert np.array_equal(shared.T_map_odom, np.eye(4))
    for k, T in shared.keyframe_poses(odom).items():
        assert np.array_equal(T, odom[k])


def test_keyframes_the_server_does_not_hold_follow_their_nearest_corrected_neighbour():
    """A radio budget sent keyframes 2, 3 and 7 as signatures only: the server sends no pose for
    them. They take the correction of the nearest corrected keyframe of their map segment; a
    keyframe the server holds and sent no pose for stays where the odometry has it."""
    rng = np.random.default_rng(5)
    odom = _odometry(9, rng)
    team = {k: se3(exp_so3(rng.normal(0, 0.01, 3)), rng.normal(0, 0.02, 3)) @ odom[k] for k in odom}
    signatures_only = {2, 3, 7}
    shared = SharedPoses(server_holds=lambda k: k not in signatures_only)
    shared.receive({1: team[1], 4: team[4], 6: team[6], 9: team[9]}, odom)
    C = {k: team[k] @ invert(odom[k]) for k in (1, 4, 6, 9)}
    poses = shared.keyframe_poses(odom)
    for k, near in ((2, 1), (3, 4), (7, 6)):  # (a tie goes to the older)
        assert transform_error(poses[k], C[near] @ odom[k])[0] < 1e-12, k
    assert transform_error(poses[5], odom[5])[0] < 1e-12  # held: within the server's thresholds
    # A new map segment from keyframe 8: its keyframes never take an older segment's correction.
    shared.start_segment(8)
    shared.forget(9)
    signatures_only.add(8)
    assert transform_error(shared.keyframe_poses(odom)[8], odom[8])[0] < 1e-12
    assert transform_error(shared.keyframe_poses(odom)[7], C[6] @ odom[7])[0] < 1e-12


def test_a_keyframe_never_takes_another_map_segments_correction():
    """Segments 1-10, 11-20 and 21-: keyframe 10, not held, is nearest to 11 by id but takes
    keyframe 8's correction, its own segment's."""
    rng = np.random.default_rng(6)
    odom = _odometry(22, rng)
    shared = SharedPoses(server_holds=lambda k: k not in (9, 10, 12))
    shared.start_segment(11)
    shared.start_segment(21)
    far = se3(t=[5.0, 0.0, 0.0])
    shared.receive({8: odom[8], 11: far @ odom[11], 22: odom[22]}, odom)
    assert transform_error(shared.correction(10), np.eye(4))[0] < 1e-12
    assert transform_error(shared.correction(12), far)[0] < 1e-12
