"""Compact encodings of keyframe messages: varints, map point id codes, moves in steps, packed
integer arrays."""

import numpy as np
import pytest

from coop_slam.wire.encodings import decode_map_point_ids, encode_map_point_ids
from coop_slam.wire.record import KeyframeError
from coop_slam.wire.varint import VarintError, decode_varints, encode_varints


def test_varints_round_trip_and_take_a_byte_below_128():
    values = np.array([0, 1, 127, 128, 300, 2**32 + 5, 2**40], np.int64)
    raw = encode_varints(values)
    assert len(encode_varints(np.arange(128))) == 128
    np.testing.assert_array_equal(decode_varints(raw, 6), values)
    with pytest.raises(VarintError, match="longer than 5 bytes"):
        decode_varints(raw, 5)
    with pytest.raises(VarintError, match="end inside a varint"):
        decode_varints(raw + b"\x80", 6)
    with pytest.raises(VarintError, match="non-negative"):
        encode_varints(np.array([-1]))


def test_map_point_ids_round_trip_in_any_order():
    rng = np.random.default_rng(0)
    ids = rng.integers(1, 2**32 - 1, 500).astype(np.uint32)
    ids[rng.random(500) < 0.4] = 0
    ids[:5] = [7, 8, 9, 10, 11]  # made together: a byte each
    for case in (ids, ids[::-1], np.zeros(3, np.uint32), np.zeros(0, np.uint32)):
        np.testing.assert_array_equal(decode_map_point_ids(encode_map_point_ids(case)), case)
    assert len(encode_map_point_ids(np.arange(1, 101, dtype=np.uint32))) == 100
    with pytest.raises(KeyframeError, match="outside"):
        decode_map_point_ids(encode_varints(np.array([2])))  # a step of -1 from 0


def test_a_move_beyond_the_steps_range_goes_as_a_position():
    """split_moves: a move travels in steps of MOVE_STEP_M, half a step off at most; one beyond
    the int16 steps' range travels as a position (exact), as does every move when the moves
    left unsent are smaller than a step."""
    from coop_slam.wire.encodings import MOVE_STEP_M, move_steps
    from coop_slam.wire.observations import apply_moves, split_moves

    ids = np.array([5, 6, 7, 8], np.uint32)
    held = np.zeros((4, 3))
    now = np.array([[0.01, 0, 0], [70000.0, 0, 0], [-7.9, 3e-5, 0], [8.1, 0, 0]])
    for min_move_m, moved in ((0.002, [0, 2]), (MOVE_STEP_M / 2, [])):
        others, got, moves = split_moves(ids, held, np.arange(4), ids, now, min_move_m)
        assert list(got) == moved and sorted(others) == sorted(set(range(4)) - set(moved))
        assert moves.dtype == np.float32 and np.all(
            moves / MOVE_STEP_M == np.round(moves / MOVE_STEP_M)
        )
        after = apply_moves(ids, held, got, moves)
        assert np.all(np.isfinite(after))
        assert np.abs(after[got] - now[got]).max(initial=0) <= MOVE_STEP_M / 2
    with pytest.raises(KeyframeError, match="beyond 8.0 m"):
        move_steps(np.array([[8.1, 0.0, 0.0]]))


def test_packed_fields_come_back_as_packed_and_a_broken_stream_is_refused():
    import zlib

    from coop_slam.wire.pack import MAX_UNPACKED_BYTES, PackError, Schema, pack_fields
    from coop_slam.wire.pack import unpack_fields as unpack

    schema = Schema(
        9,
        "test message",
        (
            ("keypoints_uv", "<u2"),
            ("octaves", "u1"),
            ("map_point_ids", "<u4"),
            ("patched", "<u4"),
            ("bow_word_gaps", "u1"),
        ),
    )
    rng = np.random.default_rng(0)
    arrays = {
        "keypoints_uv": rng.integers(0, 2**16, 200).astype(np.uint16),
        "octaves": np.repeat(np.arange(8, dtype=np.uint8), 25),
        "map_point_ids": rng.integers(0, 2**32, 100, dtype=np.uint64).astype(np.uint32),
        "bow_word_gaps": bytes(range(256)),
    }
    back = unpack(pack_fields(arrays, schema), schema)
    for name, values in arrays.items():
        np.testing.assert_array_equal(
            back[name], np.frombuffer(values, np.uint8) if isinstance(values, bytes) else values
        )
    assert back["patched"].dtype == np.uint32 and len(back["patched"]) == 0
    assert len(pack_fields({"octaves": np.zeros(10000, np.uint8)}, schema)) < 100  # deflate works
    with pytest.raises(PackError, match="cannot pack .'descriptors'. in a test message"):
        pack_fields({"descriptors": np.zeros(32, np.uint8)}, schema)
    with pytest.raises(PackError, match="more than"):
        unpack(zlib.compress(bytes(MAX_UNPACKED_BYTES + 1)), schema)
    with pytest.raises(PackError, match="ends inside its array lengths"):
        unpack(zlib.compress(b"\x09\x00\x80"), schema)
    with pytest.raises(PackError, match="3 bytes after its deflate stream"):
        unpack(pack_fields(arrays, schema) + b"abc", schema)
    with pytest.raises(PackError, match="lengths say 4"):  # two keypoint steps, no bytes
        unpack(zlib.compress(b"\x09\x02" + bytes(len(schema.fields) - 1)), schema)
    with pytest.raises(PackError, match="format 1, a test message is format 9"):
        unpack(zlib.compress(b"\x01" + bytes(len(schema.fields))), schema)
