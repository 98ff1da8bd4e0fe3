"""Keyframe messages of recorded runs: the single ``coop_slam/KeyFrame`` type every kind went as
before each kind had its own (runs recorded up to November 2026), read with the bag's own message
definition. Read only: nothing writes this format any more; :func:`decode_legacy` gives what
:func:`coop_slam.wire.codec.decode` gives for a message of today."""

from __future__ import annotations

import copy
import dataclasses
from typing import Callable

import numpy as np

from ..geometry import GeometryError
from .bow_signature import SignatureError, decode_counted_signature, decode_signature
from .codec import Decoded, Incomplete, WireError, camera_of, pose_of
from .encodings import (
    decode_depths,
    decode_map_point_ids,
    decode_point_offsets,
    decode_uv,
    moves_from_steps,
)
from .messages import KIND_DELTA, KIND_KEYFRAME
from .observations import complete_update, shared_descriptors
from .pack import PackError, Schema, field_array, unpack_fields
from .record import ACTION_NEW, ACTION_UPDATE, KeyframeError, KeyframeRecord, PlaceSignature

LEGACY_TYPE = "coop_slam/KeyFrame"
# The arrays a legacy message packed (its ``packed`` field), in stream order.
LEGACY_ARRAYS = Schema(
    1,
    "recorded KeyFrame message",
    (
        ("keypoints_uv", "<u2"),
        ("octaves", "u1"),
        ("depths_f16", "u1"),
        ("map_point_ids", "<u4"),
        ("map_point_id_codes", "u1"),
        ("patched", "<u4"),
        ("moved", "<u2"),
        ("moves_q", "<i2"),
        ("ref_keyframes", "<u4"),
        ("descriptor_refs", "u1"),
        ("covisible_ids", "<u4"),
        ("covisible_weights", "<u2"),
        ("bow_word_gaps", "u1"),
        ("bow_weights", "u1"),
        ("bow_counts", "u1"),
    ),
)


def is_legacy(msg) -> bool:
    """Whether ``msg`` is a recorded ``coop_slam/KeyFrame`` message."""
    return getattr(msg, "_type", "") == LEGACY_TYPE


def decode_legacy(
    msg, known_robots: set[int] | None = None, word_idf: np.ndarray | None = None
) -> Decoded:
    """What a recorded KeyFrame message says, as :func:`coop_slam.wire.codec.decode` says it;
    raises WireError."""
    msg = unpacked(msg)
    if not (getattr(msg, "delta", False) or len(getattr(msg, "descriptor_refs", ()))):
        return _keyframe_from_msg(msg, known_robots, None, word_idf)
    kind = KIND_DELTA if getattr(msg, "delta", False) else KIND_KEYFRAME
    return Incomplete(
        msg.robot_id,
        msg.map_segment,
        msg.keyframe_id,
        msg.header.stamp.to_sec(),
        kind,
        lambda stored: _keyframe_from_msg(msg, known_robots, stored, word_idf),
    )


def unpacked(msg):
    """A KeyFrame message with the arrays it packs (``packed``) in their own fields: a copy, or
    the message itself when it packs none; raises WireError."""
    blob = field_array(getattr(msg, "packed", b""))
    if not len(blob):
        return msg
    where = f"keyframe {msg.keyframe_id} of robot {msg.robot_id}"
    given = [name for name, _ in LEGACY_ARRAYS.fields if len(getattr(msg, name, ()))]
    if given:
        raise WireError(f"{where}: {', '.join(given)} given beside packed")
    try:
        arrays = unpack_fields(blob.tobytes(), LEGACY_ARRAYS)
    except PackError as exc:
        raise WireError(f"{where}: {exc}") from None
    out = copy.copy(msg)
    for name, values in arrays.items():
        setattr(out, name, values.tobytes() if values.dtype.itemsize == 1 else values.tolist())
    out.packed = b""
    return out


def keypoints_and_depths(msg, where: str) -> tuple[np.ndarray, np.ndarray]:
    """A KeyFrame message's keypoints (flat float32: u, v per keypoint, or u, v, size, angle)
    and depths [m], from whichever encoding it carries them in (packed too); raises
    KeyframeError or WireError."""
    msg = unpacked(msg)
    keypoints = np.asarray(msg.keypoints, np.float32)
    coded = np.asarray(getattr(msg, "keypoints_uv", ()), np.uint16)
    if len(coded):
        step = float(getattr(msg, "keypoint_step_px", 0.0))
        if keypoints.size:
            raise KeyframeError(f"{where}: keypoints and keypoints_uv are both given")
        if not (np.isfinite(step) and 0.0 < step <= 1.0):
            raise KeyframeError(f"{where}: keypoint_step_px {step!r} is not in (0, 1] px")
        if coded.size != 2 * len(msg.octaves):
            raise KeyframeError(
                f"{where}: keypoints_uv holds {coded.size} values for {len(msg.octaves)} octaves: "
                "2 per keypoint (u, v)"
            )
        keypoints = decode_uv(coded, step, offset_px=0.0).ravel()
    elif float(getattr(msg, "keypoint_step_px", 0.0)):
        raise KeyframeError(f"{where}: keypoint_step_px is given without keypoints_uv")
    depths = np.asarray(msg.depths_m, np.float32)
    half = field_array(getattr(msg, "depths_f16", b""))
    if len(half):
        if depths.size:
            raise KeyframeError(f"{where}: depths_m and depths_f16 are both given")
        depths = decode_depths(half.tobytes())
    return keypoints, depths


def _keyframe_from_msg(
    msg,
    known_robots: set[int] | None = None,
    stored: Callable[[int], KeyframeRecord | None] | None = None,
    word_idf: np.ndarray | None = None,
) -> KeyframeRecord | PlaceSignature:
    """Validated :class:`KeyframeRecord` from a KeyFrame message; raises WireError.
    ``stored(keyframe_id)`` gives a keyframe of the message's robot and map segment as the server
    holds it (None: not held): a delta update takes keypoints, octaves, descriptors and depths
    from the keyframe's own, and, when it carries a patch, the observations it leaves out; a
    message with ``descriptor_refs`` the descriptors it leaves out from the keyframes it names
    (see :func:`decode_legacy`). A message with ``signature_only`` gives a
    :class:`PlaceSignature` (``word_idf``: the vocabulary's ``word_weights``, which a signature
    of feature counts needs)."""
    try:
        where = f"keyframe {msg.keyframe_id} of robot {msg.robot_id}"
        cam = camera_of(msg.camera)
        static, ids, map_points = _arrays(msg, where)
        _take_shared_descriptors(msg, static, ids, stored, where)
        delta = bool(getattr(msg, "delta", False))
        base = _delta_base(msg, static, stored, where) if delta else None
        patched = np.asarray(getattr(msg, "patched", ()), np.int64)
        is_patch = delta and len(ids) == len(patched)
        if len(patched) and not is_patch:
            raise KeyframeError(
                f"{where}: patched lists {len(patched)} keypoints but map_point_ids has "
                f"{len(ids)} entries (a patch of a delta update has one per listed keypoint)"
            )
        rec = KeyframeRecord(
            robot_id=msg.robot_id,
            keyframe_id=msg.keyframe_id,
            stamp_s=msg.header.stamp.to_sec(),
            camera=cam,
            T_map_cam=pose_of(msg.pose, where),
            **static,
            map_point_ids=ids,
            map_points=map_points.reshape(-1, 3),
            covisible_ids=np.asarray(msg.covisible_ids, np.uint32),
            covisible_weights=np.asarray(msg.covisible_weights, np.uint16),
            map_segment=msg.map_segment,
            action=msg.action,
        )
        moves = _moves(msg, is_patch, where)
        offsets = field_array(getattr(msg, "map_point_offsets_f16", b""))
        if len(offsets):
            if delta:
                raise KeyframeError(f"{where}: only a full message carries map point offsets")
            points = decode_point_offsets(rec, offsets.tobytes(), rec.map_points)
            rec = dataclasses.replace(rec, map_points=points)
        if delta:
            rec = complete_update(rec, base, patched if is_patch else None, moves)
        if getattr(msg, "signature_only", False):
            if msg.action != ACTION_NEW or delta:
                raise KeyframeError(f"{where}: only a new keyframe goes as a place signature")
            return PlaceSignature(rec, _bow(msg, word_idf, where)).validate(known_robots)
        return rec.validate(known_robots)
    except (KeyframeError, GeometryError, SignatureError) as exc:
        raise WireError(str(exc)) from None


def _arrays(msg, where: str) -> tuple[dict, np.ndarray, np.ndarray]:
    """What the keyframe saw (keypoints, octaves, descriptors, depths), its map point ids and
    its map points, from whichever of the field pairs carries them."""
    keypoints, depths = keypoints_and_depths(msg, where)
    ids = np.asarray(msg.map_point_ids, np.uint32)
    codes = field_array(getattr(msg, "map_point_id_codes", b""))
    if len(codes):
        if len(ids):
            raise KeyframeError(f"{where}: map_point_ids and map_point_id_codes are both given")
        ids = decode_map_point_ids(codes.tobytes())
    descriptors = field_array(msg.descriptors)
    map_points = np.asarray(msg.map_points, np.float32)
    n = len(msg.octaves)
    if n and keypoints.size == 2 * n:  # u, v: size not given, no angle
        keypoints = np.column_stack(
            [keypoints.reshape(-1, 2), np.zeros(n, np.float32), np.full(n, -1, np.float32)]
        )
    elif keypoints.size % 4:
        raise KeyframeError(
            f"{where}: keypoints holds {keypoints.size} floats for {n} octaves: 2 per "
            "keypoint (u, v), or 4 (u, v, size, angle)"
        )
    if descriptors.size % 32:
        raise KeyframeError(
            f"{where}: descriptors hold {descriptors.size} bytes, not a multiple of 32"
        )
    if map_points.size % 3:
        raise KeyframeError(f"{where}: map_points holds {map_points.size} floats, not 3 per point")
    static = dict(
        keypoints=keypoints.reshape(-1, 4),
        octaves=field_array(msg.octaves),
        descriptors=descriptors.reshape(-1, 32),
        depths_m=depths,
    )
    return static, ids, map_points


def _take_shared_descriptors(msg, static: dict, ids, stored, where: str) -> None:
    """The descriptors a message took from keyframes the server holds, into ``static``."""
    refs = field_array(getattr(msg, "descriptor_refs", b""))
    if len(getattr(msg, "ref_keyframes", ())) and not len(refs):
        raise KeyframeError(f"{where}: ref_keyframes is given without descriptor_refs")
    if not len(refs):
        return
    if getattr(msg, "delta", False) or getattr(msg, "signature_only", False):
        raise KeyframeError(
            f"{where}: only a full message may refer to other keyframes' descriptors"
        )
    if stored is None:
        raise KeyframeError(
            f"{where}: refers to other keyframes' descriptors, but the keyframes the server holds "
            "are not given"
        )
    static["descriptors"] = shared_descriptors(
        ids,
        static["descriptors"],
        refs,
        np.asarray(getattr(msg, "ref_keyframes", ()), np.int64),
        stored,
        where,
    )


def _delta_base(msg, static: dict, stored, where: str) -> KeyframeRecord:
    """The stored keyframe a delta update completes."""
    if msg.action != ACTION_UPDATE:
        raise KeyframeError(f"{where}: only an update may leave out what it saw (delta)")
    if any(len(v) for v in static.values()):
        raise KeyframeError(f"{where}: a delta update carries no keypoints or descriptors")
    base = stored(msg.keyframe_id) if stored is not None else None
    if base is None:
        raise KeyframeError(f"{where}: a delta update of a keyframe the server does not hold")
    return base


def _moves(msg, is_patch: bool, where: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(moved keypoints, their (k, 3) moves [m]) of a delta update: int16 steps, or half floats
    (before the steps)."""
    moved = np.asarray(getattr(msg, "moved", ()), np.int64)
    steps = np.asarray(getattr(msg, "moves_q", ()), np.int16)
    half = field_array(getattr(msg, "moves_f16", b""))
    if len(steps) and len(half):
        raise KeyframeError(f"{where}: moves_q and moves_f16 are both given")
    if (len(steps) or len(half)) and not len(moved):
        raise KeyframeError(f"{where}: moves are given without moved")
    if not len(moved):
        return None
    if not is_patch:
        raise KeyframeError(f"{where}: only a delta update with a patch moves map points")
    if len(half):
        if len(half) != 6 * len(moved):
            raise KeyframeError(
                f"{where}: moves_f16 holds {len(half)} bytes for {len(moved)} moved keypoints "
                "(6 each)"
            )
        moves_m = np.frombuffer(half.tobytes(), "<f2").astype(np.float32)
    elif len(steps) != 3 * len(moved):
        raise KeyframeError(
            f"{where}: moves_q holds {len(steps)} values for {len(moved)} moved keypoints (3 each)"
        )
    else:
        moves_m = moves_from_steps(steps)
    return moved, moves_m.reshape(-1, 3)


def _bow(msg, word_idf, where: str):
    """A signature's BoW vector: feature counts (weighed with ``word_idf``) or 8-bit weights."""
    gaps = field_array(msg.bow_word_gaps)
    counts = field_array(getattr(msg, "bow_counts", b""))
    if not len(counts):
        weights = field_array(msg.bow_weights).tobytes()
        return decode_signature(gaps.tobytes(), weights, float(msg.bow_weight_max))
    if len(msg.bow_weights):
        raise KeyframeError(f"{where}: bow_weights and bow_counts are both given")
    if word_idf is None:
        raise KeyframeError(f"{where}: a signature of feature counts needs the server's vocabulary")
    return decode_counted_signature(gaps.tobytes(), counts.tobytes(), word_idf)
