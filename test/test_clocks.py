"""A robot's clock against the server's, from when its messages were sent and arrived; its stamps
taken in the server's time; a clock too far off refuses rendezvous with the fix named."""

import logging

import numpy as np
import pytest

from coop_slam.team.clocks import ClockConfig, RobotClocks
from helpers import make_keyframe


def _observe(clocks, robot, offset_s, transits_s, t0=100.0):
    for k, transit in enumerate(transits_s):
        sent = t0 + k + offset_s  # the robot's clock
        clocks.observe(robot, sent, t0 + k + transit)


def test_the_offset_is_the_robots_clock_minus_the_servers_low_by_the_smallest_transit():
    clocks = RobotClocks()
    rng = np.random.default_rng(0)
    _observe(clocks, 2, 0.3, 0.004 + rng.exponential(0.05, 50))
    _observe(clocks, 1, 0.0, 0.004 + rng.exponential(0.05, 50))
    assert clocks.offset(2) == pytest.approx(0.3 - 0.004, abs=0.01)
    assert clocks.offset(1) == pytest.approx(-0.004, abs=0.01)
    assert clocks.correction(1) == 0.0  # within correct_above_s: its stamps are left as they are
    assert clocks.correction(2) == pytest.approx(clocks.offset(2))
    assert clocks.said() == {2: round(clocks.offset(2), 4), 1: round(clocks.offset(1), 4)}


def test_a_server_clock_read_late_now_and_then_does_not_move_the_estimate():
    """ROS sim time: a message may race the /clock that the server reads its arrival time from,
    so that arrival reads a frame (67 ms) or two early on a few messages."""
    clocks = RobotClocks()
    rng = np.random.default_rng(1)
    late = rng.choice([0.0, -1 / 15, -2 / 15], size=200, p=[0.94, 0.04, 0.02])
    _observe(clocks, 2, 0.3, late)
    assert clocks.offset(2) == pytest.approx(0.3, abs=1e-9)


def test_no_offset_before_enough_messages_or_without_sent_stamps():
    clocks = RobotClocks(ClockConfig(min_messages=3))
    _observe(clocks, 2, 0.3, [0.01, 0.01])
    assert clocks.offset(2) is None and clocks.correction(2) == 0.0
    clocks.observe(3, 0.0, 100.0)  # an older client says nothing
    assert clocks.offset(3) is None


def test_stamps_are_taken_in_the_servers_time():
    clocks = RobotClocks()
    _observe(clocks, 2, 0.3, [0.0] * 5)
    kf = make_keyframe(robot_id=2)
    kf.stamp_s = 50.3
    assert clocks.to_server_time(kf).stamp_s == pytest.approx(50.0)
    kf1 = make_keyframe(robot_id=1)
    assert clocks.to_server_time(kf1) is kf1  # no offset known: as it came


def test_a_clock_far_off_is_said_with_the_fix_and_refuses_rendezvous(caplog):
    clocks = RobotClocks()
    with caplog.at_level(logging.WARNING):
        _observe(clocks, 2, 3600.0, [0.01] * 5)  # a robot whose clock was never set
    assert sum("chrony" in r.message for r in caplog.records) == 1  # said once
    why = clocks.refusal(1, 2)
    assert why is not None and "robot 2's clock is 3600.0 s ahead" in why and "chrony" in why
    assert clocks.refusal(1) is None


def test_bad_clock_configuration_is_refused():
    from coop_slam.errors import ConfigError

    with pytest.raises(ConfigError, match="max_offset_s"):
        RobotClocks(ClockConfig(max_offset_s=0.05, warn_above_s=0.1))


def test_clock_offsets_to_rehearse_are_read_and_bad_ones_refused():
    from coop_slam.playback import PlaybackError, parse_clock_offsets

    assert parse_clock_offsets("2:0.3, 3:-0.1") == {2: 0.3, 3: -0.1}
    assert parse_clock_offsets("") == {}
    for bad in ("2", "x:0.3", "0:0.3", "2:0.3,2:0.1", "2:nan", "2:-1"):
        with pytest.raises(PlaybackError, match="clock offset"):
            parse_clock_offsets(bad)
    from coop_slam.tools.demo_args import parse_args

    with pytest.raises(SystemExit):  # a bag's stamps are its own
        parse_args(["--bag", "x.bag", "--clock-offset", "2:0.3"])


class _Durable:
    def __init__(self):
        from types import SimpleNamespace

        self.pull, self.robots, self.taken, self.requests = None, [1, 2], [], []
        self.server = SimpleNamespace(
            known_robots={1, 2}, vocabulary=SimpleNamespace(word_weights=None)
        )

    def add_keyframe(self, item, session, sequence):
        from types import SimpleNamespace

        self.taken.append(item)
        return SimpleNamespace(merges=[], taken=1, rejected=None, stale=False, duplicate=0)

    def sighting(self, a, b, stamp_s, *_):
        self.requests.append((a, b, stamp_s))
        return None


def test_the_worker_takes_a_late_clocks_stamps_in_the_servers_time():
    """Robot 2's clock runs 0.3 s ahead: its keyframes and its sightings are stored 0.3 s
    earlier, robot 1's as they came."""
    from coop_slam.team.config import ServerConfig
    from coop_slam.team.jobs import RendezvousJob
    from coop_slam.team.worker import ServerWorker

    durable = _Durable()
    worker = ServerWorker(ServerConfig(robots=[1, 2]), lambda resume, load: durable)
    worker.acknowledge = lambda robot_id: None
    worker._publish_requests = lambda: None
    for k in range(5):
        for robot, clock in ((1, 0.0), (2, 0.3)):
            kf = make_keyframe(robot_id=robot, keyframe_id=k + 1, seed=k)
            kf.stamp_s = 10.0 + k + clock
            msg = _message(kf, sent_s=10.0 + k + clock)
            job = worker.intake(msg, robot, arrived_s=10.0 + k + 0.001)
            worker._keyframe(job)
    stamps = {(i.robot_id, i.keyframe_id): i.stamp_s for i in durable.taken}
    for k in range(5):  # from the first message on
        assert stamps[(1, k + 1)] == pytest.approx(10.0 + k)
        assert stamps[(2, k + 1)] == pytest.approx(10.0 + k, abs=2e-3)
    assert worker.clocks.said()[2] == pytest.approx(0.3, abs=2e-3)  # (/server/stats)
    worker.handle(RendezvousJob(2, 1, 20.3, None, sighting=True))
    assert durable.requests[-1][2] == pytest.approx(20.0, abs=2e-3)


def _message(kf, sent_s):
    from coop_slam.wire.codec import WHOLE, encode
    from coop_slam.wire.messages import Stamp

    msg = encode(kf, WHOLE)
    msg.sent = Stamp.from_sec(sent_s)
    return msg


def test_a_sighting_recorded_before_sightings_carried_the_marker_is_read_back():
    """scripts/replay of an older run: its RobotSighting has T_cam_body (placed with the default
    marker) and no marker pose or size."""
    from types import SimpleNamespace

    from coop_slam.geometry import se3
    from coop_slam.markers import MarkerConfig
    from coop_slam.robot_description import describe
    from coop_slam.ros.convert import marker_seen_from_msg, pose_to_msg

    T_cam_body = se3(t=[0.3, 0.1, 2.0])
    old = SimpleNamespace(T_cam_body=pose_to_msg(T_cam_body))
    seen = marker_seen_from_msg(old)
    robot = describe(2, "rgbd", np.eye(4), MarkerConfig())
    np.testing.assert_allclose(robot.T_cam_body(seen), T_cam_body, atol=1e-9)
