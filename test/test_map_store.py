"""The durable team map: the store's round trip, resume after a crash at any point, save/load
into a later session, and in-order exactly-once delivery of keyframe messages."""

import os
import sqlite3

import numpy as np
import pytest

from coop_slam.team.durable import DurableServer, poses_equal
from coop_slam.team.map_store import MapStore, MapStoreError, decode_record, encode_record
from coop_slam.team.server import TeamServer
from coop_slam.wire.delivery import DeliveryError, InOrder, Outbox, OutboxFull
from coop_slam.wire.record import KeyframeError
from helpers import depth_blob, make_keyframe, team_keyframes, team_server_config, team_world


@pytest.fixture(scope="module")
def team():
    points, desc, a, vocab = team_world(24)
    b = team_keyframes(
        2, np.linspace(2.0, 3.0, 6), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
    )
    return a, b, vocab


def _durable(vocab, path, robots=(1, 2), **kw):
    return DurableServer(team_server_config(robots), lambda c: TeamServer(c, vocab), path, **kw)


def _stream(kfs_a, kfs_b):
    """(record, session, sequence) as two clients send them, robot 1 first."""
    out = [(kf, 11, i + 1) for i, kf in enumerate(kfs_a)]
    return out + [(kf, 22, i + 1) for i, kf in enumerate(kfs_b)]


def test_record_round_trip():
    rec = make_keyframe(n=40, robot_id=3, keyframe_id=7)
    rec.depth_image = depth_blob()
    back = decode_record(encode_record(rec))
    assert (back.robot_id, back.keyframe_id, back.stamp_s) == (3, 7, rec.stamp_s)
    assert back.camera == rec.camera
    np.testing.assert_array_equal(back.T_map_cam, rec.T_map_cam)
    for name in (
        "keypoints",
        "descriptors",
        "depths_m",
        "map_point_ids",
        "map_points",
        "depth_image",
    ):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name))
        assert getattr(back, name).dtype == getattr(rec, name).dtype
    with pytest.raises(MapStoreError, match="corrupt"):
        decode_record(b"not a record")


def test_an_update_is_stored_without_what_the_keyframe_saw(tmp_path):
    import dataclasses

    from coop_slam.wire.record import ACTION_UPDATE

    store = MapStore(str(tmp_path / "m.db"), [3])
    new = make_keyframe(n=200, robot_id=3, keyframe_id=7)
    new.depth_image = depth_blob()
    moved = dataclasses.replace(new, action=ACTION_UPDATE, T_map_cam=new.T_map_cam.copy())
    moved.T_map_cam[:3, 3] += 0.1
    store.begin()
    store.log_keyframe(new)
    store.log_keyframe(moved)
    store.commit()
    sizes = [n for (n,) in store.db.execute("SELECT length(payload) FROM inputs ORDER BY seq")]
    assert sizes[1] < sizes[0] / 3
    first, second = (item.record for item in store.inputs())
    np.testing.assert_array_equal(second.T_map_cam, moved.T_map_cam)
    np.testing.assert_array_equal(second.descriptors, new.descriptors)
    np.testing.assert_array_equal(second.keypoints, new.keypoints)
    np.testing.assert_array_equal(second.depth_image, new.depth_image)
    assert second.action == ACTION_UPDATE and first.action == new.action


def test_resume_after_a_crash_at_any_point_equals_an_uninterrupted_server(team, tmp_path):
    kfs_a, kfs_b, vocab = team
    stream = _stream(kfs_a, kfs_b)
    whole = _durable(vocab, str(tmp_path / "whole.db"))
    for rec, session, seq in stream:
        whole.add_keyframe(rec, session, seq)
    assert whole.server.merges and whole.server.groups.groups() == [[1, 2]]
    rng = np.random.default_rng(5)
    for crash_at in sorted(rng.choice(np.arange(3, len(stream) - 1), 2, replace=False)):
        path = str(tmp_path / f"crash{crash_at}.db")
        first = _durable(vocab, path)
        for rec, session, seq in stream[:crash_at]:
            first.add_keyframe(rec, session, seq)
        del first  # a kill -9: nothing closed, nothing flushed beyond the commits
        resumed = _durable(vocab, path, resume=True)
        assert resumed.rebuilt.inputs == crash_at and resumed.rebuilt.max_pose_diff_m < 1e-9
        # The clients send again what was not acknowledged (and a bit more): duplicates.
        acked = {r: resumed.acknowledged(r)[1] for r in (1, 2)}
        for rec, session, seq in stream[max(0, crash_at - 3) :]:
            out = resumed.add_keyframe(rec, session, seq)
            assert out.duplicate == (seq <= acked[rec.robot_id])
        assert poses_equal(resumed.server, whole.server)
        assert [(m.map_a, m.map_b, m.keyframe_b) for m in resumed.server.merges] == [
            (m.map_a, m.map_b, m.keyframe_b) for m in whole.server.merges
        ]
        resumed.close()
    whole.close()


def test_a_deferred_global_ba_runs_when_called_and_a_resume_repeats_it(team, tmp_path):
    """The node defers the global BA after a merge (off the keyframe messages' path) and runs it
    when no message waits: it is logged as a call, so a resumed server reaches the same map."""
    kfs_a, kfs_b, vocab = team
    path = str(tmp_path / "gba.db")
    live = _durable(vocab, path, defer_global_ba=True)
    for rec, session, seq in _stream(kfs_a, kfs_b):
        live.add_keyframe(rec, session, seq)
        if live.server.global_ba_due is not None:
            assert not live.server.global_ba_runs  # not on the message's path
            break
    assert live.server.merges and live.server.global_ba_due is not None
    assert live.run_due_global_ba() and len(live.server.global_ba_runs) == 1
    assert live.server.global_ba_due is None and not live.run_due_global_ba()
    del live
    resumed = _durable(vocab, path, resume=True, defer_global_ba=True)
    assert resumed.rebuilt.max_pose_diff_m < 1e-9 and len(resumed.server.global_ba_runs) == 1
    resumed.close()


def test_gaps_are_held_until_sent_again(team, tmp_path):
    kfs_a, _, vocab = team
    server = _durable(vocab, str(tmp_path / "gaps.db"), robots=(1,))
    out = server.add_keyframe(kfs_a[0], 5, 1)
    assert out.taken == 1
    assert server.add_keyframe(kfs_a[2], 5, 3).held  # 2 was lost on the way
    assert server.acknowledged(1) == (5, 1)
    out = server.add_keyframe(kfs_a[1], 5, 2)  # sent again
    assert out.taken == 2 and server.acknowledged(1) == (5, 3)
    assert server.server.store.keyframe_ids(1) == [1, 2, 3]
    stored = MapStore(str(tmp_path / "gaps.db"))
    assert stored.acks() == {1: (5, 3)} and stored.count_inputs() == 3


def test_a_refused_message_is_acknowledged_and_not_stored(team, tmp_path):
    kfs_a, _, vocab = team
    server = _durable(vocab, str(tmp_path / "refused.db"), robots=(1,))
    server.add_keyframe(kfs_a[0], 5, 1)
    out = server.add_keyframe(kfs_a[0], 5, 2)  # the same keyframe as new again
    assert out.rejected and "already received" in out.rejected[0]
    assert server.acknowledged(1) == (5, 2) and server.store.count_inputs() == 1
    with pytest.raises(KeyframeError, match="unknown"):
        server.add_keyframe(make_keyframe(robot_id=4), 5, 3)


def test_save_and_load_into_a_later_session(team, tmp_path):
    kfs_a, kfs_b, vocab = team
    first = _durable(vocab, str(tmp_path / "day1.db"), robots=(1,))
    for i, kf in enumerate(kfs_a):
        first.add_keyframe(kf, 3, i + 1)
    saved = first.save(str(tmp_path / "kitchen.map"))
    with pytest.raises(MapStoreError, match="own live file"):
        first.save(str(tmp_path / "day1.db"))
    # Day 2: only robot 2 runs; the loaded robot 1 keeps its id, world frame and poses.
    second = _durable(vocab, str(tmp_path / "day2.db"), robots=(2,), load_path=saved)
    assert second.robots == [1, 2] and second.loaded.remapped == {}
    assert poses_equal(second.server, first.server)
    merges = []
    for i, kf in enumerate(kfs_b):
        merges += second.add_keyframe(kf, 9, i + 1).merges
    assert [(m.map_a, m.map_b) for m in merges] == [(1, 2)]
    # The new map file holds both sessions: it resumes alone.
    second.close()
    again = _durable(vocab, str(tmp_path / "day2.db"), robots=(2,), resume=True)
    assert again.robots == [1, 2] and again.server.groups.groups() == [[1, 2]]


def test_loaded_robot_ids_do_not_collide_with_running_ones(team, tmp_path):
    kfs_a, _, vocab = team
    first = _durable(vocab, str(tmp_path / "day1.db"), robots=(1,))
    for i, kf in enumerate(kfs_a[:6]):
        first.add_keyframe(kf, 3, i + 1)
    saved = first.save(str(tmp_path / "old.map"))
    second = _durable(vocab, None, robots=(1,), load_path=saved)
    assert second.loaded.remapped == {1: 2} and second.robots == [1, 2]
    assert second.server.store.keyframe_ids(2) == [1, 2, 3, 4, 5, 6]
    assert second.server.store.keyframe_ids(1) == []


def test_bad_map_files_are_named(team, tmp_path):
    _, _, vocab = team
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"this is no database" * 100)
    with pytest.raises(MapStoreError, match="not a coop_slam map"):
        MapStore(str(junk))
    other = tmp_path / "other.db"
    sqlite3.connect(str(other)).execute("CREATE TABLE t (x)").connection.commit()
    with pytest.raises(MapStoreError, match="not a coop_slam map"):
        MapStore(str(other))
    newer = MapStore(str(tmp_path / "newer.db"), [1])
    newer.db.execute("UPDATE meta SET value='99' WHERE key='schema_version'")
    newer.close()
    with pytest.raises(MapStoreError, match="schema 99"):
        MapStore(str(tmp_path / "newer.db"))
    existing = MapStore(str(tmp_path / "existing.db"), [1])
    existing.begin()
    existing.log_keyframe(make_keyframe())
    existing.commit()
    existing.close()
    with pytest.raises(MapStoreError, match="resume"):
        _durable(vocab, str(tmp_path / "existing.db"))
    with pytest.raises(MapStoreError, match="not found"):
        _durable(vocab, None, load_path=str(tmp_path / "missing.map"))
    with pytest.raises(MapStoreError, match="does not exist"):
        MapStore(os.path.join(str(tmp_path), "no", "such", "folder.db"))


def test_in_order_takes_each_message_once():
    o = InOrder(max_held=2)
    assert o.arrive(7, 1, "a").take == ["a"]
    o.taken(1)
    assert o.arrive(7, 1, "a").duplicate
    assert o.arrive(7, 3, "c").held and o.arrive(7, 4, "d").held
    assert not o.arrive(7, 5, "e").held and o.held == 2  # the bound: sent again later
    assert o.arrive(7, 2, "b").take == ["b", "c", "d"]
    assert o.arrive(6, 9, "old").stale
    assert o.arrive(8, 1, "new").take == ["new"]  # a restarted client
    assert o.arrive(0, 0, "bag").take == ["bag"]


def test_outbox_sends_again_what_is_not_acknowledged():
    box = Outbox(max_unacked=3, resend_after_s=1.0)
    seqs = [box.add(m, now=0.0)[1] for m in "abc"]
    assert seqs == [1, 2, 3] and box.due(now=0.5) == []
    assert box.ack(box.session, 1) == 1 and box.ack(box.session + 1, 3) == 0
    assert box.due(now=1.0) == ["b", "c"] and box.resent == 2
    box.add("d", now=1.0)
    assert box.full and box.unacked == 3
    with pytest.raises(OutboxFull, match="max_unacked"):  # the newest is refused, never the oldest
        box.add("e", now=1.0)
    assert box.unacked == 3 and box.sequence == 4  # no sequence used: no gap at the server
    assert box.due(now=100.0) == ["b", "c", "d"]


def test_outbox_continues_a_session_or_numbers_anew():
    """A restarted client's messages from its disk: the old session continued (new ones follow
    the last kept), or numbered 1, 2, ... in a new one."""
    box = Outbox(resend_after_s=1.0)
    box.restore(55, 9, [(8, "h"), (9, "i")], now=0.0)
    assert box.add("j", now=0.0) == (55, 10) and box.unacked == 3
    assert box.ack(55, 8) == 1 and box.pending(now=0.0) == ["i", "j"]
    assert box.renumber(66) == [(1, "i"), (2, "j")] and box.add("k") == (66, 3)
    assert box.ack(66, 2) == 2 and box.pending() == ["k"]


def test_outbox_does_not_send_again_what_the_server_received():
    """A server busy storing (a merge, a global BA) says which messages it has received: they
    do not go again while it works, for up to max_resend_after_s, unless another server run
    acknowledges (a restart lost them); receipts of another client session count for nothing."""
    box = Outbox(resend_after_s=1.0, max_resend_after_s=10.0)
    box.server_is(41)
    for m in "abc":
        box.add(m, now=0.0)
    box.received(box.session, 1, now=0.1)
    box.received(box.session, 3, now=0.1)
    box.received(box.session + 1, 2, now=0.1)  # an earlier client run's message 2
    assert box.due(now=1.0) == ["b"]  # only the one the server did not get
    assert box.due(now=5.0) == ["b"]
    assert box.due(now=10.1) == ["a", "b", "c"]  # a, c: 10 s not stored, maybe dropped
    box.received(box.session, 1, now=11.0)
    box.received(box.session, 3, now=11.0)
    box.server_is(41)  # the same run: nothing changes
    assert box.due(now=12.5) == []  # (b backs off: 8 s now)
    box.server_is(42)  # restarted: what it had received is gone
    assert box.due(now=13.0) == ["a", "c"]
    assert box.ack(box.session, 3) == 3 and box.unacked == 0


def test_outbox_waits_for_what_is_still_crossing_a_slow_link():
    """Receipts show the link delivers 8 kB/s (what arrived over the last 10 s): a message goes
    again only once its bytes and those ahead of it could have crossed (a 32 kB keyframe: 4 s),
    not every second while its first copy is still on its way; without sizes, waits as before."""
    box = Outbox(resend_after_s=1.0, max_resend_after_s=30.0)
    for k in range(10):  # 8 kB a second for 10 s
        box.add(f"s{k}", now=float(k), nbytes=8000)
        box.received(box.session, k + 1, now=float(k) + 0.9)
        box.ack(box.session, k + 1)
    box.received(box.session, 10, now=10.0)  # a second receipt of one message counts once
    assert box.link_Bps == pytest.approx(8000.0, rel=0.15)
    rate = box.link_Bps
    box.add("b", now=10.0, nbytes=32000)
    box.add("c", now=10.0, nbytes=8000)
    b_due, c_due = 10.0 + 1.0 + 32000 / rate, 10.0 + 1.0 + 40000 / rate
    assert box.due(now=11.0) == [] and box.due(now=b_due - 0.05) == []
    assert box.due(now=b_due + 0.01) == ["b"]
    assert box.due(now=c_due + 0.01) == ["c"]
    # A queue longer than max_resend_after_s at this rate: the last waits for all of it, the
    # copies of b and c that went meanwhile included.
    for k in range(50):
        box.add(f"q{k}", now=20.0, nbytes=8000)
    last_due = 20.0 + 1.0 + (2 * 40000 + 50 * 8000) / rate
    assert last_due > 20.0 + 30.0
    late = [t for t in np.arange(20.0, last_due + 1.0, 0.5) if "q49" in box.due(now=float(t))]
    assert late and late[0] >= last_due - 0.5
    # A message the link went past (a later one arrived) was lost: it goes again at once.
    lossy = Outbox(resend_after_s=1.0, max_resend_after_s=30.0)
    for k in range(10):
        lossy.add(f"m{k}", now=float(k), nbytes=8000)
        if k != 5:  # m5 lost on the way
            lossy.received(lossy.session, k + 1, now=float(k) + 0.9)
    assert lossy.link_Bps > 0 and lossy.due(now=10.0) == ["m5"]
    plain = Outbox(resend_after_s=1.0)
    plain.add("x", now=0.0)
    plain.received(plain.session, 1, now=0.5)
    plain.add("y", now=1.0)
    assert plain.link_Bps == 0.0 and plain.due(now=2.0) == ["y"]


def test_outbox_backs_off_per_message_while_the_server_lags():
    """The oldest unacknowledged message (the one the server waits for) goes again every 1 s; any
    other 1 s after it was sent, then 2 s, 4 s later (at most the cap); at most resend_window
    messages per call, the oldest first."""
    box = Outbox(max_unacked=100, resend_after_s=1.0, resend_window=2, max_resend_after_s=4.0)
    box.add("a", now=0.0)
    box.add("b", now=0.0)
    sent = {"a": [], "b": []}
    for t in np.arange(0.0, 20.0, 0.5):
        for m in box.due(now=float(t)):
            sent[m].append(float(t))
    assert sent["a"] == [float(t) for t in range(1, 20)]  # the oldest: every second
    assert sent["b"] == [1.0, 3.0, 7.0, 11.0, 15.0, 19.0]  # waits 1, 2, 4, then capped at 4 s
    assert box.ack(box.session, 1) == 1  # b is the oldest now: due 1 s after its last send
    assert box.due(now=19.5) == [] and box.due(now=20.0) == ["b"] and box.due(now=21.0) == ["b"]
    for m in "cde":
        box.add(m, now=21.0)
    assert box.due(now=22.0) == ["b", "c"]  # the window holds 2
    assert box.due(now=22.0) == ["d", "e"]
    with pytest.raises(DeliveryError, match="max_resend_after_s"):
        Outbox(resend_after_s=5.0, max_resend_after_s=1.0)
