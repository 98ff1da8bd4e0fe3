"""Keyframe records to keyframe messages and back: one encoder and one decoder per kind.

The client's uplink decides how a record goes (:class:`Outgoing`); :func:`encode` writes the
message of that kind. The server's intake calls :func:`decode`: a whole keyframe that names no
other keyframe and a place signature become a validated record at once; a delta update, and a
whole keyframe that takes descriptors from keyframes the server holds, become
:class:`Incomplete`, completed when the server takes them in order (the keyframes it refers to
as stored then). Every decoder raises :class:`WireError` naming what does not fit.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import numpy as np

from ..bow.vocabulary import BowVector
from ..camera import SENSORS, CameraModel
from ..errors import CoopSlamError
from ..geometry import GeometryError, quat_from_se3, se3_from_quat
from .bow_signature import (
    SignatureError,
    decode_counted_signature,
    decode_signature,
    encode_signature,
    encode_word_ids,
)
from .encodings import (
    decode_depths,
    decode_map_point_ids,
    decode_point_offsets,
    decode_uv,
    encode_depths,
    encode_map_point_ids,
    encode_point_offsets,
    encode_uv,
    move_steps,
    moves_from_steps,
)
from .messages import (
    KIND_DELTA,
    KIND_KEYFRAME,
    KIND_NAMES,
    KIND_REMOVAL,
    KIND_SIGNATURE,
    CameraModelMsg,
    Header,
    KeyframeDelta,
    KeyframeMessage,
    PlaceSignatureMsg,
    Point,
    Pose,
    Quaternion,
    Stamp,
    WholeKeyframe,
)
from .observations import complete_update, patch_of, shared_descriptors
from .pack import PackError, Schema, field_array, pack_fields, unpack_fields
from .record import (
    ACTION_NEW,
    ACTION_REMOVE,
    ACTION_UPDATE,
    KeyframeError,
    KeyframeRecord,
    PlaceSignature,
    camera_from_fields,
)


class WireError(CoopSlamError):
    """A keyframe message that cannot be encoded or decoded; the message says which field."""


# The integer arrays each kind packs (see coop_slam.wire.pack), with their element types.
WHOLE_ARRAYS = Schema(
    2,
    "whole keyframe",
    (
        ("keypoints_uv", "<u2"),
        ("octaves", "u1"),
        ("depths_f16", "u1"),
        ("map_point_id_codes", "u1"),
        ("ref_keyframes", "<u4"),
        ("descriptor_refs", "u1"),
        ("covisible_ids", "<u4"),
        ("covisible_weights", "<u2"),
    ),
)
DELTA_ARRAYS = Schema(
    3,
    "keyframe delta",
    (
        ("patched", "<u4"),
        ("map_point_ids", "<u4"),
        ("moved", "<u2"),
        ("moves_q", "<i2"),
        ("covisible_ids", "<u4"),
        ("covisible_weights", "<u2"),
    ),
)
SIGNATURE_ARRAYS = Schema(
    4,
    "place signature",
    (
        ("bow_word_gaps", "u1"),
        ("bow_counts", "u1"),
        ("bow_weights", "u1"),
        ("covisible_ids", "<u4"),
        ("covisible_weights", "<u2"),
    ),
)


class Outgoing(NamedTuple):
    """How the uplink sends a keyframe record: ``delta`` as an update without what the keyframe
    saw, with only the observations of the keypoints ``patched`` and the ``moves`` (keypoints
    whose map point only moved, and their (k, 3) moves [m] in steps of ``MOVE_STEP_M``);
    ``signature`` as its place signature; ``skip`` not at all; ``refs`` (a whole keyframe) the
    keyframes whose descriptors it takes and, per keypoint, which (0: its own travels; None: all
    travel)."""

    delta: bool
    patched: np.ndarray | None = None
    signature: bool = False
    skip: bool = False
    refs: tuple[np.ndarray, np.ndarray] | None = None
    moves: tuple[np.ndarray, np.ndarray] | None = None


WHOLE = Outgoing(False)


@dataclasses.dataclass
class Incomplete:
    """A decoded message the server completes from keyframes it holds when it takes it, in order:
    ``complete(stored)`` gives the validated record, ``stored(keyframe_id)`` being the robot's
    keyframe of ``map_segment`` as the server holds it then (None: not held); raises WireError."""

    robot_id: int
    map_segment: int
    keyframe_id: int
    stamp_s: float
    kind: int
    complete: Callable[[Callable[[int], KeyframeRecord | None]], KeyframeRecord]


Decoded = KeyframeRecord | PlaceSignature | Incomplete


# --- poses and cameras ----------------------------------------------------------------------------
def pose_fields(T: np.ndarray) -> Pose:
    t, q = quat_from_se3(T)
    return Pose(Point(*map(float, t)), Quaternion(*map(float, q)))


def pose_of(pose: Pose, where: str) -> np.ndarray:
    """The (4, 4) pose of a message's pose (a unit quaternion, a finite position)."""
    o, p = pose.orientation, pose.position
    q = np.array([o.x, o.y, o.z, o.w], float)
    if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise KeyframeError(f"{where}: pose orientation is not a unit quaternion")
    if not np.all(np.isfinite([p.x, p.y, p.z])):
        raise KeyframeError(f"{where}: pose position contains NaN or inf")
    try:
        return se3_from_quat([p.x, p.y, p.z], q)
    except GeometryError as exc:
        raise KeyframeError(f"{where}: {exc}") from None


def camera_fields(cam: CameraModel) -> CameraModelMsg:
    return CameraModelMsg(
        sensor_type=SENSORS.index(cam.sensor),
        width=cam.width,
        height=cam.height,
        fx=cam.fx,
        fy=cam.fy,
        cx=cam.cx,
        cy=cam.cy,
        baseline_m=cam.baseline_m,
    )


def camera_of(msg: CameraModelMsg) -> CameraModel:
    if msg.sensor_type >= len(SENSORS):
        raise KeyframeError(f"camera sensor_type {msg.sensor_type} unknown")
    return camera_from_fields(
        width=msg.width,
        height=msg.height,
        fx=msg.fx,
        fy=msg.fy,
        cx=msg.cx,
        cy=msg.cy,
        sensor=SENSORS[msg.sensor_type],
        baseline_m=msg.baseline_m,
    )


# --- encoders -------------------------------------------------------------------------------------
def encode(
    item: KeyframeRecord | PlaceSignature,
    out: Outgoing = WHOLE,
    frame_id: str = "",
) -> KeyframeMessage:
    """The message of ``item`` sent as ``out`` says (``session`` and ``sequence`` are the
    outbox's to set); raises WireError for a record that has no message of that kind."""
    rec = item.record if isinstance(item, PlaceSignature) else item
    msg = KeyframeMessage(
        header=Header(stamp=Stamp.from_sec(rec.stamp_s), frame_id=frame_id),
        robot_id=rec.robot_id,
        keyframe_id=rec.keyframe_id,
        map_segment=rec.map_segment,
    )
    where = f"keyframe {rec.keyframe_id} of robot {rec.robot_id}"
    try:
        if isinstance(item, PlaceSignature):
            msg.kind, msg.signature = KIND_SIGNATURE, [encode_signature_msg(item)]
        elif rec.action == ACTION_REMOVE:
            msg.kind, msg.header.stamp = KIND_REMOVAL, Stamp()
        elif out.delta:
            if rec.action != ACTION_UPDATE or out.patched is None:
                raise KeyframeError("only an update with a patch goes as a delta")
            msg.kind, msg.delta = KIND_DELTA, [encode_delta(rec, out.patched, out.moves)]
        else:
            msg.kind, msg.keyframe = KIND_KEYFRAME, [encode_whole(rec, out.refs)]
    except (KeyframeError, PackError, GeometryError) as exc:
        raise WireError(f"{where}: {exc}") from None
    return msg


def encode_whole(
    rec: KeyframeRecord, refs: tuple[np.ndarray, np.ndarray] | None = None
) -> WholeKeyframe:
    """A whole keyframe: keypoints in uint16 steps, depths as half floats, map point ids as
    varint steps, map points as half-float offsets from where their keypoint's depth puts them
    (where that is shorter), and the descriptors the server does not take from ``refs``."""
    cam = rec.camera
    code, step = encode_uv(rec.uv_px, cam.width, cam.height)
    depths = encode_depths(rec.depths_m)
    out = WholeKeyframe(
        replaces=rec.action == ACTION_UPDATE,
        camera=camera_fields(cam),
        pose=pose_fields(rec.T_map_cam),
        keypoint_step_px=step,
    )
    descriptors = np.asarray(rec.descriptors, np.uint8)
    arrays = {
        "keypoints_uv": code.ravel(),
        "octaves": np.asarray(rec.octaves, np.uint8),
        "depths_f16": np.frombuffer(depths, np.uint8),
        "map_point_id_codes": np.frombuffer(encode_map_point_ids(rec.map_point_ids), np.uint8),
        "covisible_ids": np.asarray(rec.covisible_ids, np.uint32),
        "covisible_weights": np.asarray(rec.covisible_weights, np.uint16),
    }
    if refs is not None:
        arrays["ref_keyframes"] = np.asarray(refs[0], np.uint32)
        arrays["descriptor_refs"] = np.asarray(refs[1], np.uint8)
        descriptors = descriptors[np.asarray(refs[1]) == 0]
    out.descriptors = descriptors.tobytes()
    points = np.asarray(rec.map_points, np.float32)
    # The offsets are taken from the keyframe as the server decodes it (its keypoints in
    # float64 here, float32 there: tens of micrometres apart at most, below the offsets' step).
    as_decoded = dataclasses.replace(
        rec,
        keypoints=_keypoints(decode_uv(code, step)).astype(np.float64),
        depths_m=decode_depths(depths),
        T_map_cam=pose_of(out.pose, "pose"),
    )
    offsets = encode_point_offsets(as_decoded)
    if offsets is not None:
        out.map_point_offsets_f16, points = offsets
    out.map_points = points.ravel().tolist()
    out.packed = pack_fields(arrays, WHOLE_ARRAYS)
    out.depth_image = np.asarray(rec.depth_image, np.uint8).tobytes()  # compressed already
    return out


def encode_delta(
    rec: KeyframeRecord,
    patched: np.ndarray,
    moves: tuple[np.ndarray, np.ndarray] | None = None,
) -> KeyframeDelta:
    """An update of a keyframe the server holds: its pose, the observations of the keypoints
    ``patched`` (map point ids, 0 = none now, and the points of the others) and the ``moves`` of
    map points that only moved (keypoints, (k, 3) moves [m])."""
    ids, points = patch_of(rec, patched)
    arrays = {
        "patched": np.asarray(patched, np.uint32),
        "map_point_ids": ids,
        "covisible_ids": np.asarray(rec.covisible_ids, np.uint32),
        "covisible_weights": np.asarray(rec.covisible_weights, np.uint16),
    }
    if moves is not None:
        arrays["moved"] = np.asarray(moves[0], np.uint16)
        arrays["moves_q"] = move_steps(moves[1]).ravel()
    return KeyframeDelta(
        pose=pose_fields(rec.T_map_cam),
        map_points=np.asarray(points, np.float32).ravel().tolist(),
        packed=pack_fields(arrays, DELTA_ARRAYS),
    )


def encode_signature_msg(sig: PlaceSignature) -> PlaceSignatureMsg:
    """A new keyframe's place signature: its BoW word ids and the features on each word (or, for
    a vector counts do not give, 8-bit weights of the largest)."""
    rec = sig.record
    out = PlaceSignatureMsg(camera=camera_fields(rec.camera), pose=pose_fields(rec.T_map_cam))
    arrays = {
        "covisible_ids": np.asarray(rec.covisible_ids, np.uint32),
        "covisible_weights": np.asarray(rec.covisible_weights, np.uint16),
    }
    if sig.counts is not None:
        if len(sig.counts) != len(sig.bow):
            raise KeyframeError(f"{len(sig.counts)} feature counts for {len(sig.bow)} words")
        arrays["bow_word_gaps"] = np.frombuffer(encode_word_ids(sig.bow), np.uint8)
        arrays["bow_counts"] = np.asarray(sig.counts, np.uint8)
    else:
        gaps, weights, out.bow_weight_max = encode_signature(sig.bow)
        arrays["bow_word_gaps"] = np.frombuffer(gaps, np.uint8)
        arrays["bow_weights"] = np.frombuffer(weights, np.uint8)
    out.packed = pack_fields(arrays, SIGNATURE_ARRAYS)
    return out


def _keypoints(uv_px: np.ndarray) -> np.ndarray:
    """(N, 4) keypoints of positions alone: size 0 (not given), angle -1 (none)."""
    n = len(uv_px)
    return np.column_stack(
        [uv_px.reshape(-1, 2), np.zeros(n, np.float32), np.full(n, -1, np.float32)]
    ).astype(np.float32)


# --- decoders -------------------------------------------------------------------------------------
def decode(
    msg: KeyframeMessage,
    known_robots: set[int] | None = None,
    word_idf: np.ndarray | None = None,
) -> Decoded:
    """What a keyframe message says: a validated record (a whole keyframe, a removal), a
    :class:`PlaceSignature` (``word_idf``: the vocabulary's word weights, which a signature of
    feature counts needs), or an :class:`Incomplete` message; raises WireError."""
    where = f"keyframe {msg.keyframe_id} of robot {msg.robot_id}"
    try:
        if msg.kind not in KIND_NAMES:
            raise KeyframeError(f"unknown message kind {msg.kind}")
        payloads = {
            KIND_KEYFRAME: msg.keyframe,
            KIND_DELTA: msg.delta,
            KIND_SIGNATURE: msg.signature,
        }
        for kind, payload in payloads.items():
            if len(payload) != (kind == msg.kind):
                raise KeyframeError(
                    f"a {msg.kind_name} message holds {len(payload)} {_NAMES[kind]} payloads"
                )
        base = KeyframeRecord(
            robot_id=msg.robot_id,
            keyframe_id=msg.keyframe_id,
            stamp_s=msg.header.stamp.to_sec(),
            camera=None,
            T_map_cam=np.eye(4),
            map_segment=msg.map_segment,
        )
        if msg.kind == KIND_REMOVAL:
            return dataclasses.replace(base, action=ACTION_REMOVE).validate(known_robots)
        if msg.kind == KIND_KEYFRAME:
            return decode_whole(base, msg.keyframe[0], known_robots, where)
        if msg.kind == KIND_DELTA:
            return decode_delta(base, msg.delta[0], known_robots, where)
        return decode_signature_msg(base, msg.signature[0], known_robots, word_idf, where)
    except (KeyframeError, PackError, SignatureError, GeometryError) as exc:
        raise WireError(str(exc) if str(exc).startswith(where) else f"{where}: {exc}") from None


_NAMES = {KIND_KEYFRAME: "keyframe", KIND_DELTA: "delta", KIND_SIGNATURE: "signature"}


def _unpacked(packed, schema: Schema) -> dict[str, np.ndarray]:
    return unpack_fields(field_array(packed).tobytes(), schema)


def _covisible(arrays: dict) -> dict:
    return dict(
        covisible_ids=np.asarray(arrays["covisible_ids"], np.uint32),
        covisible_weights=np.asarray(arrays["covisible_weights"], np.uint16),
    )


def keypoints_and_depths(body: WholeKeyframe) -> tuple[np.ndarray, np.ndarray]:
    """A whole keyframe's (N, 2) keypoint positions [px] and depths [m] alone (what a recorded
    run's report back-projects); raises WireError."""
    try:
        arrays = _unpacked(body.packed, WHOLE_ARRAYS)
        uv = decode_uv(arrays["keypoints_uv"], float(body.keypoint_step_px))
        depths = decode_depths(arrays["depths_f16"].tobytes())
    except (KeyframeError, PackError) as exc:
        raise WireError(str(exc)) from None
    if len(uv) != len(depths):
        raise WireError(f"{len(uv)} keypoints and {len(depths)} depths")
    return uv, depths


def decode_whole(
    base: KeyframeRecord, body: WholeKeyframe, known_robots, where: str
) -> KeyframeRecord | Incomplete:
    arrays = _unpacked(body.packed, WHOLE_ARRAYS)
    n = len(arrays["octaves"])
    step = float(body.keypoint_step_px)
    if not (np.isfinite(step) and 0.0 < step <= 1.0):
        raise KeyframeError(f"keypoint_step_px {step!r} is not in (0, 1] px")
    if len(arrays["keypoints_uv"]) != 2 * n:
        raise KeyframeError(
            f"keypoints_uv holds {len(arrays['keypoints_uv'])} values for {n} octaves: 2 per "
            "keypoint (u, v)"
        )
    descriptors = field_array(body.descriptors)
    if descriptors.size % 32:
        raise KeyframeError(f"descriptors hold {descriptors.size} bytes, not a multiple of 32")
    map_points = np.asarray(body.map_points, np.float32)
    if map_points.size % 3:
        raise KeyframeError(f"map_points holds {map_points.size} floats, not 3 per point")
    rec = dataclasses.replace(
        base,
        camera=camera_of(body.camera),
        T_map_cam=pose_of(body.pose, where),
        keypoints=_keypoints(decode_uv(arrays["keypoints_uv"], step)),
        octaves=np.array(arrays["octaves"], np.uint8),
        descriptors=descriptors.reshape(-1, 32),
        depths_m=decode_depths(arrays["depths_f16"].tobytes()),
        map_point_ids=decode_map_point_ids(arrays["map_point_id_codes"].tobytes()),
        map_points=map_points.reshape(-1, 3),
        action=ACTION_UPDATE if body.replaces else ACTION_NEW,
        depth_image=field_array(body.depth_image).astype(np.uint8, copy=True),
        **_covisible(arrays),
    )
    offsets = field_array(body.map_point_offsets_f16)
    if len(offsets):
        rec.map_points = decode_point_offsets(rec, offsets.tobytes(), rec.map_points)
    refs, ref_keyframes = arrays["descriptor_refs"], arrays["ref_keyframes"]
    if len(ref_keyframes) and not len(refs):
        raise KeyframeError("ref_keyframes is given without descriptor_refs")
    if not len(refs):
        return rec.validate(known_robots)

    def complete(stored) -> KeyframeRecord:
        try:
            descriptors = shared_descriptors(
                rec.map_point_ids, rec.descriptors, refs, ref_keyframes, stored, where
            )
            return dataclasses.replace(rec, descriptors=descriptors).validate(known_robots)
        except KeyframeError as exc:
            raise WireError(str(exc)) from None

    return Incomplete(
        rec.robot_id, rec.map_segment, rec.keyframe_id, rec.stamp_s, KIND_KEYFRAME, complete
    )


def decode_delta(base: KeyframeRecord, body: KeyframeDelta, known_robots, where: str) -> Incomplete:
    arrays = _unpacked(body.packed, DELTA_ARRAYS)
    patched = np.asarray(arrays["patched"], np.int64)
    ids = np.asarray(arrays["map_point_ids"], np.uint32)
    if len(ids) != len(patched):
        raise KeyframeError(
            f"patched lists {len(patched)} keypoints but map_point_ids has {len(ids)} entries"
        )
    map_points = np.asarray(body.map_points, np.float32)
    if map_points.size % 3:
        raise KeyframeError(f"map_points holds {map_points.size} floats, not 3 per point")
    moved, steps = np.asarray(arrays["moved"], np.int64), arrays["moves_q"]
    if len(steps) != 3 * len(moved):
        raise KeyframeError(
            f"moves_q holds {len(steps)} values for {len(moved)} moved keypoints (3 each)"
        )
    moves = (moved, moves_from_steps(steps).reshape(-1, 3)) if len(moved) else None
    sent = dataclasses.replace(
        base,
        T_map_cam=pose_of(body.pose, where),
        map_point_ids=ids,
        map_points=map_points.reshape(-1, 3),
        action=ACTION_UPDATE,
        **_covisible(arrays),
    )

    def complete(stored) -> KeyframeRecord:
        held = stored(sent.keyframe_id)
        if held is None:
            raise WireError(f"{where}: a delta update of a keyframe the server does not hold")
        try:
            rec = dataclasses.replace(sent, camera=held.camera)
            return complete_update(rec, held, patched, moves).validate(known_robots)
        except KeyframeError as exc:
            raise WireError(str(exc) if str(exc).startswith(where) else f"{where}: {exc}") from None

    return Incomplete(
        sent.robot_id, sent.map_segment, sent.keyframe_id, sent.stamp_s, KIND_DELTA, complete
    )


def decode_signature_msg(
    base: KeyframeRecord, body: PlaceSignatureMsg, known_robots, word_idf, where: str
) -> PlaceSignature:
    arrays = _unpacked(body.packed, SIGNATURE_ARRAYS)
    gaps, counts, weights = (
        arrays[k].tobytes() for k in ("bow_word_gaps", "bow_counts", "bow_weights")
    )
    if counts and weights:
        raise KeyframeError("bow_weights and bow_counts are both given")
    if counts:
        if word_idf is None:
            raise KeyframeError("a signature of feature counts needs the server's vocabulary")
        bow = decode_counted_signature(gaps, counts, word_idf)
    else:
        bow = decode_signature(gaps, weights, float(body.bow_weight_max))
    rec = dataclasses.replace(
        base,
        camera=camera_of(body.camera),
        T_map_cam=pose_of(body.pose, where),
        action=ACTION_NEW,
        **_covisible(arrays),
    )
    return PlaceSignature(rec, bow).validate(known_robots)


def signature_bow(gaps: bytes, weights: bytes, weight_max: float) -> BowVector:
    """A BoW vector sent as word-id gaps and 8-bit weights (a relocalization request)."""
    try:
        return decode_signature(gaps, weights, weight_max)
    except SignatureError as exc:
        raise WireError(str(exc)) from None
