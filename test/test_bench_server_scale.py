"""The server-scale bench's replay machinery (tools/bench_server_scale.py) on a tiny two-robot
stream fed fast: every message is processed once and in order, the figures agree with what the
server did. Speed is never asserted (that is the bench's job)."""

import dataclasses

import numpy as np
import pytest

from coop_slam.tools.bench_server_scale import (
    Arrival,
    backlog_at,
    bench_worker,
    plot_run,
    replay_at_rate,
    scale_figures,
)
from coop_slam.wire.codec import Outgoing, encode
from coop_slam.wire.record import ACTION_REMOVE, ACTION_UPDATE, KeyframeRecord
from helpers import team_keyframes, team_server_config, team_world

RATE = 50.0  # x the stream's real rate: its 25 s arrive in 0.5 s


def _sent(t_s, rec, session, sequence, how=None):
    msg = encode(rec, how or Outgoing(False), f"robot_{rec.robot_id}/map")
    msg.session, msg.sequence = session, sequence
    return Arrival(t_s, rec.robot_id, msg)


def _stream(kfs_a, kfs_b) -> list[Arrival]:
    """Robot 1 sends a keyframe a second, robot 2 from 8 s on, interleaved; then robot 1 sends a
    delta update of its keyframe 3 (moved 1 cm), removes keyframe 5, and robot 2 sends a delta
    update of a keyframe the server never got (refused)."""
    out = [_sent(float(k), kf, 11, k + 1) for k, kf in enumerate(kfs_a)]
    out += [_sent(8.5 + k, kf, 22, k + 1) for k, kf in enumerate(kfs_b)]
    moved = dataclasses.replace(kfs_a[2], action=ACTION_UPDATE, T_map_cam=kfs_a[2].T_map_cam.copy())
    moved.T_map_cam[:3, 3] += 0.01
    removal = KeyframeRecord(1, 5, 0.0, None, np.eye(4), map_segment=0, action=ACTION_REMOVE)
    unknown = dataclasses.replace(kfs_b[0], keyframe_id=999, action=ACTION_UPDATE)
    t_end, n_a, n_b = float(len(kfs_a)), len(kfs_a), len(kfs_b)
    patch = Outgoing(True, np.zeros(0, np.uint32))  # the pose only
    out += [
        _sent(t_end, moved, 11, n_a + 1, patch),
        _sent(t_end + 0.5, removal, 11, n_a + 2),
        _sent(t_end + 1.0, unknown, 22, n_b + 1, patch),
    ]
    return sorted(out, key=lambda a: a.t_s)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    points, desc, kfs_a, vocab = team_world(24)
    kfs_b = team_keyframes(
        2, np.linspace(2.0, 3.0, 6), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
    )
    arrivals = _stream(kfs_a, kfs_b)
    path = str(tmp_path_factory.mktemp("scale") / "team_map.db")
    worker = bench_worker(team_server_config(), vocab, path)
    try:
        run = replay_at_rate(arrivals, worker, RATE)
        assert worker.map_builder.wait_idle(60.0)
        yield arrivals, run, worker.server, kfs_a, worker
    finally:
        worker.close()
        worker.durable.close()


def test_every_message_is_processed_once_in_arrival_order(replayed):
    arrivals, run, server, kfs_a, _ = replayed
    assert [m.robot_id for m in run.messages] == [a.robot_id for a in arrivals]
    assert len(run.messages) == len(arrivals) == 24 + 6 + 3
    assert [m.kind for m in run.messages].count("remove") == 1
    ends = [m.end_s for m in run.messages]
    for prev_end, m in zip([0.0] + ends, run.messages):
        assert m.arrive_s <= m.start_s <= m.end_s
        assert m.start_s >= prev_end  # one consumer: a message after the one before it
    assert run.rejected == 1  # the delta update of a keyframe the server never got
    assert len(server.store) == 24 + 6 - 1
    # The delta update was completed from the stored keyframe: moved pose, same descriptors.
    stored = server.store.record((1, 3))
    assert stored.T_map_cam[0, 3] == pytest.approx(kfs_a[2].T_map_cam[0, 3] + 0.01)
    np.testing.assert_array_equal(stored.descriptors, kfs_a[2].descriptors)
    assert run.stream_s == pytest.approx(arrivals[-1].t_s - arrivals[0].t_s)


def test_backlog_and_merges_agree_with_the_server(replayed):
    arrivals, run, server, _, worker = replayed
    builder = worker.map_builder
    assert builder.built >= 1 and builder.failed == 0  # team clouds, beside the worker
    arr = run.arrays()
    t = np.linspace(0.0, arr["end_s"][-1], 500)
    backlog = backlog_at(run, t)
    assert backlog.min() >= 0 and backlog.max() <= len(arrivals)
    assert backlog_at(run, [arr["end_s"][-1]])[0] == 0  # drained at the end
    assert backlog_at(run, arr["arrive_s"]).min() >= 1  # a message counts until it is done
    assert server.merges, "the two robots' maps merge (place recognition)"
    assert len(run.merge_latencies_s) == len(run.merge_times_s) == len(server.merges)
    assert len(run.merge_own_s) == len(server.merges)
    assert sum(m.merges for m in run.messages) == len(server.merges)
    assert min(run.merge_own_s) >= 0.0
    for latency, own in zip(run.merge_latencies_s, run.merge_own_s):
        assert latency >= own  # the message's own time, plus its wait in the queue


def test_figures_are_consistent(replayed, tmp_path):
    arrivals, run, server, _, _ = replayed
    figures = {name: (value, unit) for name, value, unit in scale_figures(run)}
    assert all(name.startswith("server_scale_") for name in figures)
    assert all(np.isfinite(v) for v, _ in figures.values())
    value = {name: v for name, (v, _) in figures.items()}
    assert value["server_scale_robots"] == 2
    assert value["server_scale_keyframe_messages"] == len(arrivals)
    assert value["server_scale_new_messages"] == 30
    assert value["server_scale_update_messages"] == 2
    assert value["server_scale_remove_messages"] == 1
    assert value["server_scale_rejected_messages"] == 1
    assert value["server_scale_replay_rate"] == RATE
    assert value["server_scale_merges"] == len(server.merges)
    assert 0 <= value["server_scale_merge_latency_mean"] <= value["server_scale_merge_latency_max"]
    assert 0 <= value["server_scale_merge_own_time_max"] <= value["server_scale_merge_latency_max"]
    assert value["server_scale_ms_per_message_mean"] <= value["server_scale_ms_per_message_max"]
    assert value["server_scale_backlog_max"] >= max(1, value["server_scale_backlog_at_stream_end"])
    assert value["server_scale_drain_after_stream_end"] >= 0
    assert value["server_scale_queue_wait_mean"] >= 0
    assert 0 < value["server_scale_worker_busy"] <= 100.0 + 1e-6
    png = plot_run(run, str(tmp_path / "scale.png"), "test")
    with open(png, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
