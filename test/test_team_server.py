"""Place-recognition stitching in the server core, on a synthetic feature world with known truth."""

import numpy as np
import pytest

from coop_slam.errors import ConfigError
from coop_slam.geometry import invert, transform_error
from coop_slam.team.keyframe_store import track
from coop_slam.team.plausibility import interpolate_track
from coop_slam.team.server import TeamServer
from coop_slam.wire.record import KeyframeError
from helpers import (
    TEAM_T_WORLD_MAP,
    cylinder_world,
    looking_out_pose,
    team_keyframes,
    team_server_config,
    team_world,
)

T_WORLD_MAP = TEAM_T_WORLD_MAP
_keyframes = team_keyframes


_config = team_server_config


@pytest.fixture(scope="module")
def world():
    return team_world()


def test_revisit_merges_with_the_true_transform(world):
    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(robots=[1, 2]), vocab)
    for kf in kfs_a:
        assert server.add_keyframe(kf) == []
    yaws_b = np.linspace(2.0, 3.0, 8)  # robot B looks where A looked earlier, from 20 cm aside
    merges = []
    for kf in _keyframes(2, yaws_b, points, desc, offset=(0.2, 0.1), seed=100, t0=100.0):
        merges += server.add_keyframe(kf)
    assert len(merges) == 1
    m = merges[0]
    assert (m.map_a, m.map_b, m.type) == (1, 2, "place_recognition")
    dt, dr = transform_error(m.T_mapA_mapB, invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[2])
    assert dt < 0.02 and dr < 0.5
    assert server.groups.groups() == [[1, 2]]
    T, merged = server.T_group_map(2), server.in_world(2)
    # Later keyframes of B add in-group constraints, so the optimized map moves a little.
    assert merged and transform_error(T, m.T_mapA_mapB)[0] < 0.01
    assert server.constraints and all(
        c.type in ("place_recognition", "overlap") and c.key_a[0] != c.key_b[0]
        for c in server.constraints
    )


def test_unrelated_places_never_merge(world):
    _, _, kfs_a, vocab = world
    other_points, other_desc = cylinder_world(seed=99)  # a different building
    server = TeamServer(_config(robots=[1, 2]), vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    # A marker sighting says the robots are together (facing each other across an empty room):
    # co-observations then need no second verification, but still a shared scene.
    server.request_rendezvous(1, 2, stamp_s=0.0)
    for kf in _keyframes(2, np.linspace(0, 2 * np.pi, 20), other_points, other_desc, seed=7):
        assert server.add_keyframe(kf) == []  # same stamps: co-observation is tried too
    assert server.merges == [] and server.groups.groups() == [[1], [2]]
    merge, message = server.request_rendezvous(1, 2)
    assert merge is None and "not merged" in message


def _co_observe(world, sighted: bool, offset=(0.3, -0.2), min_separation_m=None, auto=True):
    """Robots 1 and 2 look at the same scene at the same times, robot 2 ``offset`` [m] from
    robot 1; (merges, server). Without ``auto`` only place recognition can join them."""
    points, desc, _, vocab = world
    cfg = _config(robots=[1, 2])
    cfg.rendezvous.auto = auto
    if min_separation_m is not None:
        cfg.rendezvous.min_separation_m = min_separation_m
    server = TeamServer(cfg, vocab)
    if sighted:  # a marker sighting before either robot has a keyframe
        merge, message = server.request_rendezvous(1, 2, stamp_s=-1.0)
        assert merge is None and "no keyframes" in message
    yaws = np.linspace(1.0, 1.6, 4)
    merges = []
    for kf_a, kf_b in zip(
        _keyframes(1, yaws, points, desc, seed=1),
        _keyframes(2, yaws + 0.05, points, desc, offset=offset, seed=50),
    ):
        merges += server.add_keyframe(kf_a) + server.add_keyframe(kf_b)
    return merges, server


def test_co_observation_merges_as_rendezvous(world):
    merges, server = _co_observe(world, sighted=False)
    assert len(merges) == 1 and merges[0].type == "rendezvous"
    # The first verification waits for a second, agreeing one ...
    (_, (robot, first_kf)), _ = server.rendezvous._co_observations[(1, 2)][0]
    assert robot == 2 and merges[0].keyframe_b > first_kf
    # ... unless a sighting said the robots are together: then the first one merges.
    cued, _ = _co_observe(world, sighted=True)
    assert len(cued) == 1 and cued[0].type == "rendezvous" and cued[0].keyframe_b == first_kf
    for m in merges + cued:
        dt, dr = transform_error(m.T_mapA_mapB, invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[2])
        assert dt < 0.02 and dr < 0.5
    merge, message = server.request_rendezvous(1, 2)
    assert merge is None and "already merged" in message
    assert server.request_rendezvous(1, 7)[1].startswith("robot 7 is unknown")


@pytest.mark.parametrize(
    "offset",
    [(0.05, 0.0), (0.8 * np.cos(1.3), 0.8 * np.sin(1.3))],
    ids=["5 cm aside", "0.8 m ahead in view"],
)
def test_views_two_robots_cannot_share_at_once_are_look_alikes(world, offset):
    """Identical posters in two buildings, seen at the same times: as one place, the robots would
    stand 5 cm apart, or robot 1 would see the wall straight through robot 2. Refused, whether a
    marker cue says they are together or not, and by place recognition alone."""
    for sighted, auto in ((False, True), (True, True), (False, False)):
        merges, server = _co_observe(world, sighted, offset=offset, auto=auto)
        assert merges == [] and server.groups.groups() == [[1], [2]], (sighted, auto)
        # The same views merge when the check is off, so the check is what refused them.
        merges, _ = _co_observe(world, sighted, offset, min_separation_m=0.0, auto=auto)
        assert len(merges) == 1, (sighted, auto)
    cfg = _config(robots=[1, 2])
    cfg.rendezvous.min_separation_m = -0.1
    with pytest.raises(ConfigError, match="min_separation_m"):
        cfg.validate()


def test_robot_position_between_keyframes_is_known_only_across_short_gaps(world):
    points, desc, _, vocab = world
    server = TeamServer(_config(robots=[1, 2]), vocab)
    kfs = _keyframes(1, [0.0, 0.1, 0.2, 0.3], points, desc)  # stamps 0, 1, 2, 3 s
    kfs[3].stamp_s = 5.0  # then nothing for 3 s
    twin = _keyframes(1, [0.15], points, desc, kid0=9)[0]
    twin.stamp_s = 2.0  # two keyframes at one stamp
    for kf in kfs + [twin]:
        server.add_keyframe(kf)
    p0, p1 = (kf.T_map_cam[:3, 3] for kf in kfs[:2])

    def position_at(robot, segment, stamp_s):
        map_id = server.segments.find(robot, segment)
        records = server.store.map_records(map_id) if map_id is not None else []
        return interpolate_track(*track(records), stamp_s)

    np.testing.assert_allclose(position_at(1, 0, 0.25), 0.75 * p0 + 0.25 * p1)
    np.testing.assert_allclose(position_at(1, 0, 1.0), p1)
    assert position_at(1, 0, 2.0) is not None
    for stamp_s in (-0.5, 3.5, 6.0):  # before the first, in the gap, after the last
        assert position_at(1, 0, stamp_s) is None
    assert position_at(1, 1, 0.5) is None  # no keyframes in that map segment
    assert position_at(2, 0, 0.5) is None  # nor of that robot


def test_unknown_robot_and_duplicates_are_rejected(world):
    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(robots=[1, 2]), vocab)
    bad = _keyframes(1, [0.0], points, desc)[0]
    bad.robot_id = 5
    with pytest.raises(KeyframeError, match="unknown"):
        server.add_keyframe(bad)
    server.add_keyframe(kfs_a[0])
    assert len(server.store) == 1


def _merged_server(world) -> TeamServer:
    """Robot 1's keyframes, then 8 of robot 2 looking at the same walls: a server that merged."""
    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(robots=[1, 2]), vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    for kf in _keyframes(
        2, np.linspace(2.0, 3.0, 8), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
    ):
        server.add_keyframe(kf)
    return server


def test_merge_optimizes_the_team_and_stitches_one_cloud(world):
    server = _merged_server(world)
    assert server.groups.groups() == [[1, 2]] and server.optimize_ms
    T, merged = server.T_group_map(2), server.in_world(2)
    dt, dr = transform_error(T, invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[2])
    assert merged and dt < 0.02 and dr < 0.5
    corrected = server.corrected_keyframes(2)
    assert len(corrected) == 8
    cloud, rgb, robots = server.team_cloud()
    assert len(cloud) == len(rgb) == len(robots) > 100 and set(robots.tolist()) <= {1, 2}
    # Both robots' points of the same wall land on the same cylinder in robot 1's map frame.
    from coop_slam.geometry import transform_points

    radius = np.linalg.norm(transform_points(T_WORLD_MAP[1], cloud)[:, :2], axis=1)
    assert np.median(np.abs(radius - 5.0)) < 0.05


def test_unmerged_maps_are_shown_apart(world):
    points, desc, kfs_a, vocab = world
    other_points, other_desc = cylinder_world(seed=99)
    server = TeamServer(_config(robots=[1, 2]), vocab)
    for kf in kfs_a[:5]:
        server.add_keyframe(kf)
    for kf in _keyframes(2, np.linspace(0, 1, 5), other_points, other_desc, seed=7, t0=50.0):
        server.add_keyframe(kf)
    cloud, _, robots = server.team_cloud()
    assert cloud[robots == 2, 0].min() > cloud[robots == 1, 0].max() + 10.0


def _drifting(kfs, step_m=0.004, step_rad=0.001):
    """Client poses that drift a little more with every keyframe (x and yaw), as real VO does."""
    from coop_slam.geometry import se3

    for k, kf in enumerate(kfs):
        c, s = np.cos(k * step_rad), np.sin(k * step_rad)
        drift = se3(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), [k * step_m, 0, 0])
        kf.T_map_cam = drift @ kf.T_map_cam
    return kfs


def test_own_revisit_closes_a_loop_and_removes_drift(world):
    points, desc, _, vocab = world
    yaws = np.concatenate(
        [np.linspace(0, 2 * np.pi, 36, endpoint=False), 2 * np.pi + np.linspace(0, 1.5, 9)]
    )
    kfs = _drifting(_keyframes(1, yaws, points, desc, seed=300))
    truth = {
        kf.keyframe_id: invert(T_WORLD_MAP[1]) @ looking_out_pose(y) for kf, y in zip(kfs, yaws)
    }
    server = TeamServer(_config(robots=[1]), vocab)
    for kf in kfs:
        assert server.add_keyframe(kf) == []  # never a merge
    assert [c.type for c in server.constraints][:1] == ["loop"]
    assert all(c.key_a[0] == c.key_b[0] == 1 for c in server.constraints)
    optimized = server.optimized_keyframes(1)
    before = {kf.keyframe_id: transform_error(kf.T_map_cam, truth[kf.keyframe_id])[0] for kf in kfs}
    after = {k: transform_error(T, truth[k])[0] for k, T in optimized.items()}
    closed = server.constraints[0].key_b[1]  # where the first loop was closed
    assert before[closed] > 0.1 and after[closed] < 0.3 * before[closed]
    assert np.mean(list(after.values())) < 0.5 * np.mean(list(before.values()))


def test_constraint_far_from_the_estimate_is_refused(world):
    points, desc, _, vocab = world
    yaws = np.concatenate(
        [np.linspace(0, 2 * np.pi, 36, endpoint=False), 2 * np.pi + np.linspace(0, 1.5, 9)]
    )
    kfs = _drifting(_keyframes(1, yaws, points, desc, seed=300), step_m=0.05)  # 2 m of drift
    cfg = _config(robots=[1])
    cfg.loops.gate_trans_m = 0.5
    server = TeamServer(cfg, vocab)
    for kf in kfs:
        server.add_keyframe(kf)
    assert server.constraints == [] and server.rejected_constraints >= 1


def test_constraint_needs_min_inliers(world):
    """The own revisit that closes a loop above adds nothing when its support is too thin."""
    points, desc, _, vocab = world
    yaws = np.concatenate(
        [np.linspace(0, 2 * np.pi, 36, endpoint=False), 2 * np.pi + np.linspace(0, 1.5, 9)]
    )
    kfs = _drifting(_keyframes(1, yaws, points, desc, seed=300))
    cfg = _config(robots=[1])
    cfg.loops.min_inliers = 100000
    server = TeamServer(cfg, vocab)
    for kf in kfs:
        server.add_keyframe(kf)
    assert server.constraints == [] and server.verifications > 0


def test_three_robots_end_in_one_group(world):
    """Robots 1 and 2 map disjoint halves at different times; robot 3 later crosses both halves and
    links the two groups: every map ends in robot 1's frame at its true place."""
    points, desc, _, vocab = world
    server = TeamServer(_config(robots=[1, 2, 3]), vocab)
    for kf in _keyframes(1, np.linspace(0, np.pi, 18), points, desc, seed=1):
        server.add_keyframe(kf)
    for kf in _keyframes(
        2,
        np.linspace(np.pi + 0.3, 2 * np.pi - 0.3, 14),
        points,
        desc,
        offset=(0.1, 0.2),
        seed=2,
        t0=100.0,
    ):
        server.add_keyframe(kf)
    assert server.groups.groups() == [[1], [2], [3]]
    for kf in _keyframes(
        3, np.linspace(1.0, 5.0, 30), points, desc, offset=(-0.2, 0.1), seed=3, t0=200.0
    ):
        server.add_keyframe(kf)
    assert server.groups.groups() == [[1, 2, 3]]
    assert [(m.map_a, m.map_b) for m in server.merges] == [(1, 3), (2, 3)]
    for r in (2, 3):
        T, merged = server.T_group_map(r), server.in_world(r)
        dt, dr = transform_error(T, invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[r])
        assert merged and dt < 0.03 and dr < 1.0


def test_rendezvous_with_a_robot_that_stands_still(world):
    """Robot 1 stopped making keyframes long ago (it waits); robot 2 arrives and sees its view: a
    sighting / operator request is checked against robot 1's latest keyframe and merges; the
    automatic co-observation test does not reach that far back in time."""
    points, desc, _, vocab = world
    cfg = _config(robots=[1, 2])
    cfg.place_recognition.enabled = False  # only the rendezvous paths may merge
    server = TeamServer(cfg, vocab)
    for kf in _keyframes(1, np.linspace(1.0, 1.6, 4), points, desc, seed=1):
        server.add_keyframe(kf)  # stamps 0..3 s
    for kf in _keyframes(
        2, np.linspace(0.5, 1.55, 4), points, desc, offset=(0.3, -0.2), seed=50, t0=30.0
    ):
        server.add_keyframe(kf)
    assert server.merges == []
    merge, message = server.request_rendezvous(2, 1)
    assert merge is not None, message
    assert server.groups.groups() == [[1, 2]] and server.merges[0].type == "rendezvous"
    T = server.T_group_map(2)
    dt, dr = transform_error(T, invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[2])
    assert dt < 0.02 and dr < 0.5


@pytest.mark.parametrize("late", [False, True])
def test_cued_request_is_retried_on_the_next_keyframes(world, late):
    """A marker sighting whose keyframes do not show the shared scene yet stays open: the next
    keyframe of either robot within the request window is verified and merges; one taken after
    the window closes the request instead."""
    points, desc, _, vocab = world
    cfg = _config(robots=[1, 2])
    cfg.place_recognition.enabled = False
    cfg.rendezvous.auto = False  # only the request may merge
    server = TeamServer(cfg, vocab)
    for kf in _keyframes(1, np.linspace(1.0, 1.6, 4), points, desc, seed=1):
        server.add_keyframe(kf)  # stamps 0..3 s
    # Robot 2 still looks the other way when robot 1 sees its marker at 1 s.
    (away,) = _keyframes(2, [1.3 + np.pi], points, desc, offset=(0.3, -0.2), seed=50, t0=1.0)
    assert server.add_keyframe(away) == []
    merge, message = server.request_rendezvous(1, 2, stamp_s=1.0)
    assert merge is None and "will be tried as they arrive" in message
    t_next = 1.0 + cfg.rendezvous.request_window_s + (1.0 if late else -0.5)
    (turned,) = _keyframes(2, [1.3], points, desc, kid0=2, offset=(0.3, -0.2), seed=51, t0=t_next)
    merges = server.add_keyframe(turned)
    assert not server.rendezvous.has_open_requests
    if late:
        assert merges == [] and server.groups.groups() == [[1], [2]]
        return
    assert len(merges) == 1 and merges[0].type == "rendezvous"
    assert merges[0].stamp_s == t_next  # when the keyframe showing the shared scene was taken
    dt, dr = transform_error(merges[0].T_mapA_mapB, invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[2])
    assert dt < 0.02 and dr < 0.5


def test_a_later_keyframe_of_a_cued_request_is_tried_against_what_the_other_saw_then(world):
    """Keyframes reach the server a while after they were taken (the clients' uplink holds them):
    a keyframe arriving for an open request is verified against the other robot's keyframes
    nearest it in time too, not only against those nearest the cue, which here look away."""
    points, desc, _, vocab = world
    cfg = _config(robots=[1, 2])
    cfg.place_recognition.enabled = False
    cfg.rendezvous.auto = False  # only the request may merge
    server = TeamServer(cfg, vocab)
    away = np.array([1.3, 1.1]) - np.pi / 2  # a quarter turn from the shared scene
    for kf in _keyframes(1, away, points, desc, seed=1, t0=0.0):  # stamps 0, 1 s
        server.add_keyframe(kf)
    for kf in _keyframes(1, [1.3, 1.5], points, desc, kid0=3, seed=3, t0=2.5):  # 2.5, 3.5 s
        server.add_keyframe(kf)
    (before,) = _keyframes(2, [1.3 + np.pi], points, desc, offset=(0.3, -0.2), seed=50, t0=0.5)
    server.add_keyframe(before)
    merge, _ = server.request_rendezvous(1, 2, stamp_s=1.0)
    assert merge is None
    (turned,) = _keyframes(2, [1.3], points, desc, kid0=2, offset=(0.3, -0.2), seed=51, t0=2.5)
    merges = server.add_keyframe(turned)
    assert len(merges) == 1 and merges[0].type == "rendezvous", server.groups.groups()
    assert merges[0].stamp_s == 2.5
    dt, dr = transform_error(merges[0].T_mapA_mapB, invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[2])
    assert dt < 0.02 and dr < 0.5


def test_a_new_map_segment_is_a_map_of_its_own_that_merges_back(world):
    """A client that lost tracking for good (or restarted) sends a new map segment in a new map
    frame: the server keeps it apart (no odometry to the old segment) and merges it back."""
    points, desc, kfs_a, vocab = world
    server = TeamServer(_config(robots=[1, 2]), vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    for kf in _keyframes(2, np.linspace(2.0, 3.0, 8), points, desc, offset=(0.2, 0.1), t0=100.0):
        server.add_keyframe(kf)
    assert server.groups.groups() == [[1, 2]]
    # Segment 1 of robot 2: its map frame is another (robot 3's in the helpers' table).
    seg = _keyframes(3, np.linspace(4.0, 5.0, 8), points, desc, kid0=100, seed=200, t0=200.0)
    for kf in seg:
        kf.robot_id, kf.map_segment = 2, 1
        server.add_keyframe(kf)
    mid = server.current_map(2)
    assert mid == 3 and server.robot_of(mid) == 2
    assert server.robot_groups() == [(1, 2)] and server.in_world(mid)
    T_true = invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[3]
    assert transform_error(server.T_group_map(mid), T_true)[0] < 0.03
    # The first segment stayed where it was (no odometry across segments pulled it).
    T_2 = invert(T_WORLD_MAP[1]) @ T_WORLD_MAP[2]
    assert transform_error(server.T_group_map(2), T_2)[0] < 0.03
    kfs = server.robot_keyframes(2)
    assert sorted(kfs)[:8] == list(range(1, 9)) and sorted(kfs)[8:] == list(range(100, 108))


def test_pose_feedback_sends_only_keyframes_that_moved_since_last_sent():
    """Incremental pose-graph sharing: at first against the client's own poses, then against
    what was sent; the newest keyframe always goes (the client anchors map -> odom on it)."""
    from coop_slam.geometry import se3
    from coop_slam.team.pose_feedback import PoseFeedback, PoseFeedbackConfig

    feedback = PoseFeedback(PoseFeedbackConfig(min_trans_m=0.005, min_rot_deg=0.2))
    client = {k: se3(t=np.array([0.1 * k, 0.0, 0.0])) for k in range(1, 6)}
    optimized = dict(client)
    optimized[2] = se3(t=np.array([0.2, 0.01, 0.0]))  # moved 1 cm
    optimized[3] = se3(t=np.array([0.3, 0.002, 0.0]))  # 2 mm: below the threshold
    assert sorted(feedback.select(7, optimized, client)) == [2, 5]
    assert sorted(feedback.select(7, optimized, client)) == [5]  # nothing moved since
    optimized[3] = se3(t=np.array([0.3, 0.008, 0.0]))  # now 8 mm from the client's pose
    del optimized[5]  # culled: the newest is now 4
    assert sorted(feedback.select(7, optimized, client)) == [3, 4]
    assert sorted(feedback.select(8, {}, {})) == []  # a map without optimized keyframes


def test_server_pose_corrections_after_a_merge_are_incremental(world):
    """After a merge a robot gets the keyframes the team map moved; the next call, with nothing
    new optimized, only the newest."""
    server = _merged_server(world)
    assert server.groups.groups() == [[1, 2]]
    first = server.pose_corrections(2)
    assert max(server.corrected_keyframes(2)) in first
    assert sorted(server.pose_corrections(2)) == [max(first)]


def test_team_map_cadence_keeps_the_cloud_within_its_share_of_the_worker():
    """After a merge or every period of data time, but a map that took c seconds to build is not
    followed by the next within c * (1 / share - 1) seconds of wall time."""
    from coop_slam.team.publish_cadence import PublishCadence, PublishCadenceConfig

    cadence = PublishCadence(PublishCadenceConfig(period_s=2.0, max_busy_share=0.25))
    assert cadence.due(stamp_s=0.0, merged=False, wall_s=0.0)
    cadence.published(0.0, started_wall_s=0.0, ended_wall_s=1.0)  # took 1 s: next from 4 s on
    assert not cadence.due(1.0, merged=False, wall_s=5.0)  # 1 s of data: not yet
    assert not cadence.due(2.5, merged=True, wall_s=3.9)  # a merge, but over the budget
    assert cadence.due(2.5, merged=True, wall_s=4.0)
    assert cadence.due(2.0, merged=False, wall_s=4.0)
    with pytest.raises(ConfigError, match="cloud_max_busy_share"):
        PublishCadence(PublishCadenceConfig(max_busy_share=0.0))


def test_map_builder_builds_one_cloud_at_a_time_beside_the_worker():
    """The worker hands over a cloud job; while it is built the builder takes no other (the map
    stays due, never a queue of stale clouds); the cost reaches the cadence; a build that fails
    is counted and the builder carries on."""
    import threading

    from coop_slam.team.map_builder import TeamMapBuilder
    from coop_slam.team.publish_cadence import PublishCadence, PublishCadenceConfig

    cadence = PublishCadence(PublishCadenceConfig(period_s=1.0, max_busy_share=1.0))
    got, gate = [], threading.Event()
    builder = TeamMapBuilder(lambda cloud, stamp_s: got.append((cloud, stamp_s)), cadence)
    try:
        assert builder.submit(lambda: gate.wait(10.0) and "first", 1.0)
        assert builder.busy
        assert not builder.submit(lambda: "second", 2.0)
        gate.set()
        assert builder.wait_idle(10.0) and not builder.busy
        assert got == [("first", 1.0)]
        assert not cadence.due(1.5, merged=False, wall_s=1e9)  # published at data time 1.0
        assert cadence.due(2.5, merged=False, wall_s=1e9)
        assert builder.submit(lambda: 1 / 0, 3.0)
        assert builder.wait_idle(10.0)
        assert builder.submit(lambda: "after", 4.0)
        assert builder.wait_idle(10.0)
        assert got[-1] == ("after", 4.0)
        assert (builder.built, builder.failed) == (2, 1)
    finally:
        builder.close()
    assert not builder.submit(lambda: "closed", 5.0)


def test_co_observation_verifies_at_most_its_budget_per_keyframe(world):
    """With several unmerged robots, a new keyframe is verified against at most
    auto_max_verifications simultaneous keyframes of the others (here 1 of 4 candidates)."""
    points, desc, kfs_a, vocab = world
    cfg = _config(robots=[1, 2, 3])
    cfg.rendezvous.auto_max_verifications = 1
    cfg.rendezvous.auto_verifications_per_s = 0.0  # the team-wide budget: the next test
    cfg.place_recognition.enabled = False
    server = TeamServer(cfg, vocab)
    for robot in (2, 3):  # two keyframes each, taken at the time of robot 1's keyframe
        for kf in _keyframes(robot, [0.0, 0.1], points, desc, seed=10 * robot, t0=5.0):
            kf.stamp_s = 5.0 + 0.1 * kf.keyframe_id
            server.add_keyframe(kf)
    before = server.rendezvous.verifications
    kf = kfs_a[0]
    kf.stamp_s = 5.15
    server.add_keyframe(kf)
    assert server.rendezvous.verifications - before == 1


@pytest.mark.parametrize("per_s", [0.0, 1.0])
def test_co_observation_budget_is_shared_by_the_team_per_second_of_data(world, per_s):
    """Keyframes arriving close together in data time share auto_verifications_per_s: a burst
    spends the budget (2 x auto_max_verifications), data time refills it; 0 is no limit."""
    points, desc, _, vocab = world
    cfg = _config(robots=[1, 2, 3])
    cfg.rendezvous.auto_verifications_per_s = 0.0  # robots 2 and 3 leave the budget full
    cfg.place_recognition.enabled = False
    cfg.links.enabled = False
    server = TeamServer(cfg, vocab)
    for robot in (2, 3):  # keyframes near t = 5 s and near t = 15 s
        kfs = _keyframes(robot, [0.0, 0.1, 3.0, 3.1], points, desc, seed=10 * robot)
        for kf, stamp in zip(kfs, (5.0, 5.1, 15.0, 15.1)):
            kf.stamp_s = stamp
            server.add_keyframe(kf)
    cfg.rendezvous.auto_verifications_per_s = per_s
    burst = _keyframes(1, np.linspace(1.5, 1.6, 6), points, desc, seed=1)
    before = server.rendezvous.verifications
    for k, kf in enumerate(burst):  # six keyframes within 0.05 s, each with 4 candidates
        kf.stamp_s = 5.15 + 0.01 * k
        server.add_keyframe(kf)
    spent = server.rendezvous.verifications - before
    later = _keyframes(1, [4.5], points, desc, kid0=7, seed=2)[0]
    later.stamp_s = 15.05
    before = server.rendezvous.verifications
    server.add_keyframe(later)
    if per_s == 0:
        assert spent == 6 * 4  # each keyframe its own 4
    else:
        assert spent == 2 * cfg.rendezvous.auto_max_verifications
    assert server.rendezvous.verifications - before == 4  # 10 s of data refilled the budget
    if per_s == 0:
        return
    # A clock that starts again (far behind the newest stamp) refills from its own time.
    made = []
    for kid, stamp in ((8, 3.5), (9, 6.5)):
        kf = _keyframes(1, [1.55], points, desc, kid0=kid, seed=kid)[0]
        kf.stamp_s = stamp
        before = server.rendezvous.verifications
        server.add_keyframe(kf)
        made.append(server.rendezvous.verifications - before)
    assert made == [4, 3]  # the 4 left; then 3 s of the new clock at 1 per second


@pytest.mark.parametrize("full_above_m", [0.0, 0.02])
def test_small_in_group_constraints_go_into_the_incremental_update(world, full_above_m):
    """After the merge, constraints between the merged robots that agree with the estimate are
    absorbed by iSAM2; only a constraint further than loops.full_above_trans_m asks for a full
    optimization (0: every constraint does)."""
    points, desc, kfs_a, vocab = world
    cfg = _config(robots=[1, 2])
    cfg.loops.full_above_trans_m = full_above_m
    server = TeamServer(cfg, vocab)
    for kf in kfs_a:
        server.add_keyframe(kf)
    kfs_b = _keyframes(
        2, np.linspace(2.0, 5.0, 20), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
    )
    for kf in kfs_b[:8]:
        server.add_keyframe(kf)
    assert server.groups.groups() == [[1, 2]]
    full = []
    optimize_full = server.graph.optimize_full
    server.graph.optimize_full = lambda: full.append(1) or optimize_full()
    before = len(server.constraints)
    for kf in kfs_b[8:]:
        server.add_keyframe(kf)
    added = len(server.constraints) - before
    assert added >= 2
    if full_above_m == 0.0:
        assert len(full) >= added
    else:
        assert len(full) == 0


def test_a_lost_robot_gets_the_teams_local_map_where_it_is_in_its_own_frame(world):
    """Server-assisted relocalization: robot 2 (merged) is lost facing a wall only robot 1 has
    mapped; its view's BoW finds robot 1's keyframe there, and the answer holds that keyframe's
    (and its neighbours') map points in robot 2's map frame."""
    from coop_slam.geometry import transform_points
    from coop_slam.team.assisted_relocalization import AssistConfig, local_map_for

    server = _merged_server(world)
    _, _, kfs_a, vocab = world
    seen = kfs_a[20]  # robot 2 looked at yaws 2-3 rad only; this one looks elsewhere
    bow, _ = vocab.transform(seen.descriptors)
    local = local_map_for(server, 2, bow, AssistConfig(keyframes=3))
    assert local is not None and local.keyframes[0] == (1, seen.keyframe_id)
    assert len(local.keyframes) == 3 and len(local.points_map) == len(local.descriptors)
    truth = transform_points(invert(T_WORLD_MAP[2]) @ T_WORLD_MAP[1], seen.map_points)
    first = local.points_map[: len(truth)]
    assert np.percentile(np.linalg.norm(first - truth, axis=1), 90) < 0.02
    # No place scores min_score: no local map.
    assert local_map_for(server, 2, bow, AssistConfig(min_score=1.0)) is None


def test_updates_wait_for_an_incremental_optimization_of_their_own_count(world):
    """A client sends several updates per keyframe (local BA): the team graph takes each at once
    but optimizes incrementally after optimize_every_updates of them (or optimize_every new
    keyframes), not after every few messages."""
    import dataclasses

    from coop_slam.wire.record import ACTION_UPDATE

    server = _merged_server(world)
    server.optimize(full=False)  # start counting from here
    runs = len(server.optimize_ms)
    kf = server.store.record((2, max(server.store.keyframe_ids(2))))
    every = server.config.optimize_every_updates
    for k in range(every):
        moved = dataclasses.replace(
            kf, robot_id=2, action=ACTION_UPDATE, T_map_cam=kf.T_map_cam.copy()
        )
        moved.T_map_cam[0, 3] += 1e-4 * (k + 1)
        server.add_keyframe(moved)
        assert len(server.optimize_ms) == runs + (k + 1 == every), k
