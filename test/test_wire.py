"""What crosses the radio (coop_slam.wire): each kind of keyframe message encoded and decoded,
its compact encodings' error bounds, the checks that refuse a malformed message by name, and the
ROS message classes agreeing field for field with the wire's own."""

import dataclasses
import functools

import numpy as np
import pytest

from coop_slam.uplink.config import UplinkConfig
from coop_slam.uplink.planner import Planner
from coop_slam.wire.codec import (
    DELTA_ARRAYS,
    SIGNATURE_ARRAYS,
    WHOLE_ARRAYS,
    Incomplete,
    Outgoing,
    WireError,
    decode,
    encode,
)
from coop_slam.wire.encodings import MOVE_STEP_M, encode_map_point_ids
from coop_slam.wire.messages import KIND_DELTA, KIND_KEYFRAME, KIND_REMOVAL, KIND_SIGNATURE
from coop_slam.wire.pack import pack_fields, unpack_fields
from coop_slam.wire.record import (
    ACTION_NEW,
    ACTION_REMOVE,
    ACTION_UPDATE,
    KeyframeError,
    KeyframeRecord,
)
from helpers import depth_blob, make_keyframe

SCHEMAS = {KIND_KEYFRAME: WHOLE_ARRAYS, KIND_DELTA: DELTA_ARRAYS, KIND_SIGNATURE: SIGNATURE_ARRAYS}


def _body(msg):
    return (msg.keyframe or msg.delta or msg.signature)[0]


def _arrays(msg) -> dict:
    """The arrays a message packs, by name (copies: to change and repack)."""
    return {k: v.copy() for k, v in unpack_fields(_body(msg).packed, SCHEMAS[msg.kind]).items()}


def _repacked(msg, **arrays):
    """A copy of ``msg`` with some of its packed arrays replaced."""
    msg = _copy(msg)
    packed = _arrays(msg)
    packed.update({k: np.asarray(v) for k, v in arrays.items()})
    _body(msg).packed = pack_fields(packed, SCHEMAS[msg.kind])
    return msg


def _copy(msg):
    import copy

    return copy.deepcopy(msg)


def _decoded(msg, known=(1, 2), stored=None, idf=None):
    """What the server takes: decoded, and completed from ``stored`` when it must be."""
    got = decode(msg, set(known), idf)
    if isinstance(got, Incomplete):
        got = got.complete(stored or (lambda _kf: None))
    return got


def _size(msg) -> int:
    body = _body(msg) if msg.kind != KIND_REMOVAL else None
    if body is None:
        return 0
    return sum(len(getattr(body, f)) * (4 if f == "map_points" else 1) for f in _byte_fields(body))


def _byte_fields(body):
    return [
        f.name for f in dataclasses.fields(body) if isinstance(getattr(body, f.name), (bytes, list))
    ]


# --- whole keyframes ------------------------------------------------------------------------------
def test_a_whole_keyframe_round_trip():
    kf = make_keyframe(n=40, robot_id=2, keyframe_id=9)
    kf.T_map_cam[:3, 3] = [1.0, -2.0, 0.5]
    kf.depth_image = depth_blob()
    msg = encode(kf, frame_id="robot_2/map")
    assert msg.kind == KIND_KEYFRAME and not msg.keyframe[0].replaces
    back = _decoded(msg)
    assert back.robot_id == 2 and back.keyframe_id == 9 and back.action == ACTION_NEW
    assert np.array_equal(back.descriptors, kf.descriptors)
    # Keypoints in 1/64 px steps (a 640x480 image), depths as half floats.
    assert msg.keyframe[0].keypoint_step_px == 1 / 64
    np.testing.assert_allclose(back.keypoints[:, :2], kf.keypoints[:, :2], rtol=0, atol=1 / 128)
    np.testing.assert_allclose(back.depths_m, kf.depths_m, rtol=2**-11, atol=0)
    # Their size and angle do not travel (the server does not use them).
    assert np.all(back.keypoints[:, 2] == 0) and np.all(back.keypoints[:, 3] == -1)
    assert np.array_equal(back.map_point_ids, kf.map_point_ids)
    assert np.allclose(back.map_points, kf.map_points)
    assert np.allclose(back.T_map_cam, kf.T_map_cam, atol=1e-9)
    assert back.stamp_s == pytest.approx(kf.stamp_s)
    assert back.depth_image.tobytes() == kf.depth_image.tobytes()  # as compressed on the robot
    # Map point ids as varint steps: a byte each here (ids 1, 3, 5, ... on every other keypoint)
    assert len(_arrays(msg)["map_point_id_codes"]) == 40
    # An update sent whole replaces what the server holds.
    again = encode(dataclasses.replace(kf, action=ACTION_UPDATE))
    assert again.keyframe[0].replaces and _decoded(again).action == ACTION_UPDATE


def test_keypoints_travel_from_a_pixel_outside_the_image_and_no_further():
    kf = make_keyframe(n=10)
    kf.keypoints[0, :2] = [-0.75, 480.9]  # within a pixel of the 640x480 image
    back = _decoded(encode(kf))
    np.testing.assert_allclose(back.keypoints[0, :2], [-0.75, 480.9], atol=1 / 128)
    kf.keypoints[0, 0] = -1.5
    with pytest.raises(WireError, match="more than 1 px outside the 640x480 image"):
        encode(kf)


def test_depths_that_have_no_half_float_are_refused_by_name():
    kf = make_keyframe(n=10)
    for depth in (70000.0, 1e-6):  # beyond the half float's range; so small it loses precision
        with pytest.raises(WireError, match="depths must be 0 or within"):
            encode(dataclasses.replace(kf, depths_m=np.full(10, depth, np.float32)))


def test_map_points_travel_as_offsets_from_their_keypoints_depths():
    """A whole keyframe carries an observed keypoint's map point as a half-float offset from the
    keypoint at its depth (as the server decodes both), the others' as float32; a point a metre
    and more from its keypoint's depth goes as float32."""
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
    msg = encode(kf)
    body, seen = msg.keyframe[0], kf.map_point_ids != 0
    assert len(body.map_point_offsets_f16) == 6 * int((seen & ~no_depth).sum())
    assert len(body.map_points) == 3 * int((seen & no_depth).sum())
    back = _decoded(msg)
    assert np.abs(back.map_points - kf.map_points).max() < 0.05 * 2**-11 + 1e-5
    np.testing.assert_array_equal(
        back.map_points_per_keypoint()[seen & no_depth],
        kf.map_points_per_keypoint()[seen & no_depth],
    )
    far = kf.map_points.copy()
    far[np.flatnonzero(~no_depth[seen])[0]] += 1.5
    msg = encode(dataclasses.replace(kf, map_points=far))
    assert len(msg.keyframe[0].map_points) == 3 * (int((seen & no_depth).sum()) + 1)
    assert np.abs(_decoded(msg).map_points - far).max() < 0.05 * 2**-11 + 1e-5
    good = encode(kf)
    for field, value, match in (
        ("map_point_offsets_f16", good.keyframe[0].map_point_offsets_f16[:-6], "bytes for 24"),
        ("map_point_offsets_f16", np.full(72, np.inf, "<f2").tobytes(), "holds inf"),
        ("map_point_offsets_f16", np.full(72, np.nan, "<f2").tobytes(), "points for 30 observed"),
        ("map_points", list(good.keyframe[0].map_points)[:-3], "points for 6 observed keypoints"),
    ):
        bad = _copy(good)
        setattr(bad.keyframe[0], field, value)
        with pytest.raises(WireError, match=match):
            _decoded(bad)


def _remove_many_keypoints(m):
    """A message claiming 200,000 keypoints (the record's limit is 10,000)."""
    n = 200_000
    return _repacked(
        m,
        octaves=np.zeros(n, np.uint8),
        keypoints_uv=np.zeros(2 * n, np.uint16),
        depths_f16=np.zeros(2 * n, np.uint8),
        map_point_id_codes=np.zeros(n, np.uint8),
    )


def _set(path, value):
    def change(m):
        m = _copy(m)
        *head, last = path.split(".")
        obj = m
        for part in head:
            obj = getattr(obj, part)
            if isinstance(obj, list):  # a message's payload
                obj = obj[0]
        setattr(obj, last, value(getattr(obj, last)) if callable(value) else value)
        return m

    return change


@pytest.mark.parametrize(
    "mutate, match",
    [
        (_set("keyframe.descriptors", lambda d: d[:-5]), "multiple of 32"),
        (_set("robot_id", 9), "unknown"),
        (_set("keyframe.pose.orientation.w", float("nan")), "unit quaternion"),
        (_set("keyframe.pose.position.x", float("inf")), "NaN or inf"),
        (_set("keyframe.camera.fx", 0.0), "camera model"),
        # Finite yet absurd, as a fuzzer sent them.
        (_set("keyframe.camera.fx", 1e-300), "camera fx = 1e-300 px is outside"),
        (_set("keyframe.pose.position.y", 1e300), "pose position 1e.300 m"),
        (_set("keyframe.camera.sensor_type", 7), "sensor_type 7 unknown"),
        (_set("keyframe.keypoint_step_px", 0.0), "keypoint_step_px 0.0 is not in"),
        (_set("keyframe.keypoint_step_px", float("nan")), "keypoint_step_px nan"),
        (_set("keyframe.keypoint_step_px", 1.0), "keypoints outside the 640x480 image"),
        (_set("keyframe.packed", b"not zlib"), "packed is no deflate stream"),
        (_set("keyframe.packed", lambda p: p[:-3]), "ends inside its deflate stream"),
        (lambda m: _repacked(m, keypoints_uv=[7] * 19), "keypoints_uv holds 19 values"),
        (lambda m: _repacked(m, depths_f16=np.zeros(19, np.uint8)), "depths_f16 holds 19 bytes"),
        (
            lambda m: _repacked(m, depths_f16=np.frombuffer(np.full(10, 1e4, "<f2"), np.uint8)),
            "depths must be in",
        ),
        (lambda m: _repacked(m, ref_keyframes=[4]), "ref_keyframes is given without"),
        (lambda m: _repacked(m, map_point_id_codes=[0x80]), "_codes: the"),
        (lambda m: _repacked(m, map_point_id_codes=[2] * 10), "an id outside"),
        (lambda m: _repacked(m, covisible_ids=[3]), "covisible_ids and covisible_weights"),
        (_remove_many_keypoints, "holds 200000 entries, above the limit"),
        (_set("kind", KIND_DELTA), "a delta message holds 1 keyframe payloads"),
        (_set("kind", 9), "unknown message kind 9"),
    ],
)
def test_malformed_keyframes_are_refused_by_name(mutate, match):
    msg = encode(make_keyframe(n=10, robot_id=1))
    with pytest.raises(WireError, match=match):
        _decoded(mutate(msg))


def test_a_packed_stream_of_another_kind_or_format_is_refused():
    import zlib

    msg = encode(make_keyframe(n=10, robot_id=1))
    delta_stream = pack_fields({"patched": np.arange(3)}, DELTA_ARRAYS)
    for packed, match in (
        (delta_stream, "packed is of format 3, a whole keyframe is format 2"),
        (zlib.compress(b"\x02" + bytes(len(WHOLE_ARRAYS.fields)) + b"x"), "packed holds 1 bytes"),
        (zlib.compress(b"\x02") + b"tail", "bytes after its deflate stream"),
    ):
        bad = _copy(msg)
        bad.keyframe[0].packed = packed
        with pytest.raises(WireError, match=match):
            _decoded(bad)


# --- delta updates --------------------------------------------------------------------------------
def test_a_delta_update_rebuilds_the_same_keyframe_as_a_whole_one():
    sent = make_keyframe(n=60, robot_id=2, keyframe_id=9)
    sent.depth_image = depth_blob()
    held = _decoded(encode(sent))
    upd = dataclasses.replace(sent, action=ACTION_UPDATE, T_map_cam=sent.T_map_cam.copy())
    upd.T_map_cam[:3, 3] += [0.1, 0.0, -0.05]
    upd.map_points = upd.map_points + np.float32(0.01)
    every = np.arange(60, dtype=np.uint32)  # a patch of every keypoint: all observations go
    whole, delta = encode(upd), encode(upd, Outgoing(True, every))
    assert delta.kind == KIND_DELTA and _size(delta) < _size(whole) / 3
    full = _decoded(whole)
    got = _decoded(delta, stored=lambda _kf: held)
    for name in ("T_map_cam", "keypoints", "octaves", "descriptors", "depths_m", "depth_image"):
        np.testing.assert_array_equal(getattr(got, name), getattr(full, name))
    # The depth image stays on the server: a delta is no larger for it.
    bare = dataclasses.replace(upd, depth_image=np.zeros(0, np.uint8))
    assert len(got.depth_image) and _size(delta) == _size(encode(bare, Outgoing(True, every)))
    np.testing.assert_allclose(got.map_points, upd.map_points, atol=1e-6)
    assert got.static_digest() == full.static_digest() and got.action == ACTION_UPDATE
    with pytest.raises(WireError, match="does not hold"):
        _decoded(delta)
    with pytest.raises(WireError, match="only an update with a patch goes as a delta"):
        encode(sent, Outgoing(True, every))


def test_delta_updates_carry_only_the_observations_that_changed():
    """A client's updates through the planner, completed by the server from what it holds, give
    the keyframe as a whole message would -- within point_move_m for points that moved less."""
    move_m = 0.002
    planner = Planner(UplinkConfig(point_move_m=move_m))
    rng = np.random.default_rng(3)
    kf = make_keyframe(n=80, robot_id=2, keyframe_id=9)
    out = planner.prepare(kf)
    assert not out.delta and out.patched is None
    held = _decoded(encode(kf, out))
    for step in range(4):
        upd = dataclasses.replace(kf, action=ACTION_UPDATE, T_map_cam=kf.T_map_cam.copy())
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
        out = planner.prepare(upd)
        # The reassigned keypoints travel as a patch, the moved points as moves.
        reassigned = np.flatnonzero(ids != kf.map_point_ids)
        assert out.delta and np.array_equal(out.patched, reassigned)
        assert 0 < len(out.moves[0]) <= 10
        msg = encode(upd, out)
        arrays = _arrays(msg)
        assert len(arrays["moves_q"]) == 3 * len(arrays["moved"]) == 3 * len(out.moves[0])
        assert _size(msg) < _size(encode(upd)) / 2
        held = _decoded(msg, stored=lambda _kf, base=held: base)
        np.testing.assert_array_equal(held.map_point_ids, upd.map_point_ids)
        np.testing.assert_allclose(held.T_map_cam, upd.T_map_cam, atol=1e-6)
        err = np.linalg.norm(held.map_points - upd.map_points, axis=1)
        assert err.max() <= move_m + 1e-6
        moved = held.map_points_per_keypoint()[out.moves[0]] - per_kp[out.moves[0]]
        assert np.abs(moved).max() <= MOVE_STEP_M / 2 + 1e-6
        kf = upd
    # What the keyframe saw changed (a client re-extracted it): the update goes whole.
    redone = dataclasses.replace(kf, descriptors=kf.descriptors[::-1].copy())
    assert not planner.prepare(redone).delta
    assert not planner.prepare(dataclasses.replace(kf, action=ACTION_NEW)).delta


def test_malformed_patches_and_moves_are_refused_by_name():
    sent = make_keyframe(n=20, robot_id=1, keyframe_id=4)
    held = _decoded(encode(sent), known=(1,))
    upd = dataclasses.replace(sent, action=ACTION_UPDATE)
    msg = encode(upd, Outgoing(True, np.array([2], np.uint32)))

    def refused(match, **arrays):
        with pytest.raises(WireError, match=match):
            _decoded(_repacked(msg, **arrays), known=(1,), stored=lambda _kf: held)

    refused("names keypoint 25 of a keyframe with 20", patched=[25])
    refused("names a keypoint twice", patched=[1, 1], map_point_ids=[0, 0])
    refused("patched lists 3 keypoints but map_point_ids has 1", patched=[1, 2, 3])
    bad = _copy(msg)
    bad.delta[0].map_points = [0.0] * 6
    with pytest.raises(WireError, match="gives 2 map points for 1 observed"):
        _decoded(bad, known=(1,), stored=lambda _kf: held)
    # Moves of map points (keypoint 0 observes map point 1, keypoint 1 none)
    for moved, n, match in (
        ([0], 2, "moves_q holds 2 values for 1 moved"),
        ([25], 3, "moved names keypoint 25 of a keyframe with 20"),
        ([0, 0], 6, "moved names a keypoint twice"),
        ([1], 3, "moved names a keypoint that observes no map point"),
        ([2], 3, "both patched and moved"),
    ):
        refused(match, moved=np.array(moved, np.uint16), moves_q=np.zeros(n, np.int16))
    got = _decoded(
        _repacked(msg, moved=np.array([0], np.uint16), moves_q=np.array([2048, -1, 0], np.int16)),
        known=(1,),
        stored=lambda _kf: held,
    )
    np.testing.assert_allclose(
        got.map_points[0], held.map_points[0] + [0.5, -MOVE_STEP_M, 0], atol=1e-6
    )


# --- descriptors taken from keyframes the server holds --------------------------------------------
def _sees(kf, ids_from, keypoints, bits=4):
    """``kf`` with its ``keypoints`` now observing the map points of keyframe ``ids_from``'s
    same keypoints (tracked from it), at the points' positions there moved by 5 cm, their
    descriptors there with ``bits`` bits flipped."""
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
    planner = Planner()
    server: dict[int, object] = {}  # keyframe id -> as the server holds it

    def send(rec):
        out = planner.prepare(rec)
        msg = encode(rec, out)
        got = _decoded(msg, stored=server.get)
        if rec.action == ACTION_REMOVE:
            server.pop(rec.keyframe_id, None)
        else:
            server[rec.keyframe_id] = got
        return out, msg, got

    a = make_keyframe(n=80, robot_id=2, keyframe_id=1)  # map points 1, 3, 5, ... at 0, 2, 4, ...
    b = make_keyframe(n=80, robot_id=2, keyframe_id=2, seed=1)
    b.map_point_ids = np.where(b.map_point_ids != 0, b.map_point_ids + 1000, 0).astype(np.uint32)
    b = _sees(b, a, np.arange(0, 30, 2))  # tracked 15 of a's points
    b = _sees(b, a, np.array([31]))  # a keypoint with no map point in a: nothing to take
    b = _sees(b, a, np.arange(32, 40, 2), bits=40)  # the view changed them too much: they travel
    out_a, _, _ = send(a)
    assert out_a.refs is None  # the server holds nothing yet
    out_b, msg_b, got_b = send(b)
    ref_kfs, refs = out_b.refs
    assert list(ref_kfs) == [1] and np.array_equal(np.flatnonzero(refs), np.arange(0, 30, 2))
    assert len(msg_b.keyframe[0].descriptors) == 32 * (80 - 15)
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
    # new map segment tracking b's, and c sent whole again (what it saw changed) refers to b
    # but not to itself.
    removal = send(KeyframeRecord(2, 1, 0.0, None, np.eye(4), action=ACTION_REMOVE))[1]
    assert removal.kind == KIND_REMOVAL
    d = _sees(make_keyframe(n=80, robot_id=2, keyframe_id=4, seed=3), a, np.arange(60, 70, 2))
    per_kp = d.map_points_per_keypoint()
    d.map_point_ids = np.where(np.arange(80) < 60, 0, d.map_point_ids).astype(np.uint32)
    d.map_points = per_kp[d.map_point_ids != 0].astype(np.float32)
    assert send(d)[0].refs is None
    e = _sees(make_keyframe(n=80, robot_id=2, keyframe_id=5), b, [0])
    assert planner.prepare(dataclasses.replace(e, map_segment=1)).refs is None
    redone = dataclasses.replace(c, action=ACTION_UPDATE, descriptors=c.descriptors.copy())
    redone.descriptors[:, -1] ^= 1
    out = planner.prepare(redone)
    assert not out.delta and list(out.refs[0]) == [2]
    # The server no longer holds what a message refers to: refused, naming it.
    del server[2]
    with pytest.raises(WireError, match="refer to keyframe 2, which the server does not hold"):
        _decoded(encode(redone, out), stored=server.get)
    # Switched off, every descriptor travels.
    plain = Planner(UplinkConfig(share_descriptors=False))
    plain.prepare(a)
    assert plain.prepare(b).refs is None
    # Any difference allowed, the ones the view changed too are taken from a.
    anyway = Planner(UplinkConfig(share_max_bits=256))
    anyway.prepare(a)
    tracked = np.r_[np.arange(0, 30, 2), np.arange(32, 40, 2)]
    assert np.array_equal(np.flatnonzero(anyway.prepare(b).refs[1]), tracked)


def test_malformed_descriptor_refs_are_refused_by_name():
    from coop_slam.wire.observations import observation_index

    np.testing.assert_array_equal(
        observation_index(np.array([0, 7, 3, 7]), np.array([7, 3, 0, 9])), [1, 2, -1, -1]
    )
    held = make_keyframe(n=20, robot_id=1, keyframe_id=4)
    kf = make_keyframe(n=20, robot_id=1, keyframe_id=5, seed=1)  # map points 1, 3, ... as held
    refs = np.where(kf.map_point_ids != 0, 1, 0).astype(np.uint8)
    stored = {4: held}.get
    ok = encode(kf, Outgoing(False, refs=(np.array([4]), refs)))
    assert isinstance(decode(ok, {1}), Incomplete)  # completed when the server takes it
    got = _decoded(ok, known=(1,), stored=stored)
    np.testing.assert_array_equal(got.descriptors[refs != 0], held.descriptors[::2])
    codes = np.frombuffer(encode_map_point_ids(np.where(refs, 99, 0)), np.uint8)
    for change, match in (
        (dict(descriptor_refs=refs[:-1]), "descriptor_refs has 19 entries"),
        (dict(descriptor_refs=refs * 2), "names reference 2 of 1"),
        (dict(map_point_id_codes=codes), "map point 99 in"),
        (dict(ref_keyframes=[6]), "keyframe 6, which the server does not hold"),
        (dict(ref_keyframes=[4] * 256), "ref_keyframes lists 256 keyframes, above the limit"),
    ):
        with pytest.raises(WireError, match=match):
            _decoded(_repacked(ok, **change), known=(1,), stored=stored)
    bad = _copy(ok)
    bad.keyframe[0].descriptors = bad.keyframe[0].descriptors[:-32]
    with pytest.raises(WireError, match="hold 9 descriptors for 10 keypoints"):
        _decoded(bad, known=(1,), stored=stored)
    wrong = refs.copy()
    wrong[1] = 1  # keypoint 1 observes no map point
    with pytest.raises(WireError, match="observes no map point"):
        _decoded(encode(kf, Outgoing(False, refs=(np.array([4]), wrong))), (1,), stored)


# --- place signatures and removals ----------------------------------------------------------------
def test_a_place_signature_round_trip():
    """Low-bandwidth mode: a new keyframe as its BoW vector only, a few kB instead of ~40."""
    from coop_slam.bow.vocabulary import l1_score
    from coop_slam.uplink.records import signature_of
    from coop_slam.wire.record import PlaceSignature
    from helpers import team_world

    _, _, kfs, vocab = team_world(4)
    kf = kfs[1]
    idf = vocab.word_weights
    bow = vocab.transform(kf.descriptors)[0]
    signature = signature_of(kf, vocab)
    msg = encode(signature)
    assert msg.kind == KIND_SIGNATURE
    back = _decoded(msg, idf=idf)
    assert isinstance(back, PlaceSignature) and back.keyframe_id == kf.keyframe_id
    # Feature counts travel: the server's vector is the client's (weights: within 1 %)
    assert signature.counts is not None and len(_arrays(msg)["bow_counts"]) == len(bow)
    np.testing.assert_allclose(back.bow.weights, bow.weights, rtol=1e-9)
    np.testing.assert_array_equal(back.bow.words, bow.words)
    np.testing.assert_allclose(back.record.T_map_cam, kf.T_map_cam, atol=1e-9)
    weighed = encode(dataclasses.replace(signature, counts=None))
    assert l1_score(_decoded(weighed).bow, bow) > 0.99
    assert _size(msg) < _size(weighed) < _size(encode(kf)) / 5
    with pytest.raises(WireError, match="needs the server's vocabulary"):
        _decoded(msg)
    with pytest.raises(WireError, match="must share one vocabulary"):
        _decoded(msg, idf=idf[: bow.words[-1]])
    counts = _arrays(msg)["bow_counts"]
    for change, match in (
        (dict(bow_counts=counts[:-1]), "words but"),
        (dict(bow_counts=np.zeros(len(bow), np.uint8)), "no feature on a word"),
        (dict(bow_weights=np.ones(len(bow), np.uint8)), "bow_weights and bow_counts are both"),
    ):
        with pytest.raises(WireError, match=match):
            _decoded(_repacked(msg, **change), idf=idf)
    weights = _arrays(weighed)["bow_weights"]
    with pytest.raises(WireError, match="words but"):
        _decoded(_repacked(weighed, bow_weights=weights[:-1]))


def test_a_removal_carries_no_camera_and_a_keyframe_without_keypoints_goes_whole():
    kf = make_keyframe()
    removal = KeyframeRecord(kf.robot_id, kf.keyframe_id, 0.0, kf.camera, np.eye(4))
    removal.action = ACTION_REMOVE
    msg = encode(removal)
    assert msg.kind == KIND_REMOVAL and not (msg.keyframe or msg.delta or msg.signature)
    back = _decoded(msg)
    assert back.action == ACTION_REMOVE and back.keyframe_id == kf.keyframe_id
    assert back.camera is None and back.stamp_s == 0.0
    empty = make_keyframe(n=0)
    back = _decoded(encode(empty))
    assert len(back.keypoints) == 0 and back.keyframe_id == empty.keyframe_id


def test_a_refused_keyframe_is_not_referred_to_after_the_acknowledgement():
    """The server acknowledges the keyframes it refused (KeyframeAck.refused_keyframe_ids); the
    client's planner forgets them, so later keyframes carry the descriptors themselves instead of
    being refused in turn (one refusal refused every later keyframe before)."""
    from coop_slam.team.durable import DurableServer
    from coop_slam.team.server import TeamServer
    from helpers import team_server_config, team_vocabulary

    a = make_keyframe(n=80, keyframe_id=1)
    vocab = team_vocabulary([a])
    durable = DurableServer(team_server_config(robots=[1]), lambda c: TeamServer(c, vocab), None)
    planner, sequence = Planner(), [0]

    def send(rec):
        """Decoded when the server takes it, as a message it completes: a refusal then is the
        durable server's, which it acknowledges."""
        msg = encode(rec, planner.prepare(rec))
        sequence[0] += 1
        item = Incomplete(
            1, 0, rec.keyframe_id, rec.stamp_s, msg.kind, lambda held: _decoded(msg, (1,), held)
        )
        return msg, durable.add_keyframe(item, 7, sequence[0])

    bad = dataclasses.replace(a, depths_m=np.full(80, 5000.0, np.float32))  # beyond any camera
    _, taken = send(bad)
    assert taken.rejected and durable.refused(1) == [1]
    b = _sees(make_keyframe(n=80, keyframe_id=2, seed=1), a, np.arange(0, 20, 2))
    msg, taken = send(b)  # sent before the acknowledgement came: refused as well
    assert len(_arrays(msg)["descriptor_refs"]) and taken.rejected
    assert durable.refused(1) == [1, 2]
    planner.forget(durable.refused(1))
    c = _sees(make_keyframe(n=80, keyframe_id=3, seed=2), a, np.arange(0, 20, 2))
    msg, taken = send(c)
    assert not len(_arrays(msg)["descriptor_refs"]) and not taken.rejected
    # Keyframe 1's next update goes whole and the server holds it again.
    msg, taken = send(dataclasses.replace(a, action=ACTION_UPDATE))
    assert msg.kind == KIND_KEYFRAME and not taken.rejected and durable.refused(1) == [2]


# --- the ROS message classes ----------------------------------------------------------------------
def test_the_ros_messages_have_the_wire_messages_fields_and_carry_them_unchanged():
    """Every wire class has the fields, in order, of the ROS message it stands for, and a
    message of each kind crosses a ROS topic (serialized, deserialized) and decodes to the same
    record."""
    import io

    pytest.importorskip("coop_slam.msg", reason="generated messages need the catkin workspace")
    from coop_slam.ros.wire_bridge import from_ros, ros_class, to_ros
    from coop_slam.wire import messages as wm

    for cls, name in wm.ROS_TYPES.items():
        slots = list(ros_class(name).__slots__)
        assert [f.name for f in dataclasses.fields(cls)] == slots, name

    def crossed(msg):
        ros = to_ros(msg)
        buf = io.BytesIO()
        ros.serialize(buf)
        out = type(ros)()
        out.deserialize(buf.getvalue())
        return from_ros(out, wm.KeyframeMessage)

    kf = make_keyframe(n=30, robot_id=2, keyframe_id=5)
    upd = dataclasses.replace(kf, action=ACTION_UPDATE, T_map_cam=kf.T_map_cam.copy())
    upd.T_map_cam[0, 3] += 0.1
    patch = Outgoing(True, np.array([1, 2], np.uint32))
    removal = KeyframeRecord(2, 5, 0.0, None, np.eye(4), action=ACTION_REMOVE)
    for msg in (encode(kf, frame_id="robot_2/map"), encode(upd, patch), encode(removal)):
        msg.session, msg.sequence = 7, 3
        back = crossed(msg)
        assert back == msg
        stored = functools.partial(lambda k, rec: rec, rec=_decoded(encode(kf)))
        a, b = _decoded(msg, stored=stored), _decoded(back, stored=stored)
        for f in ("T_map_cam", "keypoints", "descriptors", "depths_m", "map_points"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_the_ros_serializer_refuses_what_rospy_could_not_publish_and_reads_back_what_it_wrote():
    """The client's serializer (the bytes rospy publishes, kept in the spool): a float32 beyond
    its range or a stamp beyond uint32 is a WireError naming the message, not a half-written
    stream; what it wrote reads back unchanged. Such a stamp is refused by validate already."""
    pytest.importorskip("coop_slam.msg", reason="generated messages need the catkin workspace")
    from coop_slam.ros.wire_bridge import RosSerializer
    from coop_slam.wire.messages import Stamp

    ser = RosSerializer()
    msg = encode(make_keyframe(n=30, robot_id=2, keyframe_id=5), frame_id="robot_2/map")
    assert ser.loads(ser.dumps(msg)) == msg
    msg.keyframe[0].keypoint_step_px = 1e300
    with pytest.raises(WireError, match="keyframe message of keyframe 5 cannot be serialized"):
        ser.dumps(msg)
    msg.keyframe[0].keypoint_step_px = 1.0
    msg.header.stamp = Stamp(2**32 + 5, 0)
    with pytest.raises(WireError, match="cannot be serialized") as err:
        ser.dumps(msg)
    assert len(str(err.value)) < 600  # not the whole message, as genpy says it
    late = make_keyframe(n=30, robot_id=2, keyframe_id=5)
    late.stamp_s = 5e9
    with pytest.raises(KeyframeError, match="stamp"):
        late.validate()
    with pytest.raises(WireError, match="does not deserialize"):
        ser.loads(b"\x01\x02")


# --- recorded runs of the format before the kinds ------------------------------------------------
def test_keyframe_messages_of_runs_recorded_before_the_kinds_decode_as_they_did():
    """Real messages of the single KeyFrame type (whole keyframes sharing descriptors, delta
    updates with patches and moves, a removal, place signatures; test/fixtures/legacy_keyframes,
    recorded at cd4229f) decode, through the worker's intake, to the records the code of that
    time decoded (their arrays' digests, legacy_keyframes.json)."""
    import hashlib
    import json
    import os

    rosbag = pytest.importorskip("rosbag", reason="reading a bag needs ROS's rosbag")
    from coop_slam.bow import Vocabulary
    from coop_slam.default_vocabulary import ensure_default_vocabulary
    from coop_slam.wire.legacy import decode_legacy, is_legacy

    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fixtures")
    with open(os.path.join(here, "legacy_keyframes.json"), encoding="utf-8") as fh:
        expected = json.load(fh)
    idf = Vocabulary.load(ensure_default_vocabulary()).word_weights

    def digest(a):
        a = np.ascontiguousarray(a)
        return f"{a.dtype.str}{list(a.shape)}:" + hashlib.sha256(a.tobytes()).hexdigest()[:16]

    stored = {}
    with rosbag.Bag(os.path.join(here, "legacy_keyframes.bag")) as bag:
        got = [
            (topic, msg) for topic, msg, _ in bag.read_messages()
        ]  # (by time: each run in order)
    assert len(got) == len(expected) and all(is_legacy(m) for _, m in got)
    by_key = {(e["topic"], e["sequence"], e["signature"]): e for e in expected}
    for topic, msg in got:
        want = by_key[(topic, msg.sequence, bool(msg.signature_only))]
        rec = decode_legacy(msg, {1, 2}, idf)
        if isinstance(rec, Incomplete):
            rec = rec.complete(stored.get)
        signature = hasattr(rec, "bow")
        r = rec.record if signature else rec
        assert (r.keyframe_id, r.action, signature) == (
            want["keyframe_id"],
            want["action"],
            want["signature"],
        )
        if not signature and r.robot_id == 2:
            stored[r.keyframe_id] = r
        assert r.stamp_s == want["stamp_s"]
        for f in ("T_map_cam", "keypoints", "octaves", "descriptors", "depths_m", "map_point_ids"):
            assert digest(getattr(r, f)) == want[f], (want["sequence"], f)
        for f in ("map_points", "covisible_ids", "covisible_weights"):
            assert digest(getattr(r, f)) == want[f], (want["sequence"], f)
        if signature:
            assert digest(rec.bow.words) == want["bow_words"]
            assert digest(rec.bow.weights) == want["bow_weights"]
    # A broken one is refused by name, as today's are.
    broken = got[5][1]
    broken.packed = broken.packed[:-2]
    with pytest.raises(WireError, match="ends inside its deflate stream"):
        decode_legacy(broken, {1, 2}, idf)
