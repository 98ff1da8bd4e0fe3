"""When a client's keyframe records go (vo.outbox.Holdback through Uplink): new keyframes wait and
go as local BA left them, culled ones never, updates of sent keyframes go coalesced."""

import dataclasses

import numpy as np
import pytest

from coop_slam.config import ConfigError
from coop_slam.keyframe_record import ACTION_NEW, ACTION_REMOVE, ACTION_UPDATE
from coop_slam.vo.outbox import Holdback, Uplink, UplinkConfig
from helpers import make_keyframe


def _moved(rec, action, dx):
    out = dataclasses.replace(rec, action=action, T_map_cam=rec.T_map_cam.copy())
    out.T_map_cam[0, 3] += dx
    return out


def _what(records):
    return [(r.keyframe_id, r.action, round(float(r.T_map_cam[0, 3]), 3)) for r in records]


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
    uplink = Uplink(UplinkConfig(hold_new_s=0.5, coalesce_updates_s=0.5))
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
    pull = Uplink(UplinkConfig(mode="pull"))
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
