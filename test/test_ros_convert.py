"""ROS message conversion and validation (no master needed)."""

import dataclasses
import functools

import numpy as np
import pytest

from helpers import make_keyframe

msg_mod = pytest.importorskip(
    "coop_slam.msg", reason="generated messages need the catkin workspace"
)
from coop_slam.keyframe_record import MOVE_STEP_M, encode_map_point_ids  # noqa: E402
from coop_slam.ros.convert import (  # noqa: E402
    MessageError,
    depth_from_msg,
    image_from_msg,
    image_to_msg,
    keyframe_from_msg,
    keyframe_to_msg,
    needs_stored,
    pose_from_msg,
    pose_to_msg,
    transform_from_msg,
    transform_to_msg,
    unpacked,
)
from coop_slam.ros.validation import RejectCounter  # noqa: E402


def _wire(msg):
    """Serialize and deserialize, as a message crossing a topic."""
    import io

    buf = io.BytesIO()
    msg.serialize(buf)
    out = type(msg)()
    out.deserialize(buf.getvalue())
    return out


def test_keyframe_round_trip_over_the_wire():
    kf = make_keyframe(n=40, robot_id=2, keyframe_id=9)
    kf.T_map_cam[:3, 3] = [1.0, -2.0, 0.5]
    msg = _wire(keyframe_to_msg(kf, "robot_2/map"))
    back = keyframe_from_msg(msg, known_robots={1, 2})
    assert back.robot_id == 2 and back.keyframe_id == 9
    assert np.array_equal(back.descriptors, kf.descriptors)
    # Keypoints in 1/64 px steps (a 640x480 image), depths as half floats: 6 bytes a keypoint
    # less than float32s, within half a step and 2^-11 of the depth; map point ids as varints
    # (a byte each here: ids 1, 3, 5, ... on every other keypoint, 4 as uint32).
    assert msg.keypoint_step_px == 1 / 64 and not len(msg.keypoints) and not len(msg.depths_m)
    np.testing.assert_allclose(back.keypoints[:, :2], kf.keypoints[:, :2], rtol=0, atol=1 / 128)
    np.testing.assert_allclose(back.depths_m, kf.depths_m, rtol=2**-11, atol=0)
    plain = _wire(keyframe_to_msg(kf, "robot_2/map", compact=False))
    assert _size(plain) - _size(msg) >= 6 * 40 + 3 * 40  # (and the map points near their depth)
    exact = keyframe_from_msg(plain, known_robots={1, 2})
    assert np.array_equal(exact.keypoints[:, :2], kf.keypoints[:, :2])
    assert np.array_equal(exact.depths_m, kf.depths_m)
    # What does not fit goes as float32: a depth beyond the half float's range.
    far = dataclasses.replace(kf, depths_m=np.full(40, 70000.0, np.float32))
    assert not len(keyframe_to_msg(far, "robot_2/map").depths_f16)
    tiny = dataclasses.replace(kf, depths_m=np.full(40, 1e-6, np.float32))  # loses precision
    assert not len(keyframe_to_msg(tiny, "robot_2/map").depths_f16)
    # Their size and angle do not travel (the server does not use them).
    assert np.all(back.keypoints[:, 2] == 0) and np.all(back.keypoints[:, 3] == -1)
    assert np.array_equal(back.map_point_ids, kf.map_point_ids)
    assert np.allclose(back.map_points, kf.map_points)
    assert np.allclose(back.T_map_cam, kf.T_map_cam, atol=1e-9)
    assert back.stamp_s == pytest.approx(kf.stamp_s)


def test_map_points_travel_as_offsets_from_their_keypoints_depths():
    """A full message carries an observed keypoint's map point as a half-float offset from the
    keypoint at its depth (as the server decodes both), the others' as float32; an offset beyond
    a metre sends every point as float32."""
    from coop_slam.geometry import transform_points

    kf = make_keyframe(n=60, robot_id=2, keyframe_id=9)
    kf.T_map_cam[:3, 3] = [3.0, -1.0, 0.5]
    kf.depths_m[::5] = 0.0  # some keypoints without a depth
    rng = np.random.default_rng(1)
    at_depth = transform_points(kf.T_map_cam, kf.points_cam())
    per_kp = at_depth + rng.normal(0, 0.01, at_depth.shape)  # local BA moved them by ~1 cm
    no_depth = kf.depths_m == 0
    per_kp[no_depth] = rng.uniform(-5, 5, (int(no_depth.sum()), 3))
    kf.map_points = per_kp[kf.map_point_ids != 0].astype(np.float32)
    msg = _wire(keyframe_to_msg(kf, "robot_2/map"))
    seen = kf.map_point_ids != 0
    assert len(msg.map_point_offsets_f16) == 6 * int((seen & ~no_depth).sum())
    assert len(msg.map_points) == 3 * int((seen & no_depth).sum())
    back = keyframe_from_msg(msg, {1, 2})
    err = np.abs(back.map_points - kf.map_points)
    assert err.max() < 0.05 * 2**-11 + 1e-5  # the offsets' half-float rounding (and float32)
    np.testing.assert_array_equal(
        back.map_points_per_keypoint()[seen & no_depth],
        kf.map_points_per_keypoint()[seen & no_depth],
    )
    plain = _wire(keyframe_to_msg(kf, "robot_2/map", compact=False))
    assert not len(plain.map_point_offsets_f16)
    # A point a metre and more from its keypoint's depth goes as float32, the others as before.
    far = kf.map_points.copy()
    far[np.flatnonzero(~no_depth[seen])[0]] += 1.5
    msg = _wire(keyframe_to_msg(dataclasses.replace(kf, map_points=far), "robot_2/map"))
    assert len(msg.map_points) == 3 * (int((seen & no_depth).sum()) + 1)
    back = keyframe_from_msg(msg, {1, 2})
    assert np.abs(back.map_points - far).max() < 0.05 * 2**-11 + 1e-5
    # Malformed offsets
    good = _wire(keyframe_to_msg(kf, "robot_2/map"))
    for field, value, match in (
        ("map_point_offsets_f16", good.map_point_offsets_f16[:-6], "bytes for 24 observed"),
        ("map_point_offsets_f16", np.full(72, np.inf, "<f2").tobytes(), "holds inf"),
        ("map_point_offsets_f16", np.full(72, np.nan, "<f2").tobytes(), "points for 30 observed"),
        ("map_points", list(good.map_points)[:-3], "points for 6 observed keypoints without"),
    ):
        bad = _wire(keyframe_to_msg(kf, "robot_2/map"))
        setattr(bad, field, value)
        with pytest.raises(MessageError, match=match):
            keyframe_from_msg(bad, {1, 2})


def _size(msg) -> int:
    import io

    buf = io.BytesIO()
    msg.serialize(buf)
    return len(buf.getvalue())


def test_a_delta_update_rebuilds_the_same_keyframe_as_a_full_one():
    import dataclasses

    from coop_slam.keyframe_record import ACTION_UPDATE

    sent = make_keyframe(n=60, robot_id=2, keyframe_id=9)
    # (float32 map points: the comparison below is exact)
    new = keyframe_from_msg(_wire(keyframe_to_msg(sent, "robot_2/map", compact=False)), {1, 2})
    upd = dataclasses.replace(sent, action=ACTION_UPDATE, T_map_cam=sent.T_map_cam.copy())
    upd.T_map_cam[:3, 3] += [0.1, 0.0, -0.05]
    upd.map_points = upd.map_points + np.float32(0.01)
    assert upd.static_digest() == sent.static_digest()
    full_msg, delta_msg = (
        _wire(keyframe_to_msg(upd, "robot_2/map", d, compact=False)) for d in (False, True)
    )
    assert _size(delta_msg) < _size(full_msg) / 3
    full = keyframe_from_msg(full_msg, {1, 2})
    delta = keyframe_from_msg(delta_msg, {1, 2}, stored=lambda _kf: new)
    for name in ("T_map_cam", "keypoints", "octaves", "descriptors", "depths_m", "map_points"):
        np.testing.assert_array_equal(getattr(delta, name), getattr(full, name))
    assert delta.static_digest() == full.static_digest() and delta.action == ACTION_UPDATE
    with pytest.raises(MessageError, match="does not hold"):
        keyframe_from_msg(delta_msg, {1, 2})
    delta_msg.action = delta_msg.ACTION_NEW
    with pytest.raises(MessageError, match="only an update"):
        keyframe_from_msg(delta_msg, {1, 2}, stored=lambda _kf: new)


def test_delta_updates_carry_only_the_observations_that_changed():
    """A client's updates through Uplink, completed by the server from what it holds, give
    the keyframe as a full message would -- within point_move_m for points that moved less."""
    import dataclasses

    from coop_slam.keyframe_record import ACTION_NEW, ACTION_UPDATE
    from coop_slam.vo.outbox import Uplink, UplinkConfig

    move_m = 0.002
    deltas = Uplink(UplinkConfig(point_move_m=move_m))
    rng = np.random.default_rng(3)
    kf = make_keyframe(n=80, robot_id=2, keyframe_id=9)
    out = deltas.prepare(kf)
    assert not out.delta and out.patched is None
    held = keyframe_from_msg(_wire(keyframe_to_msg(kf, "robot_2/map")), {1, 2})
    sizes = []
    for step in range(4):
        upd = dataclasses.replace(
            kf, action=ACTION_UPDATE, T_map_cam=kf.T_map_cam.copy(), map_point_ids=kf.map_point_ids
        )
        upd.T_map_cam[:3, 3] += 0.01 * (step + 1)
        # Local BA: a few points move a lot, all of them a little (below the threshold).
        per_kp = kf.map_points_per_keypoint()
        per_kp += rng.uniform(-0.4, 0.4, per_kp.shape) * move_m / np.sqrt(3)
        per_kp[rng.choice(len(per_kp), 10, replace=False)] += 0.05
        ids = kf.map_point_ids.copy()
        ids[5 * step + 1] = 1000 + step  # a keypoint now observes a map point (fused)
        ids[5 * step + 2] = 0  # another lost its map point (culled)
        per_kp[5 * step + 1] = [0.5, 0.5, 2.0]
        upd.map_point_ids = ids
        upd.map_points = per_kp[ids != 0].astype(np.float32)
        out = deltas.prepare(upd)
        # The reassigned keypoints travel as a patch, the moved points as moves.
        reassigned = np.flatnonzero(ids != kf.map_point_ids)
        assert out.delta and np.array_equal(out.patched, reassigned)
        assert 0 < len(out.moves[0]) <= 10
        msg = _wire(keyframe_to_msg(upd, "robot_2/map", out.delta, out.patched, moves=out.moves))
        opened = unpacked(msg)
        assert len(opened.moves_q) == 3 * len(opened.moved) and not len(msg.moves_f16)
        sizes.append((_size(msg), _size(_wire(keyframe_to_msg(upd, "robot_2/map", True)))))
        held = keyframe_from_msg(msg, {1, 2}, stored=lambda _kf, base=held: base)
        np.testing.assert_array_equal(held.map_point_ids, upd.map_point_ids)
        np.testing.assert_allclose(held.T_map_cam, upd.T_map_cam, atol=1e-6)
        err = np.linalg.norm(held.map_points - upd.map_points, axis=1)
        assert err.max() <= move_m + 1e-6
        moved = held.map_points_per_keypoint()[out.moves[0]] - per_kp[out.moves[0]]
        assert np.abs(moved).max() <= MOVE_STEP_M / 2 + 1e-6
        kf = upd
    assert all(patch < whole / 2 for patch, whole in sizes)
    # A later map segment's keyframe: the server holds it under the segment's map id.
    again = keyframe_from_msg(msg, {1, 2}, stored=lambda _kf: dataclasses.replace(held, robot_id=3))
    np.testing.assert_array_equal(again.map_point_ids, held.map_point_ids)
    # What the keyframe saw changed (a client re-extracted it): the update goes in full.
    redone = dataclasses.replace(kf, descriptors=kf.descriptors[::-1].copy())
    assert not deltas.prepare(redone).delta
    assert not deltas.prepare(dataclasses.replace(kf, action=ACTION_NEW)).delta


def _sees(kf, ids_from, keypoints, bits=4):
    """``kf`` with its ``keypoints`` now observing the map points of keyframe ``ids_from``'s
    same keypoints (tracked from it), at the points' positions there moved by 5 cm, their
    descriptors there with ``bits`` bits flipped."""
    import dataclasses

    desc = kf.descriptors.copy()
    desc[keypoints] = ids_from.descriptors[keypoints]
    desc[keypoints, : bits // 8] ^= 0xFF
    desc[keypoints, bits // 8] ^= (1 << (bits % 8)) - 1
    ids = kf.map_point_ids.copy()
    ids[keypoints] = ids_from.map_point_ids[keypoints]
    per_kp = kf.map_points_per_keypoint()
    per_kp[keypoints] = ids_from.map_points_per_keypoint()[keypoints] + 0.05
    return dataclasses.replace(
        kf, descriptors=desc, map_point_ids=ids, map_points=per_kp[ids != 0].astype(np.float32)
    )


def test_a_map_points_descriptor_travels_once():
    """A new keyframe observing map points a keyframe the server holds observes goes without
    their descriptors; the server takes them there and gets the keyframe otherwise as sent. A
    removed keyframe, another map segment's, or the keyframe itself is never referred to."""
    import dataclasses

    from coop_slam.keyframe_record import ACTION_REMOVE, ACTION_UPDATE
    from coop_slam.vo.outbox import Uplink, UplinkConfig

    uplink = Uplink()
    server: dict[int, object] = {}  # keyframe id -> as the server holds it

    def send(rec):
        out = uplink.prepare(rec)
        msg = _wire(keyframe_to_msg(rec, "robot_2/map", out.delta, out.patched, out.refs))
        got = keyframe_from_msg(msg, {1, 2}, stored=server.get)
        server[rec.keyframe_id] = got
        return out, msg, got

    a = make_keyframe(n=80, robot_id=2, keyframe_id=1)  # map points 1, 3, 5, ... at 0, 2, 4, ...
    b = make_keyframe(n=80, robot_id=2, keyframe_id=2, seed=1)
    b.map_point_ids = np.where(b.map_point_ids != 0, b.map_point_ids + 1000, 0).astype(np.uint32)
    b = _sees(b, a, np.arange(0, 30, 2))  # tracked 15 of a's points
    b = _sees(b, a, np.array([31]))  # a keypoint with no map point in a: nothing to take
    b = _sees(b, a, np.arange(32, 40, 2), bits=40)  # the view changed them too much: they travel
    out_a, msg_a, _ = send(a)
    assert out_a.refs is None  # the server holds nothing yet
    out_b, msg_b, got_b = send(b)
    ref_kfs, refs = out_b.refs
    assert list(ref_kfs) == [1] and np.array_equal(np.flatnonzero(refs), np.arange(0, 30, 2))
    assert len(msg_b.descriptors) == 32 * (80 - 15)
    # 15 descriptors less, a byte per keypoint and a keyframe id more (before packing)
    unpacked_b = keyframe_to_msg(b, "robot_2/map", refs=out_b.refs, compact=False)
    plain_b = keyframe_to_msg(b, "robot_2/map", compact=False)
    assert _size(_wire(unpacked_b)) == _size(_wire(plain_b)) - 15 * 32 + 80 + 4
    # The server's b: a's descriptors for the tracked keypoints, b's own for the others; its
    # observations are b's (the points' positions travel: they moved).
    np.testing.assert_array_equal(got_b.descriptors[refs != 0], a.descriptors[refs != 0])
    np.testing.assert_array_equal(got_b.descriptors[refs == 0], b.descriptors[refs == 0])
    for name in ("octaves", "map_point_ids", "map_points", "T_map_cam"):
        np.testing.assert_allclose(getattr(got_b, name), getattr(b, name), atol=1e-6)
    np.testing.assert_allclose(got_b.keypoints[:, :2], b.keypoints[:, :2], atol=1 / 128)
    # c tracks a's points and b's own: it takes from both, b (covisible, heavier) first.
    c = make_keyframe(n=80, robot_id=2, keyframe_id=3, seed=2)
    c.map_point_ids = np.where(c.map_point_ids != 0, c.map_point_ids + 2000, 0).astype(np.uint32)
    c = _sees(_sees(c, a, np.arange(40, 60, 2)), b, np.arange(0, 20, 2))
    c.covisible_ids, c.covisible_weights = np.array([1, 2], np.uint32), np.array([5, 9], np.uint16)
    out_c, _, got_c = send(c)
    assert list(out_c.refs[0]) == [2, 1]
    np.testing.assert_array_equal(got_c.descriptors[:20:2], a.descriptors[:20:2])  # b took a's
    np.testing.assert_array_equal(got_c.descriptors[40:60:2], a.descriptors[40:60:2])
    # a removed: d, tracking a's points, carries their descriptors; so does a keyframe of a
    # new map segment tracking b's, and c sent in full again (what it saw changed) refers to b
    # (which holds c's first ten points) but not to itself.
    send(dataclasses.replace(a, action=ACTION_REMOVE))
    d = _sees(make_keyframe(n=80, robot_id=2, keyframe_id=4, seed=3), a, np.arange(60, 70, 2))
    per_kp = d.map_points_per_keypoint()
    d.map_point_ids = np.where(np.arange(80) < 60, 0, d.map_point_ids).astype(np.uint32)
    d.map_points = per_kp[d.map_point_ids != 0].astype(np.float32)
    assert send(d)[0].refs is None
    e = dataclasses.replace(_sees(make_keyframe(n=80, robot_id=2, keyframe_id=5), b, [0]))
    assert uplink.prepare(dataclasses.replace(e, map_segment=1)).refs is None
    redone = dataclasses.replace(c, action=ACTION_UPDATE, descriptors=c.descriptors.copy())
    redone.descriptors[:, -1] ^= 1
    out = uplink.prepare(redone)
    assert not out.delta and list(out.refs[0]) == [2]
    # The server no longer holds what a message refers to: refused, naming it.
    del server[2]
    msg = _wire(keyframe_to_msg(redone, "robot_2/map", False, None, out.refs))
    with pytest.raises(MessageError, match="refer to keyframe 2, which the server does not hold"):
        keyframe_from_msg(msg, {1, 2}, stored=server.get)
    with pytest.raises(MessageError, match="keyframes the server holds are not given"):
        keyframe_from_msg(msg, {1, 2})
    # Switched off, every descriptor travels.
    plain = Uplink(UplinkConfig(share_descriptors=False))
    plain.prepare(a)
    assert plain.prepare(b).refs is None
    # Any difference allowed, the ones the view changed too are taken from a.
    anyway = Uplink(UplinkConfig(share_max_bits=256))
    anyway.prepare(a)
    tracked = np.r_[np.arange(0, 30, 2), np.arange(32, 40, 2)]
    assert np.array_equal(np.flatnonzero(anyway.prepare(b).refs[1]), tracked)


def test_malformed_descriptor_refs_are_rejected():
    from coop_slam.keyframe_record import observation_index

    np.testing.assert_array_equal(
        observation_index(np.array([0, 7, 3, 7]), np.array([7, 3, 0, 9])), [1, 2, -1, -1]
    )
    held = make_keyframe(n=20, robot_id=1, keyframe_id=4)
    kf = make_keyframe(n=20, robot_id=1, keyframe_id=5, seed=1)  # map points 1, 3, ... as held
    refs = np.where(kf.map_point_ids != 0, 1, 0).astype(np.uint8)
    stored = {4: held}.get
    ok = _wire(unpacked(keyframe_to_msg(kf, "robot_1/map", refs=(np.array([4]), refs))))
    np.testing.assert_array_equal(
        keyframe_from_msg(ok, {1}, stored=stored).descriptors[refs != 0], held.descriptors[::2]
    )
    for change, match in (
        (dict(descriptor_refs=bytes(refs[:-1])), "descriptor_refs has 19 entries"),
        (dict(descriptor_refs=bytes(refs * 2)), "names reference 2 of 1"),
        (dict(descriptors=ok.descriptors[:-32]), "hold 9 descriptors for 10 keypoints"),
        (dict(map_point_id_codes=encode_map_point_ids(np.where(refs, 99, 0))), "map point 99 in"),
        (dict(ref_keyframes=[6]), "keyframe 6, which the server does not hold"),
        (dict(ref_keyframes=[4] * 256), "ref_keyframes lists 256 keyframes, above the limit"),
    ):
        msg = _wire(unpacked(keyframe_to_msg(kf, "robot_1/map", refs=(np.array([4]), refs))))
        for k, v in change.items():
            setattr(msg, k, v)
        with pytest.raises(MessageError, match=match):
            keyframe_from_msg(msg, {1}, stored=stored)
    bad = refs.copy()
    bad[1] = 1  # keypoint 1 observes no map point
    msg = _wire(keyframe_to_msg(kf, "robot_1/map", refs=(np.array([4]), bad)))
    with pytest.raises(MessageError, match="observes no map point"):
        keyframe_from_msg(msg, {1}, stored=stored)


def test_malformed_patches_are_rejected():
    sent = make_keyframe(n=20, robot_id=1, keyframe_id=4)
    held = keyframe_from_msg(_wire(keyframe_to_msg(sent, "robot_1/map")), {1})
    msg = _wire(keyframe_to_msg(sent, "robot_1/map", compact=False))
    msg.action, msg.delta = msg.ACTION_UPDATE, True
    msg.keypoints, msg.octaves, msg.descriptors, msg.depths_m = [], b"", b"", []
    msg.patched, msg.map_point_ids, msg.map_points = [25], [3], [0.0, 0.0, 1.0]
    with pytest.raises(MessageError, match="names keypoint 25 of a keyframe with 20"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    msg.patched, msg.map_point_ids, msg.map_points = [1, 1], [3, 4], [0.0] * 6
    with pytest.raises(MessageError, match="names a keypoint twice"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    msg.patched, msg.map_point_ids, msg.map_points = [1, 2], [3, 0], [0.0] * 6
    with pytest.raises(MessageError, match="gives 2 map points for 1 observed"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    msg.patched, msg.map_point_ids = [1, 2, 3], [3, 0]
    with pytest.raises(MessageError, match="patched lists 3 keypoints"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    # Moves of map points (keypoint 0 observes map point 1, keypoint 1 none)
    msg.patched, msg.map_point_ids, msg.map_points = [2], [0], []
    for moved, n, match in (
        ([0], 2, "moves_q holds 2 values for 1 moved"),
        ([25], 3, "moved names keypoint 25 of a keyframe with 20"),
        ([0, 0], 6, "moved names a keypoint twice"),
        ([1], 3, "moved names a keypoint that observes no map point"),
        ([2], 3, "both patched and moved"),
    ):
        msg.moved, msg.moves_q = moved, [0] * n
        with pytest.raises(MessageError, match=match):
            keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    msg.moved, msg.moves_q = [0], [2048, -1, 0]
    got = keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    np.testing.assert_allclose(
        got.map_points[0], held.map_points[0] + [0.5, -MOVE_STEP_M, 0], atol=1e-6
    )
    msg.moves_f16 = np.array([0.5, 0, 0], "<f2").tobytes()
    with pytest.raises(MessageError, match="moves_q and moves_f16 are both given"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    # Recorded runs' moves: half floats
    msg.moves_q = []
    got = keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    np.testing.assert_allclose(got.map_points[0], held.map_points[0] + [0.5, 0, 0], atol=1e-6)
    msg.moves_f16 = np.full(3, np.inf, "<f2").tobytes()
    with pytest.raises(MessageError, match="NaN or inf"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    msg.moves_f16 = bytes(5)
    with pytest.raises(MessageError, match="moves_f16 holds 5 bytes for 1 moved"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)
    msg.moves_f16 = np.array([0.5, 0, 0], "<f2").tobytes()
    msg.delta, msg.patched, msg.map_point_ids = False, [], list(sent.map_point_ids)
    with pytest.raises(MessageError, match="only a delta update with a patch moves"):
        keyframe_from_msg(msg, {1}, stored=lambda _kf: held)


def _remove_with_200k_keypoints(msg):
    msg.action = msg.ACTION_REMOVE
    msg.keypoints = [1.0] * (4 * 200_000)


@pytest.mark.parametrize(
    "mutate, match, compact",
    [
        (lambda m: setattr(m, "descriptors", m.descriptors[:-5]), "multiple of 32", False),
        (lambda m: setattr(m, "robot_id", 9), "unknown", False),
        (lambda m: setattr(m.pose.orientation, "w", float("nan")), "unit quaternion", False),
        (lambda m: setattr(m.pose.position, "x", float("inf")), "NaN or inf", False),
        (lambda m: setattr(m, "keypoints", list(m.keypoints)[:-1]), "2 per keypoint .u, v.", False),
        (lambda m: setattr(m, "depths_m", list(m.depths_m)[:-1]), "depths_m", False),
        (lambda m: setattr(m.camera, "fx", 0.0), "camera model", False),
        # Finite yet absurd, as a fuzzer sent them.
        (lambda m: setattr(m.camera, "fx", 1e-300), "camera fx = 1e-300 px is outside", False),
        (lambda m: setattr(m.pose.position, "y", 1e300), "pose position 1e.300 m", False),
        (lambda m: setattr(m, "depths_m", [1e30] * len(m.depths_m)), "depths must be in", False),
        (_remove_with_200k_keypoints, "keypoints holds 200000 entries, above the limit", False),
        # The compact encodings
        (lambda m: setattr(m, "keypoint_step_px", 0.5), "keypoint_step_px is given without", False),
        (lambda m: setattr(m, "keypoints_uv", [7] * 19), "keypoints_uv holds 19 values", True),
        (
            lambda m: setattr(m, "keypoints_uv", [7] * 40),
            "keypoints_uv holds 40 values for 10",
            True,
        ),
        (lambda m: setattr(m, "ref_keyframes", [4]), "ref_keyframes is given without", True),
        (lambda m: setattr(m, "moves_q", [0, 0, 0]), "moves are given without moved", True),
        (lambda m: setattr(m, "keypoint_step_px", 0.0), "keypoint_step_px 0.0 is not in", True),
        (lambda m: setattr(m, "keypoint_step_px", float("nan")), "keypoint_step_px nan", True),
        (
            lambda m: setattr(m, "keypoints", [1.0] * 20),
            "keypoints and keypoints_uv are both",
            True,
        ),
        (lambda m: setattr(m, "depths_f16", m.depths_f16[:-1]), "depths_f16 holds 19 bytes", True),
        (lambda m: setattr(m, "depths_m", [1.0] * 10), "depths_m and depths_f16 are both", True),
        (
            lambda m: setattr(m, "keypoint_step_px", 1.0),
            "keypoints outside the 640x480 image",
            True,
        ),
        (
            lambda m: setattr(m, "map_point_id_codes", m.map_point_id_codes + b"\x80"),
            "_codes: the",
            True,
        ),
        (
            lambda m: setattr(m, "map_point_ids", [1] * 10),
            "map_point_ids and map_point_id_codes",
            True,
        ),
        (lambda m: setattr(m, "map_point_id_codes", b"\x02" * 10), "an id outside", True),
    ],
)
def test_malformed_keyframes_are_rejected(mutate, match, compact):
    msg = keyframe_to_msg(make_keyframe(n=10, robot_id=1), "robot_1/map", compact=compact)
    msg = _wire(unpacked(msg))  # the arrays in their own fields, to break them one by one
    mutate(msg)
    with pytest.raises(MessageError, match=match):
        keyframe_from_msg(msg, known_robots={1, 2})


def test_images_and_depth():
    img = np.random.default_rng(0).integers(0, 255, (4, 5, 3), dtype=np.uint8)
    assert np.array_equal(image_from_msg(_wire(image_to_msg(img, "bgr8"))), img)
    rgb = image_to_msg(img[:, :, ::-1], "rgb8")
    assert np.array_equal(image_from_msg(rgb), img)
    d16 = image_to_msg(np.full((3, 3), 1500, np.uint16), "16UC1")
    assert np.allclose(depth_from_msg(d16), 1.5)
    d32 = np.full((3, 3), 2.0, np.float32)
    d32[0, 0] = np.nan
    out = depth_from_msg(image_to_msg(d32, "32FC1"))
    assert out[0, 0] == 0.0 and out[1, 1] == 2.0
    bad = image_to_msg(img, "bgr8")
    bad.data = bad.data[:-1]
    with pytest.raises(MessageError, match="bytes"):
        image_from_msg(bad)
    empty = image_to_msg(np.zeros((0, 0, 3), np.uint8), "bgr8")
    with pytest.raises(MessageError, match="empty"):
        image_from_msg(empty)
    bad.encoding = "yuv422"
    with pytest.raises(MessageError, match="unsupported"):
        image_from_msg(bad)


def test_pose_conversion_and_reject_counter():
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    assert np.allclose(pose_from_msg(pose_to_msg(T)), T)
    T[1, 3] = 1e300  # a map correction placing a keyframe there would move the client's pose
    with pytest.raises(MessageError, match="keyframe pose position 1e.300 m is beyond"):
        pose_from_msg(pose_to_msg(T), "keyframe pose")
    with pytest.raises(MessageError, match="T_world_map position"):
        transform_from_msg(transform_to_msg(T), "T_world_map")
    counter = RejectCounter("test", log_period_s=100.0)
    counter.reject("/a", "bad")
    counter.reject("/a", "bad")
    counter.reject("/b", "worse")
    assert counter.counts["/a"] == 2 and counter.total == 3


def test_stereo_camera_from_the_ros_stereo_camera_infos():
    """The baseline comes from the right camera's projection matrix (P[3] = -fx * b); a swapped
    pair, a left info on the right topic or sizes that disagree are named."""
    import dataclasses

    from coop_slam.ros.convert import camera_info_to_msg, stereo_camera_from_infos
    from helpers import camera

    stereo = dataclasses.replace(camera(), sensor="stereo", baseline_m=0.12)
    left = _wire(camera_info_to_msg(stereo))
    right = _wire(camera_info_to_msg(stereo, right=True))
    got = stereo_camera_from_infos(left, right)
    assert got.sensor == "stereo" and got.baseline_m == pytest.approx(0.12)
    assert (got.width, got.height, got.fx, got.cx) == (640, 480, stereo.fx, stereo.cx)
    with pytest.raises(MessageError, match="left and right swapped"):
        stereo_camera_from_infos(right, left)  # the "right" info is the left camera's
    flipped = _wire(camera_info_to_msg(stereo, right=True))
    flipped.P = list(flipped.P[:3]) + [-flipped.P[3]] + list(flipped.P[4:])
    with pytest.raises(MessageError, match="baseline -0.1200 m"):
        stereo_camera_from_infos(left, flipped)
    small = _wire(
        camera_info_to_msg(dataclasses.replace(stereo, width=320, height=240), right=True)
    )
    with pytest.raises(MessageError, match="differ in size"):
        stereo_camera_from_infos(left, small)


def test_a_place_signature_round_trip_over_the_wire():
    """Low-bandwidth mode: a new keyframe as its BoW vector only, a few kB instead of ~50."""
    from coop_slam.bow.vocabulary import l1_score
    from coop_slam.keyframe_record import PlaceSignature
    from coop_slam.vo.outbox import signature_of
    from helpers import team_world

    _, _, kfs, vocab = team_world(4)
    kf = kfs[1]
    idf = vocab.word_weights
    bow = vocab.transform(kf.descriptors)[0]
    signature = signature_of(kf, vocab)
    msg = _wire(keyframe_to_msg(signature, "robot_1/map"))
    back = keyframe_from_msg(msg, {1, 2}, word_idf=idf)
    assert isinstance(back, PlaceSignature) and back.keyframe_id == kf.keyframe_id
    # Feature counts travel: the server's vector is the client's (weights: within 1 %)
    assert signature.counts is not None and len(unpacked(msg).bow_counts) == len(bow)
    np.testing.assert_allclose(back.bow.weights, bow.weights, rtol=1e-9)
    np.testing.assert_array_equal(back.bow.words, bow.words)
    np.testing.assert_allclose(back.record.T_map_cam, kf.T_map_cam, atol=1e-9)
    weighed = _wire(keyframe_to_msg(dataclasses.replace(signature, counts=None), "robot_1/map"))
    assert l1_score(keyframe_from_msg(weighed, {1, 2}).bow, bow) > 0.99
    assert _size(msg) < _size(weighed) < _size(_wire(keyframe_to_msg(kf, "robot_1/map"))) / 5
    with pytest.raises(MessageError, match="needs the server's vocabulary"):
        keyframe_from_msg(msg, {1, 2})
    with pytest.raises(MessageError, match="must share one vocabulary"):
        keyframe_from_msg(msg, {1, 2}, word_idf=idf[: bow.words[-1]])
    msg.action = msg.ACTION_UPDATE
    with pytest.raises(MessageError, match="only a new keyframe"):
        keyframe_from_msg(msg, {1, 2}, word_idf=idf)
    msg = unpacked(msg)
    msg.action = msg.ACTION_NEW
    for change, match in (
        (dict(bow_counts=msg.bow_counts[:-1]), "words but"),
        (dict(bow_counts=bytes(len(bow))), "no feature on a word"),
        (dict(bow_weights=bytes(len(bow))), "bow_weights and bow_counts are both given"),
    ):
        bad = _wire(msg)
        for k, v in change.items():
            setattr(bad, k, v)
        with pytest.raises(MessageError, match=match):
            keyframe_from_msg(bad, {1, 2}, word_idf=idf)
    weighed = unpacked(weighed)
    weighed.bow_weights = weighed.bow_weights[:-1]
    with pytest.raises(MessageError, match="words but"):
        keyframe_from_msg(weighed, {1, 2})


def test_a_refused_keyframe_is_not_referred_to_after_the_acknowledgement():
    """The server acknowledges the keyframes it refused (KeyframeAck.refused_keyframe_ids); the
    client's uplink forgets them, so later keyframes carry the descriptors themselves instead of
    being refused in turn (one refusal refused every later keyframe before)."""
    import dataclasses

    from coop_slam.team.durable import DurableServer, PendingKeyframe
    from coop_slam.team.server import TeamServer
    from coop_slam.vo.outbox import Uplink
    from helpers import team_server_config, team_vocabulary

    a = make_keyframe(n=80, keyframe_id=1)
    vocab = team_vocabulary([a])
    durable = DurableServer(team_server_config(robots=[1]), lambda c: TeamServer(c, vocab), None)
    uplink, sequence = Uplink(), [0]

    def send(rec):
        out = uplink.prepare(rec)
        msg = _wire(keyframe_to_msg(rec, "robot_1/map", out.delta, out.patched, out.refs))
        stored = functools.partial(durable.server.stored_record, 1, msg.map_segment)
        item = PendingKeyframe(1, lambda: keyframe_from_msg(msg, {1}, stored), msg.keyframe_id)
        sequence[0] += 1
        return msg, durable.add_keyframe(item, 7, sequence[0])

    bad = dataclasses.replace(a, depths_m=np.full(80, 5000.0, np.float32))  # beyond any camera
    _, taken = send(bad)
    assert taken.rejected and durable.refused(1) == [1]
    b = _sees(make_keyframe(n=80, keyframe_id=2, seed=1), a, np.arange(0, 20, 2))
    msg, taken = send(b)  # sent before the acknowledgement came: refused as well
    assert len(unpacked(msg).descriptor_refs) and taken.rejected and durable.refused(1) == [1, 2]
    uplink.forget(durable.refused(1))
    c = _sees(make_keyframe(n=80, keyframe_id=3, seed=2), a, np.arange(0, 20, 2))
    msg, taken = send(c)
    assert not len(msg.descriptor_refs) and not taken.rejected
    # Keyframe 1's next update goes whole and the server holds it again.
    msg, taken = send(dataclasses.replace(a, action=1))
    assert not msg.delta and not taken.rejected and durable.refused(1) == [2]


def test_a_removal_and_a_keyframe_without_keypoints_go_in_compact_messages():
    """A culled keyframe's removal carries no keypoints: its message must still be written (the
    compact keypoint encoding once refused it, and the client lost the batch it was in)."""
    from coop_slam.keyframe_record import ACTION_REMOVE, KeyframeRecord

    kf = make_keyframe()
    removal = KeyframeRecord(
        kf.robot_id, kf.keyframe_id, 0.0, kf.camera, np.eye(4), action=ACTION_REMOVE
    )
    back = keyframe_from_msg(keyframe_to_msg(removal, "robot_1/map"))
    assert back.action == ACTION_REMOVE and back.keyframe_id == kf.keyframe_id
    empty = make_keyframe(n=0)
    back = keyframe_from_msg(keyframe_to_msg(empty, "robot_1/map"))
    assert len(back.keypoints) == 0 and back.keyframe_id == empty.keyframe_id


def test_a_packed_message_decodes_to_the_keyframe_its_fields_would():
    """Compact messages pack their integer arrays into one zlib stream: smaller, the same
    keyframe; a broken stream, or a packed array also given in its own field, is refused."""
    import zlib

    from coop_slam.field_pack import PACKED_FIELDS
    from coop_slam.vo.outbox import Uplink

    n_fields = len(PACKED_FIELDS)
    uplink = Uplink()
    a = make_keyframe(n=80, robot_id=2, keyframe_id=1)
    b = _sees(make_keyframe(n=80, robot_id=2, keyframe_id=2, seed=1), a, np.arange(0, 30, 2))
    held = {}
    for rec in (a, b):
        out = uplink.prepare(rec)
        msg = _wire(keyframe_to_msg(rec, "robot_2/map", out.delta, out.patched, out.refs))
        assert len(msg.packed) and not len(msg.octaves) and not len(msg.keypoints_uv)
        opened = _wire(unpacked(msg))
        assert not len(opened.packed) and len(opened.octaves) == 80
        assert _size(msg) < _size(opened)
        assert needs_stored(msg) == needs_stored(opened) == (rec is b)
        got = keyframe_from_msg(msg, {2}, stored=held.get)
        want = keyframe_from_msg(opened, {2}, stored=held.get)
        for name in ("keypoints", "octaves", "descriptors", "depths_m", "map_point_ids"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        np.testing.assert_array_equal(got.map_points, want.map_points)
        np.testing.assert_array_equal(got.covisible_ids, rec.covisible_ids)
        held[rec.keyframe_id] = got
    for change, match in (
        (dict(packed=b"not zlib"), "packed is no deflate stream"),
        (dict(packed=msg.packed[:-3]), "ends inside its deflate stream"),
        (dict(packed=zlib.compress(b"\x07")), "packed is of format 7"),
        (dict(packed=zlib.compress(b"\x01" + bytes(n_fields) + b"x")), "packed holds 1 bytes"),
        (dict(octaves=bytes(80)), "octaves given beside packed"),
    ):
        bad = _wire(msg)
        for k, v in change.items():
            setattr(bad, k, v)
        with pytest.raises(MessageError, match=match):
            keyframe_from_msg(bad, {2}, stored=held.get)
        with pytest.raises(MessageError, match=match):
            needs_stored(bad)
