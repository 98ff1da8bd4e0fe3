"""A client's uplink (coop_slam.uplink): when its keyframe records go (the holdback: new keyframes
wait and go as local BA left them, culled ones never, updates of sent keyframes go coalesced),
and the engine the client node and the bench drive: events in, numbered messages of each kind out,
requests answered, acknowledgements taken, a restart continuing above the server's ids."""

import dataclasses

import numpy as np
import pytest

from coop_slam.config import ConfigError
from coop_slam.uplink.config import UplinkConfig
from coop_slam.uplink.holdback import Holdback
from coop_slam.uplink.planner import Planner
from coop_slam.wire.messages import KeyframeRequest
from coop_slam.wire.record import ACTION_NEW, ACTION_REMOVE, ACTION_UPDATE
from helpers import make_keyframe, map_keyframe


def _moved(rec, action, dx):
    out = dataclasses.replace(rec, action=action, T_map_cam=rec.T_map_cam.copy())
    out.T_map_cam[0, 3] += dx
    return out


def _what(records):
    return [(r.keyframe_id, r.action, round(float(r.T_map_cam[0, 3]), 3)) for r in records]


def test_a_full_mode_budget_keeps_a_whole_keyframe_in_hand_for_the_servers_requests():
    """What the server asks for goes whatever the budget holds; in full mode the bucket keeps one
    whole keyframe in hand for it, so a request does not take the robot over its budget."""
    from coop_slam.uplink.budget import RadioBudget

    budget = RadioBudget(10.0, reserve="whole")  # 10 kB/s
    budget.settle("whole", 0.0, 20_000)  # a first whole keyframe (asked for): 20 kB in debt
    assert budget.capacity == 40_000  # one to send and one in hand
    assert budget.take("whole", 0.0) is None
    assert budget.take("whole", 5.9) is None  # 39 kB
    assert budget.take("whole", 6.0) == pytest.approx(20_000)
    budget.settle("whole", 0.0, 20_000)  # the server asks for one: it goes from the hand
    assert budget.tokens == pytest.approx(0.0)
    assert RadioBudget(10.0).capacity == 5000  # no reserve: half a second's worth


def test_new_keyframes_wait_and_go_as_they_are_then_culled_ones_never():
    hold = Holdback(hold_new_s=1.0, coalesce_s=1.0)
    kf1, kf2 = make_keyframe(keyframe_id=1), make_keyframe(keyframe_id=2, seed=1)
    x1 = float(kf1.T_map_cam[0, 3])
    assert hold.offer(kf1, 0.0) == []
    assert hold.offer(_moved(kf1, ACTION_UPDATE, 0.01), 0.4) == []
    assert hold.offer(kf2, 0.5) == []
    assert hold.offer(dataclasses.replace(kf2, action=ACTION_REMOVE), 0.8) == []  # culled
    assert hold.due(0.99) == [] and len(hold) == 1
    # keyframe 1 goes as new, with local BA's pose; keyframe 2 never goes
    assert _what(hold.due(1.0)) == [(1, ACTION_NEW, round(x1 + 0.01, 3))]
    assert len(hold) == 0 and hold.due(10.0) == []


def test_updates_of_a_sent_keyframe_go_once_per_interval_the_latest():
    hold = Holdback(hold_new_s=1.0, coalesce_s=1.0)
    kf = make_keyframe(keyframe_id=4)
    x = float(kf.T_map_cam[0, 3])
    hold.offer(kf, 0.0)
    assert len(hold.due(1.0)) == 1
    for t, dx in ((1.2, 0.01), (1.5, 0.02), (2.1, 0.03)):
        assert hold.offer(_moved(kf, ACTION_UPDATE, dx), t) == []
    assert hold.due(2.19) == []
    assert _what(hold.due(2.2)) == [(4, ACTION_UPDATE, round(x + 0.03, 3))]
    hold.offer(_moved(kf, ACTION_UPDATE, 0.04), 2.3)
    # a removal goes at once and takes the held update with it
    assert _what(hold.offer(dataclasses.replace(kf, action=ACTION_REMOVE), 2.5)) == [
        (4, ACTION_REMOVE, round(x, 3))
    ]
    assert len(hold) == 0


def test_data_time_going_back_lets_what_is_held_go():
    """A looped bag or a reset clock: records held at a later data time go at once, not when
    data time has caught up with them."""
    hold = Holdback(hold_new_s=1.0, coalesce_s=1.0)
    hold.offer(make_keyframe(keyframe_id=1), 100.0)
    hold.offer(make_keyframe(keyframe_id=2), 100.5)
    assert [r.keyframe_id for r in hold.due(100.6)] == []
    assert [r.keyframe_id for r in hold.due(3.0)] == [1, 2]


def test_flush_sends_everything_held_and_zero_waits_send_at_once():
    hold = Holdback(hold_new_s=1.0, coalesce_s=1.0)
    hold.offer(make_keyframe(keyframe_id=1), 0.0)
    hold.offer(make_keyframe(keyframe_id=2), 0.1)
    assert [r.keyframe_id for r in hold.flush()] == [1, 2]
    now = Holdback()
    kf = make_keyframe(keyframe_id=3)
    assert _what(now.offer(kf, 0.0)) == _what([kf])
    upd = _moved(kf, ACTION_UPDATE, 0.01)
    assert _what(now.offer(upd, 0.1)) == _what([upd]) and len(now) == 0


def test_uplink_offers_through_its_holdback_and_prepares_deltas_in_sending_order():
    """What the server ends up holding is the keyframe's last state, with the delta protocol
    intact: the update after a held new keyframe is a patch against what that new carried (the
    points local BA moved while it was held), not against the keyframe as first made."""
    uplink = Planner(UplinkConfig(hold_new_s=0.5, coalesce_updates_s=0.5, budget_kBps=0.0))
    kf = make_keyframe(n=60, keyframe_id=7)
    assert uplink.offer(kf, 0.0) == []
    moved = _moved(kf, ACTION_UPDATE, 0.02)
    moved.map_points = kf.map_points + np.float32(0.05)  # every point moved while held
    uplink.offer(moved, 0.3)
    going = uplink.due(0.5)
    assert len(going) == 1 and going[0][0].action == ACTION_NEW and not going[0][1].delta
    np.testing.assert_array_equal(going[0][0].map_points, moved.map_points)
    again = _moved(moved, ACTION_UPDATE, 0.01)
    again.map_points = moved.map_points.copy()
    again.map_points[:3] += np.float32(0.05)  # three points moved since the new went
    uplink.offer(again, 0.6)
    ((rec, out),) = uplink.due(1.1)
    assert rec.action == ACTION_UPDATE and out.delta and len(out.patched) == 0
    # (they moved 5 cm: a move in steps of 0.24 mm)
    assert sorted(rec.map_point_ids[out.moves[0]]) == sorted(
        rec.map_point_ids[rec.map_point_ids != 0][:3]
    )
    # pull mode (low-bandwidth): no holding, its own rules
    pull = Planner(UplinkConfig(mode="pull", pull_budget_kBps=0.0))
    ((rec, out),) = pull.offer(make_keyframe(keyframe_id=8), 0.0)
    assert out.signature


@pytest.mark.parametrize(
    "field, value", [("hold_new_s", -1.0), ("coalesce_updates_s", -0.1), ("idle_flush_s", 0.0)]
)
def test_bad_holdback_settings_are_named(field, value):
    with pytest.raises(ConfigError, match=f"uplink.{field}"):
        UplinkConfig(**{field: value}).validate()


def test_keyframe_points_travel_with_the_held_new_keyframe():
    hold = Holdback(hold_new_s=1.0)
    kf = make_keyframe(n=40, keyframe_id=2)
    upd = dataclasses.replace(kf, action=ACTION_UPDATE, map_points=kf.map_points + 0.5)
    hold.offer(kf, 0.0)
    hold.offer(upd, 0.5)
    (sent,) = hold.due(1.0)
    np.testing.assert_array_equal(sent.map_points, upd.map_points)


# --- the engine ----------------------------------------------------------------------------------
def test_the_client_uplink_sends_each_kind_numbered_and_what_it_held_on_flush():
    """New keyframes go whole, an update as a delta when what the keyframe saw is unchanged (else
    whole), a removal by id; numbered 1, 2, ... in one session; events that are no keyframe send
    nothing. With the holdback (client.yaml) a keyframe made and culled within hold_new_s sends
    nothing at all."""
    from coop_slam.uplink.engine import ClientUplink
    from coop_slam.vo.types import (
        EVENT_KEYFRAME_NEW,
        EVENT_KEYFRAME_REMOVE,
        EVENT_KEYFRAME_UPDATE,
        EVENT_WARNING,
        VoEvent,
    )
    from coop_slam.wire.codec import Incomplete, decode
    from coop_slam.wire.messages import KIND_DELTA, KIND_KEYFRAME, KIND_REMOVAL

    rec = make_keyframe(n=40, keyframe_id=7)
    kf = map_keyframe(rec)
    moved = dataclasses.replace(kf, T_map_cam=kf.T_map_cam.copy())
    moved.T_map_cam[:3, 3] += 0.05
    seen_again = dataclasses.replace(moved, depths_m=kf.depths_m * 1.01)
    events = [
        VoEvent(EVENT_KEYFRAME_NEW, 0, 7, kf),
        VoEvent(EVENT_WARNING, 0, message="time went back"),
        VoEvent(EVENT_KEYFRAME_UPDATE, 0, 7, moved),
        VoEvent(EVENT_KEYFRAME_UPDATE, 0, 7, seen_again),
        VoEvent(EVENT_KEYFRAME_REMOVE, 0, 7),
    ]
    held = ClientUplink(3, T_base_cam=np.eye(4))
    held.camera = rec.camera
    step = held.events(events, 4.5)
    assert step.messages == [] and held.held == 0  # made and culled while held: never sent
    assert [n.kind for n in step.notes] == [
        "keyframe",
        "warning",
        "keyframe",
        "keyframe",
        "keyframe",
    ]
    uplink = ClientUplink(
        3,
        UplinkConfig(hold_new_s=0.0, coalesce_updates_s=0.0, budget_kBps=0.0),
        T_base_cam=np.eye(4),
    )
    uplink.camera = rec.camera
    sent = uplink.events(events, 4.5).messages
    assert [m.sequence for m in sent] == [1, 2, 3, 4] and {m.robot_id for m in sent} == {3}
    assert len({m.session for m in sent}) == 1 and uplink.unacked == 4
    assert [m.kind for m in sent] == [KIND_KEYFRAME, KIND_DELTA, KIND_KEYFRAME, KIND_REMOVAL]
    new = decode(sent[0], {3})
    delta = decode(sent[1], {3})
    assert isinstance(delta, Incomplete) and delta.keyframe_id == 7
    completed = delta.complete({7: new}.get)
    np.testing.assert_array_equal(completed.descriptors, new.descriptors)
    np.testing.assert_allclose(completed.T_map_cam, moved.T_map_cam, atol=1e-9)
    assert sent[2].keyframe[0].replaces
    # The server acknowledges the first two: the rest stay to be sent again.
    from coop_slam.wire.messages import KeyframeAck

    uplink.acknowledged(KeyframeAck(robot_id=3, session=sent[0].session, sequence=2))
    assert uplink.unacked == 2
    assert [m.sequence for m in uplink.due_again(now=1e12)] == [3, 4]


def test_a_restarted_client_continues_above_the_servers_keyframes_and_answers_requests_once():
    from coop_slam.uplink.engine import ClientUplink
    from coop_slam.vo.types import EVENT_KEYFRAME_NEW, VoEvent
    from coop_slam.wire.messages import KIND_KEYFRAME, KeyframeRequest

    rec = make_keyframe(n=20, keyframe_id=2)
    kf = map_keyframe(rec)
    uplink = ClientUplink(4, UplinkConfig(hold_new_s=0.0, budget_kBps=0.0), T_base_cam=np.eye(4))
    uplink.camera = rec.camera
    uplink.continue_after(last_keyframe_id=30, last_map_segment=1)
    (msg,) = uplink.events([VoEvent(EVENT_KEYFRAME_NEW, 0, 2, kf)], 1.0).messages
    assert (msg.keyframe_id, msg.map_segment) == (32, 2)
    uplink.planner.forget([32])  # the server refused it (said in its acknowledgement)
    request = KeyframeRequest(robot_id=4, request=1, keyframe_ids=[32, 33])
    answered = uplink.answer(request, {2: kf}.get)  # keyframe 33 (odometry's 3) is gone
    assert [(m.kind, m.keyframe_id) for m in answered] == [(KIND_KEYFRAME, 32)]
    assert uplink.answer(request, {2: kf}.get) == []  # latched: answered already
    assert uplink.keyframes_sent == 1  # keyframe 32, whatever went for it


def test_a_message_that_cannot_be_serialized_takes_no_sequence_and_its_next_update_goes_whole(
    caplog,
):
    """What cannot travel is never numbered (the server would wait at the gap for good, and a
    publisher that fails part-way corrupts its stream): said, left out, and the keyframe's next
    update goes whole; the records that fail the server's own checks likewise."""
    from coop_slam.errors import CoopSlamError
    from coop_slam.uplink.engine import ClientUplink
    from coop_slam.vo.types import EVENT_KEYFRAME_NEW, EVENT_KEYFRAME_UPDATE, VoEvent
    from coop_slam.wire.messages import KIND_DELTA, KIND_KEYFRAME

    class RefusesKeyframe8:
        format_id = "test"

        def dumps(self, msg):
            if msg.keyframe_id == 8:
                raise CoopSlamError("keypoint_step_px 1e300 does not fit a float32")
            return b"ok"

        def loads(self, data):
            raise AssertionError("not read back")

    recs = [make_keyframe(n=30, keyframe_id=k, seed=k) for k in (7, 8, 9)]
    kfs = [map_keyframe(r) for r in recs]
    uplink = ClientUplink(
        3,
        UplinkConfig(hold_new_s=0.0, coalesce_updates_s=0.0, budget_kBps=0.0),
        T_base_cam=np.eye(4),
        serializer=RefusesKeyframe8(),
    )
    uplink.camera = recs[0].camera
    events = [VoEvent(EVENT_KEYFRAME_NEW, 0, kf.keyframe_id, kf) for kf in kfs]
    with caplog.at_level("ERROR", logger="coop_slam.uplink.engine"):
        sent = uplink.events(events, 1.0).messages
    assert [(m.keyframe_id, m.sequence) for m in sent] == [(7, 1), (9, 2)]
    assert "keyframe 8 not sent: keypoint_step_px" in caplog.text
    uplink.serializer = None  # keyframe 8 can travel now
    moved = [dataclasses.replace(kf, T_map_cam=kf.T_map_cam + 0.0) for kf in kfs[:2]]
    for kf in moved:
        kf.T_map_cam[0, 3] += 0.01
    updates = [VoEvent(EVENT_KEYFRAME_UPDATE, 0, kf.keyframe_id, kf) for kf in moved]
    again = uplink.events(updates, 2.0).messages
    assert [(m.keyframe_id, m.kind, m.sequence) for m in again] == [
        (7, KIND_DELTA, 3),
        (8, KIND_KEYFRAME, 4),  # whole: the server never got it
    ]
    bad = dataclasses.replace(kfs[2], stamp_s=5e9)  # beyond a uint32 stamp: cannot travel
    assert uplink.events([VoEvent(EVENT_KEYFRAME_UPDATE, 0, 9, bad)], 3.0).messages == []
    assert uplink.outbox.sequence == 4 and uplink.unacked == 4


def test_a_radio_budget_spreads_what_goes_and_keeps_the_rest_on_the_robot():
    """A token bucket over data time (pull mode): 10 new keyframes a second, their signatures
    ~10 kB each against 25 kB/s -- about one in four goes; the others, with their updates and
    removals, never reach the server, and are counted. Full mode before the server's vocabulary
    came (no signatures to send instead): every keyframe goes whole."""
    from coop_slam.uplink.budget import RadioBudget
    from coop_slam.uplink.engine import ClientUplink
    from coop_slam.vo.types import EVENT_KEYFRAME_NEW, EVENT_KEYFRAME_UPDATE, VoEvent
    from helpers import team_vocabulary

    class Sized:  # stands in for the ROS serializer: every message 10 kB
        def dumps(self, msg):
            return b"x" * 10_000

        def loads(self, payload):
            raise AssertionError("not used")

    class SizedBoth:  # a whole keyframe 10 kB, a signature 1 kB
        def dumps(self, msg):
            return b"x" * (1000 if msg.signature else 10_000)

    config = UplinkConfig(mode="pull", pull_budget_kBps=25.0)
    uplink = ClientUplink(2, config, T_base_cam=np.eye(4), serializer=Sized())
    rec = make_keyframe(n=20, keyframe_id=1)
    uplink.camera = rec.camera
    uplink.vocabulary = team_vocabulary([rec])
    sent_bytes, sent_ids = [], []
    for k in range(1, 101):  # 10 s of data
        kf = map_keyframe(dataclasses.replace(rec, keyframe_id=k))
        events = [VoEvent(EVENT_KEYFRAME_NEW, 0, k, kf)]
        if k > 1:
            events.append(VoEvent(EVENT_KEYFRAME_UPDATE, 0, k - 1, kf))
        t = 0.1 * k
        step = uplink.events(events, t)
        for m in step.messages:
            sent_bytes.append((t, 10_000))
            if not m.delta:
                sent_ids.append(m.keyframe_id)
    total = sum(n for _, n in sent_bytes)
    assert total <= 25_000 * 10  # the budget
    assert 15 <= len(sent_ids) <= 30
    assert uplink.planner.gate.held_back == 100 - len(sent_ids)  # not sent at all
    assert uplink.keyframes_held_back == 100 and uplink.keyframes_sent == 0  # (none whole)
    # spread evenly: no second carries more than the budget and a burst
    per_s = np.bincount([int(t) for t, _ in sent_bytes], weights=[n for _, n in sent_bytes])
    assert per_s.max() <= 50_000
    # full mode without the server's vocabulary: every keyframe whole, not charged (no debt that
    # would silence the robot once the vocabulary came); the budget applies from then on
    unsigned = ClientUplink(
        2, UplinkConfig(hold_new_s=0.0), T_base_cam=np.eye(4), serializer=Sized()
    )
    unsigned.camera = rec.camera
    for k in range(1, 11):
        kf = map_keyframe(dataclasses.replace(rec, keyframe_id=k))
        assert len(unsigned.events([VoEvent(EVENT_KEYFRAME_NEW, 0, k, kf)], 0.1 * k).messages) == 1
    assert unsigned.keyframes_sent == 10 and unsigned.planner.gate.budget.tokens == 0.0
    unsigned.vocabulary = team_vocabulary([rec])
    unsigned.serializer = SizedBoth()
    whole = 0
    for k in range(11, 61):  # 5 s more at 10 keyframes/s against 50 kB/s: 10 kB of signatures
        kf = map_keyframe(dataclasses.replace(rec, keyframe_id=k))
        step = unsigned.events([VoEvent(EVENT_KEYFRAME_NEW, 0, k, kf)], 0.1 * k)
        whole += sum(not m.signature for m in step.messages)
    assert 12 <= whole <= 24  # 40 kB/s of 10 kB keyframes: the budget, from the vocabulary on
    # no budget: everything goes
    free = RadioBudget(0.0)
    assert free.take("whole", 0.0) == 0.0 and not free.limited


def test_a_radio_budget_lets_through_what_the_server_asks_for_and_waits_out_the_debt():
    from coop_slam.uplink.budget import RadioBudget

    budget = RadioBudget(5.0)  # 5 kB/s, a 2.5 kB burst; empty at first
    assert budget.take("signature", 0.0) is None
    charge = budget.take("signature", 0.5)  # the first of a kind: half a second's worth
    assert charge == pytest.approx(2500.0)
    budget.settle("signature", charge, 2000)  # it cost 2 kB: 500 bytes left
    budget.settle("whole", 0.0, 40_000)  # asked for: went anyway, 39.5 kB in debt
    assert budget.capacity == 40_000  # the bucket holds the largest message
    assert budget.take("signature", 1.0) is None
    assert budget.take("signature", 8.5) is None  # 500 bytes after 8 s x 5 kB/s
    assert budget.take("signature", 8.9) == pytest.approx(2000.0)  # what one costs now
    with pytest.raises(ConfigError, match="budget_kBps"):
        UplinkConfig(budget_kBps=-1.0).validate()


def _seeing(rec, keyframe_id, ids, covisible):
    """``rec`` as keyframe ``keyframe_id`` observing map points ``ids`` (on its first keypoints),
    covisible with ``covisible``."""
    ids = np.asarray(ids, np.uint32)
    out = dataclasses.replace(
        rec,
        keyframe_id=keyframe_id,
        map_point_ids=np.concatenate([ids, np.zeros(len(rec.keypoints) - len(ids), np.uint32)]),
        map_points=np.zeros((len(ids), 3), np.float32),
        covisible_ids=np.asarray(covisible, np.uint32),
        covisible_weights=np.full(len(covisible), 10, np.uint16),
    )
    out.validate({rec.robot_id})
    return out


def test_the_budget_sends_signatures_at_once_and_the_newest_views_whole_first():
    """Full mode: every new keyframe's place signature goes at once; the budget then lets
    through whole the candidate that shows most the server has not seen (not the oldest); a
    candidate's update replaces it, its removal goes; after ``defer_s`` a candidate stays a
    signature (the server may still ask for it)."""
    from coop_slam.uplink.budget import BudgetGate, RadioBudget

    gate = BudgetGate(RadioBudget(10.0), "whole", defer_s=2.0)  # 10 kB/s, 5 kB burst
    gate.budget.tokens = 5000.0  # half a second's worth saved up
    base = make_keyframe(n=10)
    kf = {
        1: _seeing(base, 1, [1, 2, 3, 4], []),
        2: _seeing(base, 2, [1, 2, 3, 4], [1]),  # nothing new
        3: _seeing(base, 3, [3, 4, 5, 6], [1]),  # half new
        4: _seeing(base, 4, [7, 8, 9, 10], [1]),  # all new
        5: _seeing(base, 5, [5, 6, 11, 12], [3]),
    }
    never = lambda k: False  # noqa: E731
    (first,) = gate.admit([kf[1]], 0.0, never)
    gate.sent(1, "whole", 5000)  # whole keyframes cost 5 kB: one in 0.5 s
    signatures = gate.admit([kf[2], kf[3], kf[4]], 0.1, never)
    assert [r.keyframe_id for r in signatures] == [4, 3, 2] and gate.signed == {2, 3, 4}
    for r in signatures:
        gate.sent(r.keyframe_id, "signature", 0)  # (free here, to follow the whole ones)
    assert gate.held_back == 0  # (the server has heard of every one)
    assert [gate.novelty(kf[k]) for k in (2, 3, 4)] == [0.0, 0.5, 1.0]
    (upgrade,) = gate.admit([], 0.6, never)
    assert upgrade.keyframe_id == 4 and gate.signed == {2, 3}
    gate.sent(4, "whole", 5000)
    moved = _moved(kf[3], ACTION_UPDATE, 0.05)
    assert gate.admit([moved], 0.7, never) == []  # keyframe 3 waits, now as moved
    (third,) = gate.admit([], 1.1, never)
    assert third.keyframe_id == 3 and third.action == ACTION_NEW
    assert third.T_map_cam[0, 3] == moved.T_map_cam[0, 3]
    gate.sent(3, "whole", 5000)
    gone = dataclasses.replace(kf[2], action=ACTION_REMOVE)
    assert gate.admit([gone], 1.2, never) == [gone]  # the server has its signature
    assert gate.signed == set()
    # keyframe 5 sees two of keyframe 3's points: half new
    (sig,) = gate.admit([kf[5]], 1.3, never)
    assert sig.keyframe_id == 5 and gate.novelty(kf[5]) == 0.5
    gate.budget.tokens = -100_000  # a large answer went meanwhile
    assert gate.admit([], 3.4, never) == [] and gate.signed == {5}
    gate.budget.tokens = gate.budget.capacity
    assert gate.admit([], 3.5, never) == []  # waited beyond defer_s: it stays a signature
    assert gate.admit([_moved(kf[5], ACTION_UPDATE, 0.1)], 3.6, never) == []
    gate.answered(kf[5])  # the server asked for it: its updates go from now on
    assert gate.held_back == 0 and gate.signed == set()


def test_in_pull_mode_the_newest_views_signatures_go_first_and_the_rest_at_the_end():
    """Pull mode: a candidate is its signature; the most novel goes first, one that waited
    ``defer_s`` stays on the robot (the server never hears of it, nor of its removal); when the
    camera stops, what still waits goes (a few kB)."""
    from coop_slam.uplink.budget import BudgetGate, RadioBudget

    base = make_keyframe(n=10)
    kf = {
        1: _seeing(base, 1, [1, 2, 3, 4], []),
        2: _seeing(base, 2, [1, 2, 3, 4], [1]),
        3: _seeing(base, 3, [1, 2, 5, 6], [1]),
        4: _seeing(base, 4, [1, 2, 7, 8], [1]),
    }
    never = lambda k: False  # noqa: E731
    pull = BudgetGate(RadioBudget(1.0), "signature", defer_s=2.0)  # 1 kB/s, 500 B burst
    pull.budget.tokens = 500.0
    (first,) = pull.admit([kf[1]], 0.0, never)
    pull.sent(1, "signature", 500)
    assert pull.admit([kf[2], kf[3]], 0.1, never) == [] and pull.held_back == 2
    assert [r.keyframe_id for r in pull.admit([], 0.6, never)] == [3]  # half new, before 2
    pull.sent(3, "signature", 2500)  # 2 kB over: no more until 2.6 s
    assert pull.admit([], 2.2, never) == [] and pull.held_back == 1  # 2 stayed on the robot
    assert pull.admit([dataclasses.replace(kf[2], action=ACTION_REMOVE)], 2.3, never) == []
    pull.budget.tokens = -10_000
    assert pull.admit([kf[4]], 2.4, never) == []
    assert [r.keyframe_id for r in pull.admit([], 2.5, never, flush=True)] == [4]
    assert pull.signed == set() and pull.held_back == 1


def test_in_pull_mode_the_budget_decides_which_signatures_go():
    """With the server's vocabulary, full mode sends what the budget holds back as signatures;
    pull mode's keyframes are signatures already, and the budget holds some back for good."""
    from coop_slam.uplink.engine import ClientUplink

    for mode, signs in (("full", True), ("pull", False)):
        uplink = ClientUplink(2, UplinkConfig(mode=mode), T_base_cam=np.eye(4))
        uplink.vocabulary = object()  # (what signatures name: the server's words)
        assert uplink.planner.gate.sign is signs
        uplink.vocabulary = None
        assert uplink.planner.gate.sign is False


def test_the_uplink_counts_keyframes_sent_whole_and_held_back():
    """Full mode with a small budget and the server's vocabulary: every new keyframe's signature
    goes; those that never went whole are held back; one the server then asks for counts as
    sent whole."""
    from coop_slam.uplink.engine import ClientUplink
    from coop_slam.vo.types import EVENT_KEYFRAME_NEW, VoEvent
    from helpers import team_vocabulary

    class Sized:  # stands in for the ROS serializer: a whole keyframe 10 kB, a signature 1 kB
        def dumps(self, msg):
            return b"x" * (1000 if msg.signature else 10_000)

        def loads(self, payload):
            raise AssertionError("not used")

    recs = [make_keyframe(n=40, robot_id=2, keyframe_id=k, seed=k) for k in range(1, 11)]
    config = UplinkConfig(hold_new_s=0.0, budget_kBps=25.0)
    uplink = ClientUplink(2, config, T_base_cam=np.eye(4), serializer=Sized())
    uplink.vocabulary = team_vocabulary(recs)
    uplink.camera = recs[0].camera
    whole = []
    for i, rec in enumerate(recs):
        step = uplink.events(
            [VoEvent(EVENT_KEYFRAME_NEW, 0, rec.keyframe_id, map_keyframe(rec))], 0.2 * i
        )
        whole += [m.keyframe_id for m in step.messages if not m.signature]
    assert 1 <= uplink.keyframes_sent == len(set(whole)) < 10
    assert uplink.keyframes_held_back == 10 - uplink.keyframes_sent
    held = next(r.keyframe_id for r in recs if r.keyframe_id not in whole)
    request = KeyframeRequest(robot_id=2, keyframe_ids=[held], request=1)
    uplink.answer(request, lambda k: map_keyframe(recs[k - 1]))
    assert uplink.keyframes_sent == len(set(whole)) + 1
    assert uplink.keyframes_held_back == 9 - len(set(whole))
    # Asked for one that went whole meanwhile (its request crossed it): it is not sent again
    again = KeyframeRequest(robot_id=2, keyframe_ids=[whole[0], held], request=2)
    assert uplink.answer(again, lambda k: map_keyframe(recs[k - 1])) == []


def test_an_update_the_budget_cannot_afford_goes_when_it_can():
    """An update of a keyframe the server holds waits for the budget (not for the keyframe's next
    update, which may never come): a newer one replaces it; when the camera stops, it goes."""
    from coop_slam.uplink.budget import BudgetGate, RadioBudget

    gate = BudgetGate(RadioBudget(10.0), "whole", defer_s=2.0)  # 10 kB/s
    held = lambda k: True  # noqa: E731  (the server holds keyframes 1 and 2 whole)
    kf1, kf2 = (make_keyframe(n=10, keyframe_id=k, seed=k) for k in (1, 2))
    gate.budget.tokens = -10_000  # a whole keyframe went: 1 s of debt
    first = _moved(kf1, ACTION_UPDATE, 0.01)
    assert gate.admit([first, _moved(kf2, ACTION_UPDATE, 0.01)], 0.0, held) == []
    newer = _moved(kf1, ACTION_UPDATE, 0.02)
    assert gate.admit([newer], 0.5, held) == []  # replaces the first, keeps its place
    (went,) = gate.admit([], 1.6, held)  # 6 kB: one delta (cost: half a second's worth)
    assert went is newer
    gate.sent(1, "delta", 1000)
    assert [r.keyframe_id for r in gate.admit([], 1.6, held, flush=True)] == [2]


@pytest.mark.parametrize(
    "config, carried",
    [
        (UplinkConfig(hold_new_s=0.0, budget_kBps=0.0), True),
        (UplinkConfig(hold_new_s=0.0, budget_kBps=0.0, depth_images=False), False),
        (UplinkConfig(mode="pull", pull_budget_kBps=0.0), False),
        (UplinkConfig(mode="pull", pull_budget_kBps=0.0, pull_depth_images=True), True),
    ],
)
def test_a_keyframes_depth_image_goes_whole_in_full_mode_and_in_pull_mode_only_if_asked(
    config, carried
):
    from coop_slam.uplink.engine import ClientUplink
    from coop_slam.vo.types import EVENT_KEYFRAME_NEW, VoEvent
    from helpers import depth_blob, team_vocabulary

    rec = make_keyframe(n=20, keyframe_id=2)
    kf = dataclasses.replace(map_keyframe(rec), depth_image=depth_blob().tobytes())
    uplink = ClientUplink(4, config, T_base_cam=np.eye(4), vocabulary=team_vocabulary([rec]))
    uplink.camera = rec.camera
    (note,) = uplink.events([VoEvent(EVENT_KEYFRAME_NEW, 0, 2, kf)], 1.0).notes
    assert (len(note.record.depth_image) > 0) == carried
    answered = uplink.answer(KeyframeRequest(robot_id=4, request=1, keyframe_ids=[2]), {2: kf}.get)
    assert all(bool(m.keyframe[0].depth_image) == carried for m in answered if m.keyframe)


def test_with_delta_updates_off_the_uplink_still_knows_what_the_server_holds():
    """Every update goes whole; the keyframe stays one the server holds (its corrections apply,
    the budget sends its updates as updates)."""
    planner = Planner(UplinkConfig(hold_new_s=0.0, coalesce_updates_s=0.0, delta_updates=False))
    rec = make_keyframe(n=20, keyframe_id=4)
    how = planner.prepare(rec)
    assert not how.delta and planner.holds(4)
    how = planner.prepare(_moved(rec, ACTION_UPDATE, 0.01))
    assert not how.delta and planner.holds(4)
    planner.prepare(_moved(rec, ACTION_REMOVE, 0.0))
    assert not planner.holds(4)


def test_a_new_keyframe_that_finds_no_room_counts_as_held_back():
    """The outbox is full (the server does not acknowledge): a new keyframe's message is
    refused; it is neither sent nor lost from the counts, and goes whole with its next update once
    there is room."""
    from coop_slam.uplink.engine import ClientUplink
    from coop_slam.vo.types import EVENT_KEYFRAME_NEW, EVENT_KEYFRAME_UPDATE, VoEvent
    from coop_slam.wire.messages import KeyframeAck

    config = UplinkConfig(hold_new_s=0.0, coalesce_updates_s=0.0, budget_kBps=0.0)
    uplink = ClientUplink(2, config, T_base_cam=np.eye(4))
    uplink.outbox.max_unacked = 2
    recs = [make_keyframe(n=20, robot_id=2, keyframe_id=k, seed=k) for k in (1, 2, 3)]
    uplink.camera = recs[0].camera
    events = [VoEvent(EVENT_KEYFRAME_NEW, 0, r.keyframe_id, map_keyframe(r)) for r in recs]
    sent = uplink.events(events, 1.0).messages
    assert [m.keyframe_id for m in sent] == [1, 2] and uplink.refused_full == 1
    assert uplink.keyframes_sent == 2 and uplink.keyframes_held_back == 1
    uplink.acknowledged(KeyframeAck(robot_id=2, session=sent[-1].session, sequence=2))
    update = VoEvent(
        EVENT_KEYFRAME_UPDATE, 0, 3, map_keyframe(_moved(recs[2], ACTION_UPDATE, 0.01))
    )
    (again,) = uplink.events([update], 2.0).messages
    assert again.keyframe_id == 3 and not again.delta
    assert uplink.keyframes_sent == 3 and uplink.keyframes_held_back == 0  # whole: new to it
