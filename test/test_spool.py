"""A client's spool (coop_slam.uplink.spool): a client killed with kill -9 loses no keyframe
message it numbered, whatever became of each (dropped by the radio, held by the server behind a
gap, taken with the acknowledgement lost, acknowledged and not yet deleted); the restarted client
sends them first, in the old session or a new one as the server's acknowledgement says, and the
server stores every keyframe once. Plus the spool's bound, its lock and its durability."""

import logging
import multiprocessing
import os
import pickle
import signal
import sqlite3

import numpy as np
import pytest

from coop_slam.team.durable import DurableServer
from coop_slam.team.server import TeamServer
from coop_slam.uplink.config import UplinkConfig
from coop_slam.uplink.engine import ClientUplink
from coop_slam.uplink.spool import Spool, SpooledMessage, SpoolError
from coop_slam.vo.types import EVENT_KEYFRAME_NEW, EVENT_KEYFRAME_UPDATE, VoEvent
from coop_slam.wire.codec import decode
from coop_slam.wire.delivery import DeliveryConfig
from coop_slam.wire.messages import KIND_KEYFRAME, KeyframeAck
from helpers import map_keyframe, team_keyframes, team_server_config, team_world

ROBOT = 2
MAP_ID = "map-a"
fork = multiprocessing.get_context("fork")


class PickleSerializer:
    """The wire message as a pickle: what a test needs of genpy's serialization."""

    format_id = "pickle-test"

    def dumps(self, msg) -> bytes:
        return pickle.dumps(msg)

    def loads(self, data: bytes):
        return pickle.loads(data)


@pytest.fixture(scope="module")
def world():
    points, desc, _, vocab = team_world(24)
    first = team_keyframes(ROBOT, np.linspace(2.0, 2.6, 6), points, desc, seed=100, t0=100.0)
    second = team_keyframes(ROBOT, np.linspace(2.7, 3.0, 3), points, desc, seed=200, t0=200.0)
    return first, second, vocab


def _events(records) -> list[VoEvent]:
    """Each keyframe new, then the one before it moved by local BA (a delta with moves)."""
    out = []
    for i, rec in enumerate(records):
        out.append(VoEvent(EVENT_KEYFRAME_NEW, 0, rec.keyframe_id, map_keyframe(rec)))
        if i:
            prev = records[i - 1]
            out.append(
                VoEvent(EVENT_KEYFRAME_UPDATE, 0, prev.keyframe_id, map_keyframe(prev, 0.01))
            )
    return out


def _uplink(path, camera, max_unacked=1000, max_mb=200.0) -> ClientUplink:
    spool = Spool(path, ROBOT, PickleSerializer.format_id, int(max_mb * 1e6))
    up = ClientUplink(
        ROBOT,
        UplinkConfig(hold_new_s=0.0, coalesce_updates_s=0.0, budget_kBps=0.0),
        DeliveryConfig(max_unacked=max_unacked),
        serializer=PickleSerializer(),
        spool=spool,
    )
    up.camera = camera
    return up


def _durable(vocab, path):
    return DurableServer(team_server_config((1, ROBOT)), lambda c: TeamServer(c, vocab), path)


def _ack(durable) -> KeyframeAck:
    """What the server acknowledges (as ServerWorker.acknowledge)."""
    session, sequence = durable.acknowledged(ROBOT)
    last_kf, last_seg = durable.last_ids().get(ROBOT, (0, 0))
    return KeyframeAck(
        robot_id=ROBOT,
        session=session,
        sequence=sequence,
        last_keyframe_id=last_kf,
        last_map_segment=last_seg,
        durable=True,
        refused_keyframe_ids=durable.refused(ROBOT),
        server_session=7,
    )


def _deliver(durable, messages, rejected: list) -> None:
    server = durable.server
    for m in messages:
        item = decode(m, server.known_robots, server.vocabulary.word_weights)
        rejected += durable.add_keyframe(item, m.session, m.sequence).rejected or []


def _killed_client(path, camera, records, first_ack, conn, die_in_ack: bool) -> None:
    """The child: a client sends ``records``' messages and is killed (SIGKILL) before the
    server's acknowledgement of them reaches its spool."""
    up = _uplink(path, camera)
    up.server_found(first_ack, MAP_ID)
    step = up.events(_events(records), 1.0)
    conn.send((step.messages, [n.record for n in step.notes]))
    if die_in_ack:  # acknowledged, killed before the spool deletes what the ack covers
        Spool.ack = lambda self, session, sequence: os.kill(os.getpid(), signal.SIGKILL)
        up.acknowledged(conn.recv())
    os.kill(os.getpid(), signal.SIGKILL)


def _run_killed_client(path, camera, records, durable, fates) -> tuple[list, list, list]:
    """Run the child; ``fates``: sequences the server takes before the ack the client gets
    (``ack``), then those it gets after (the rest are dropped by the radio). Returns the
    messages sent, the records made, and the server's refusals."""
    parent, child = fork.Pipe()
    proc = fork.Process(
        target=_killed_client,
        args=(path, camera, records, _ack(durable), child, bool(fates.get("ack"))),
    )
    proc.start()
    sent, made = parent.recv()
    rejected: list = []
    by_seq = {m.sequence: m for m in sent}
    _deliver(durable, [by_seq[q] for q in fates.get("ack", [])], rejected)
    if fates.get("ack"):
        parent.send(_ack(durable))
    _deliver(durable, [by_seq[q] for q in fates.get("after", [])], rejected)
    proc.join(30)
    assert proc.exitcode == -signal.SIGKILL
    return sent, made, rejected


# Sequences 1-2 taken and acknowledged (the client dies before deleting them), 3-4 taken (their
# ack lost), 5-6 dropped, 7-8 held behind that gap, 9-11 dropped.
CONTINUE = {"ack": [1, 2], "after": [3, 4, 7, 8]}
RESEQUENCE = {}  # the server saw nothing of the killed client's session


@pytest.mark.parametrize(
    "fates, ack_at_start",
    [(CONTINUE, True), (RESEQUENCE, True), (CONTINUE, False), (RESEQUENCE, False)],
    ids=["continue-old-session", "re-sequence", "no-ack-yet-continue", "no-ack-yet-re-sequence"],
)
def test_a_killed_client_loses_nothing_and_the_map_gets_nothing_twice(
    world, tmp_path, fates, ack_at_start
):
    first, second, vocab = world
    camera, path = first[0].camera, str(tmp_path / "spool.db")
    durable = _durable(vocab, str(tmp_path / "map.db"))
    sent, made, rejected = _run_killed_client(path, camera, first, durable, fates)
    assert [m.sequence for m in sent] == list(range(1, 12))  # 6 new, 5 deltas
    old_session = sent[0].session

    up = _uplink(path, camera)
    assert up.waiting_for_server and up.unacked == 11  # nothing lost, nothing sent yet
    going = up.server_found(_ack(durable) if ack_at_start else None, MAP_ID)
    step = up.events(_events(second), 2.0)  # the new odometry
    if not ack_at_start:  # nothing goes until the server has said what it holds
        assert going == [] and step.messages == [] and up.due_again(now=1e12) == []
        going = up.server_found(_ack(durable), MAP_ID)
    else:
        going += step.messages
    taken = set(fates.get("ack", []) + fates.get("after", [])) - {7, 8}  # held: not taken yet
    if fates:  # the old session continues: what the server took does not go again
        assert {m.session for m in going} == {old_session}
        assert [m.sequence for m in going][:7] == list(range(5, 12))
    else:  # numbered anew: 1, 2, ... in a newer session, the kept ones first
        assert {m.session for m in going} == {going[0].session} and going[0].session > old_session
        assert [m.sequence for m in going] == list(range(1, len(going) + 1))
        assert [m.keyframe_id for m in going[:11]] == [m.keyframe_id for m in sent]
    assert up.resent_from_spool == 11 - len(taken) and up.keyframes_sent == 3
    _deliver(durable, going, rejected)
    up.acknowledged(_ack(durable))

    assert not rejected  # no "already received as new", no delta of a keyframe not held
    assert durable.keyframes_stored()[ROBOT] == 9
    twice = durable.store.db.execute(
        "SELECT keyframe_id, COUNT(*) FROM inputs WHERE kind='keyframe' AND action=0 "
        "GROUP BY keyframe_id HAVING COUNT(*) > 1"
    ).fetchall()
    assert twice == []
    new = [n.record for n in step.notes]
    assert min(r.keyframe_id for r in new) > max(m.keyframe_id for m in sent)
    assert min(r.map_segment for r in new) > max(m.map_segment for m in sent)
    latest = {r.keyframe_id: r for r in made + new}  # the client's last word on each keyframe
    for kid, rec in latest.items():
        stored = durable.server.stored_record(ROBOT, rec.map_segment, kid)
        np.testing.assert_allclose(  # a delta taken twice would have moved them twice
            stored.map_points_per_keypoint(), rec.map_points_per_keypoint(), atol=1e-3
        )
    assert up.spool.count == 0 and up.unacked == 0
    assert _spool_rows(path) == 0
    up.close()
    durable.close()


def _spool_rows(path) -> int:
    db = sqlite3.connect(path)
    try:
        return db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
    finally:
        db.close()


def test_a_spool_made_for_another_map_is_set_aside_and_nothing_of_it_goes(world, tmp_path):
    """A spool left by another mission (another team map): renamed, not sent; the new keyframes
    start above the server's ids only, in its first segment."""
    first, second, vocab = world
    camera, path = first[0].camera, str(tmp_path / "spool.db")
    durable = _durable(vocab, str(tmp_path / "map.db"))
    _run_killed_client(path, camera, first, durable, RESEQUENCE)
    up = _uplink(path, camera)
    assert up.server_found(_ack(durable), "map-b") == []
    assert up.spool.count == 0 and up.unacked == 0
    (aside,) = [p for p in os.listdir(tmp_path) if p.startswith("spool.db.stale-")]
    assert _spool_rows(str(tmp_path / aside)) == 11  # kept, never sent
    step = up.events(_events(second), 2.0)
    assert [m.sequence for m in step.messages] == [1, 2, 3, 4, 5]
    assert [m.keyframe_id for m in step.messages if m.kind == KIND_KEYFRAME] == [1, 2, 3]
    assert {m.map_segment for m in step.messages} == {0}
    up.close()
    # The same with the server heard from only later: what was numbered meanwhile goes, anew.
    path = str(tmp_path / "later" / "spool.db")
    _run_killed_client(path, camera, first, durable, RESEQUENCE)
    up = _uplink(path, camera)
    up.server_found(None)
    assert up.events(_events(second), 2.0).messages == []
    going = up.server_found(_ack(durable), "map-c")
    assert [m.sequence for m in going] == [1, 2, 3, 4, 5] and up.spool.count == 5
    assert up.spool.load().map_id == "map-c"
    up.close()
    durable.close()


def test_a_full_spool_refuses_the_newest_says_so_once_and_leaves_no_gap(world, tmp_path, caplog):
    """Full (max_unacked, or spool_max_mb), the client refuses new messages and keeps the oldest
    (the server waits for those); a refused keyframe's next update goes whole; the server takes
    everything kept, in order."""
    first, _, vocab = world
    camera = first[0].camera
    durable = _durable(vocab, str(tmp_path / "map.db"))
    up = _uplink(str(tmp_path / "spool.db"), camera, max_unacked=3)
    up.server_found(_ack(durable), MAP_ID)
    new = [VoEvent(EVENT_KEYFRAME_NEW, 0, r.keyframe_id, map_keyframe(r)) for r in first[:5]]
    with caplog.at_level(logging.WARNING, logger="coop_slam.uplink.engine"):
        sent = up.events(new, 1.0).messages
        up.events(new[4:], 1.0)  # the same keyframe again: still full
    assert [m.sequence for m in sent] == [1, 2, 3] and up.refused_full == 3
    full_lines = [r for r in caplog.records if "not acknowledged by the server" in r.message]
    assert len(full_lines) == 1 and "spool.db" in full_lines[0].message
    rejected: list = []
    _deliver(durable, sent, rejected)
    up.acknowledged(_ack(durable))
    assert up.spool.count == 0 and not rejected
    moved = VoEvent(EVENT_KEYFRAME_UPDATE, 0, 4, map_keyframe(first[3], 0.01))
    (again,) = up.events([moved], 2.0).messages
    assert again.sequence == 4 and again.kind == KIND_KEYFRAME and again.keyframe[0].replaces
    _deliver(durable, [again], rejected)
    assert not rejected and durable.keyframes_stored()[ROBOT] == 4
    up.close()
    # The byte bound (one byte): the first message goes (an empty spool takes any), no other.
    small = _uplink(str(tmp_path / "small.db"), camera, max_mb=1e-6)
    small.server_found(_ack(durable), MAP_ID)
    assert [m.sequence for m in small.events(new[:3], 1.0).messages] == [1]
    assert small.refused_full == 2
    small.close()
    durable.close()


def test_two_clients_of_one_robot_cannot_share_a_spool_and_foreign_spools_are_set_aside(tmp_path):
    path = str(tmp_path / "robot_2" / "spool.db")
    spool = Spool(path, ROBOT, "fmt-1", 10**6)
    with pytest.raises(SpoolError, match="in use by another process"):
        Spool(path, ROBOT, "fmt-1", 10**6)
    spool.append(SpooledMessage(5, 1, 1, 0, True, b"x" * 10))
    spool.close()
    other = Spool(path, 3, "fmt-1", 10**6)  # robot 3's client given robot 2's file
    assert other.count == 0 and "robot 2's" in other.set_aside_as[0][1]
    other.close()
    os.replace(other.set_aside_as[0][0], path)
    newer = Spool(path, ROBOT, "fmt-2", 10**6)  # another message version: not decoded
    assert newer.count == 0 and "another version" in newer.set_aside_as[0][1]
    newer.close()


def _writer(path: str) -> None:
    """The child of the durability test: appends 45 kB messages until it is killed."""
    spool = Spool(path, ROBOT, "fmt", 10**12)
    state = spool.load()
    q = state.last_sequence
    while True:
        q += 1
        body = np.random.default_rng(q).bytes(45_000)
        spool.append(SpooledMessage(1, q, q, 0, True, body))
        if q % 3 == 0:
            spool.ack(1, q - 2)


def test_a_spool_survives_kill_9_at_any_point(tmp_path):
    """kill -9 while appending and deleting: the file is intact, what it holds is contiguous and
    every payload whole; the lock goes with the process."""
    path = str(tmp_path / "spool.db")
    rng = np.random.default_rng(0)
    for _ in range(12):
        proc = fork.Process(target=_writer, args=(path,))
        proc.start()
        proc.join(float(rng.uniform(0.05, 0.3)))
        os.kill(proc.pid, signal.SIGKILL)
        proc.join()
        spool = Spool(path, ROBOT, "fmt", 10**12)  # the lock is free again
        assert spool.db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        state = spool.load()
        seqs = [m.sequence for m in state.messages]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) if seqs else True
        assert not seqs or seqs[-1] == state.last_sequence
        for m in state.messages:
            assert m.payload == np.random.default_rng(m.sequence).bytes(45_000)
        spool.close()
    assert state.last_sequence > 0
