"""Conversion between ROS messages and the pure core's numpy types.

Images are converted without cv_bridge (numpy views of the message buffer). Every ``*_from_msg``
function validates what it reads and raises :class:`MessageError` with a message naming the field.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Callable

import numpy as np
import rospy
from geometry_msgs.msg import Pose, Transform
from sensor_msgs.msg import CameraInfo, Image

from ..bow.signature import (
    SignatureError,
    decode_counted_signature,
    decode_signature,
    encode_signature,
    encode_word_ids,
)
from ..datasets.base import SENSORS, CameraModel, DatasetError
from ..errors import CoopSlamError
from ..field_pack import PACKED_FIELDS, PackError, field_array, pack_fields, unpack_fields
from ..geometry import GeometryError, quat_from_se3, se3_from_quat
from ..keyframe_record import (
    ACTION_NEW,
    ACTION_UPDATE,
    MAX_POSITION_M,
    KeyframeError,
    KeyframeRecord,
    PlaceSignature,
    camera_from_fields,
    complete_update,
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
    patch_of,
    shared_descriptors,
)


class MessageError(CoopSlamError):
    """An incoming ROS message is malformed (wrong sizes, NaN, unknown encoding, ...)."""


# --- poses ----------------------------------------------------------------------------------------
def pose_to_msg(T: np.ndarray) -> Pose:
    t, q = quat_from_se3(T)
    msg = Pose()
    msg.position.x, msg.position.y, msg.position.z = map(float, t)
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = map(float, q)
    return msg


def pose_from_msg(msg: Pose, name: str = "pose") -> np.ndarray:
    p, o = msg.position, msg.orientation
    try:
        T = se3_from_quat([p.x, p.y, p.z], [o.x, o.y, o.z, o.w])
    except GeometryError as exc:
        raise MessageError(f"{name}: {exc}") from None
    return _finite_pose(T, name)


def _finite_pose(T: np.ndarray, name: str) -> np.ndarray:
    if not np.all(np.isfinite(T)):
        raise MessageError(f"{name} contains NaN or inf")
    # Finite yet absurd (a correction placing a keyframe 1e300 m away would move the client's
    # published pose there): every pose and transform between map frames lies within a map.
    far = float(np.abs(T[:3, 3]).max())
    if far > MAX_POSITION_M:
        raise MessageError(
            f"{name} position {far:.3g} m is beyond the {MAX_POSITION_M:g} m any map spans"
        )
    return T


def transform_to_msg(T: np.ndarray) -> Transform:
    t, q = quat_from_se3(T)
    msg = Transform()
    msg.translation.x, msg.translation.y, msg.translation.z = map(float, t)
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = map(float, q)
    return msg


def transform_from_msg(msg: Transform, name: str = "transform") -> np.ndarray:
    t, r = msg.translation, msg.rotation
    try:
        return _finite_pose(se3_from_quat([t.x, t.y, t.z], [r.x, r.y, r.z, r.w]), name)
    except GeometryError as exc:
        raise MessageError(f"{name}: {exc}") from None


# --- images ---------------------------------------------------------------------------------------
_ENCODINGS = {
    "bgr8": (np.uint8, 3),
    "rgb8": (np.uint8, 3),
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "16UC1": (np.uint16, 1),
    "mono16": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}


def image_to_msg(img: np.ndarray, encoding: str, stamp=None, frame_id: str = "") -> Image:
    dtype, channels = _ENCODINGS[encoding]
    img = np.ascontiguousarray(img, dtype=dtype)
    msg = Image()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = img.shape[:2]
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = msg.width * channels * np.dtype(dtype).itemsize
    msg.data = img.tobytes()
    return msg


def image_from_msg(msg: Image) -> np.ndarray:
    """numpy view of an image message (BGR for colour); raises MessageError when malformed."""
    if msg.encoding not in _ENCODINGS:
        raise MessageError(
            f"image encoding '{msg.encoding}' unsupported; use one of {sorted(_ENCODINGS)}"
        )
    if msg.width == 0 or msg.height == 0:
        raise MessageError(f"image is empty ({msg.width}x{msg.height})")
    dtype, channels = _ENCODINGS[msg.encoding]
    itemsize = np.dtype(dtype).itemsize
    row = msg.width * channels * itemsize
    if msg.step < row or len(msg.data) < msg.step * msg.height:
        raise MessageError(
            f"image data holds {len(msg.data)} bytes, expected {msg.step * msg.height} "
            f"({msg.width}x{msg.height} {msg.encoding}, step {msg.step})"
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8, count=msg.step * msg.height).reshape(
        msg.height, msg.step
    )
    img = buf[:, :row].copy().view(dtype)
    if msg.is_bigendian and itemsize > 1:
        img = img.byteswap()
    img = (
        img.reshape(msg.height, msg.width, channels)
        if channels > 1
        else img.reshape(msg.height, msg.width)
    )
    if msg.encoding == "rgb8":
        img = img[:, :, ::-1].copy()
    return img


def depth_from_msg(msg: Image, depth_scale: float = 1000.0) -> np.ndarray:
    """Depth in metres (float32, 0 = none) from a 16UC1 (``depth_scale`` units per metre, REP-118:
    millimetres) or 32FC1 (metres) image."""
    img = image_from_msg(msg)
    if img.dtype == np.uint16:
        return img.astype(np.float32) / np.float32(depth_scale)
    if img.dtype != np.float32:
        raise MessageError(f"depth image encoding '{msg.encoding}' is not 16UC1 or 32FC1")
    depth = img.astype(np.float32, copy=True)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


# --- camera ---------------------------------------------------------------------------------------
def camera_info_to_msg(
    camera: CameraModel, stamp=None, frame_id: str = "", right: bool = False
) -> CameraInfo:
    """The rectified camera; ``right``: the right camera of a stereo pair (P[3] = -fx * b)."""
    msg = CameraInfo()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = camera.width, camera.height
    msg.distortion_model = "plumb_bob"
    msg.D = [0.0] * 5
    msg.K = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    msg.R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    Tx = -camera.fx * camera.baseline_m if right else 0.0  # ROS convention for the right camera
    msg.P = [camera.fx, 0.0, camera.cx, Tx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def stereo_camera_from_infos(left: CameraInfo, right: CameraInfo) -> CameraModel:
    """The stereo camera of a rectified pair's camera infos: the left camera's intrinsics, the
    baseline from the right camera's projection matrix (P[3] = -fx * baseline)."""
    P = list(right.P)
    if len(P) != 12 or not np.all(np.isfinite(P)) or P[0] <= 0:
        raise MessageError("right camera_info P must hold 12 finite numbers with fx > 0")
    if (left.width, left.height) != (right.width, right.height):
        raise MessageError(
            f"left and right camera_info differ in size: {left.width}x{left.height} and "
            f"{right.width}x{right.height}"
        )
    baseline_m = -P[3] / P[0]
    if baseline_m <= 0:
        raise MessageError(
            f"right camera_info gives baseline {baseline_m:.4f} m (P[3] = {P[3]:.3f}); a "
            "rectified right camera has P[3] = -fx * baseline < 0: are left and right swapped, "
            "or is it the left camera's info?"
        )
    return camera_from_info(left, sensor="stereo", baseline_m=baseline_m)


def camera_from_info(
    msg: CameraInfo, sensor: str = "rgbd", depth_scale: float = 1000.0, baseline_m: float = 0.0
) -> CameraModel:
    K = list(msg.K)
    if len(K) != 9 or not np.all(np.isfinite(K)):
        raise MessageError("camera_info K must hold 9 finite numbers")
    try:
        return CameraModel(
            width=msg.width,
            height=msg.height,
            fx=K[0],
            fy=K[4],
            cx=K[2],
            cy=K[5],
            sensor=sensor,
            depth_scale=depth_scale,
            baseline_m=baseline_m,
        )
    except DatasetError as exc:
        raise MessageError(f"camera_info: {exc}") from None


# --- keyframes ------------------------------------------------------------------------------------
def keyframe_to_msg(
    kf: KeyframeRecord | PlaceSignature,
    frame_id: str,
    delta: bool = False,
    patched: np.ndarray | None = None,
    refs: tuple[np.ndarray, np.ndarray] | None = None,
    compact: bool = True,
    moves: tuple[np.ndarray, np.ndarray] | None = None,
):
    """The KeyFrame message of a record; ``delta`` (an update): without keypoints, octaves,
    descriptors and depths, which the server has from the keyframe's first message, and with
    ``patched`` (not None) only those keypoints' observations. ``refs`` (a full message): the
    keyframes the server holds and, per keypoint, the one whose descriptor it takes (0: the
    descriptor travels; see :class:`coop_slam.vo.outbox.Outgoing`). ``compact``: keypoint
    positions and depths in their compact encodings (``keypoints_uv``, ``depths_f16``) where they
    fit, map point ids as varints (not in a patch), map points as half-float offsets from their
    keypoints' depths (a full message, where they fit), and the integer arrays packed into one
    zlib stream (``packed``) where that is smaller. ``moves`` (a delta update with a patch):
    keypoints whose map point moved, and the moves [m] (``moves_q``: steps of ``MOVE_STEP_M``).
    A place signature goes as a new keyframe with only its BoW vector (``signature_only``: its
    feature counts when the signature has them, else 8-bit weights)."""
    from coop_slam.msg import CameraModel as CameraModelMsg
    from coop_slam.msg import KeyFrame

    signature = None
    if isinstance(kf, PlaceSignature):
        signature, kf = kf, kf.record
    msg = KeyFrame()
    msg.header.stamp = rospy.Time.from_sec(kf.stamp_s)
    msg.header.frame_id = frame_id
    msg.robot_id = kf.robot_id
    msg.keyframe_id = kf.keyframe_id
    msg.map_segment = kf.map_segment
    msg.action = kf.action
    cam = kf.camera
    msg.camera = CameraModelMsg(
        sensor_type=SENSORS.index(cam.sensor),
        width=cam.width,
        height=cam.height,
        fx=cam.fx,
        fy=cam.fy,
        cx=cam.cx,
        cy=cam.cy,
        baseline_m=cam.baseline_m,
    )
    msg.pose = pose_to_msg(kf.T_map_cam)
    msg.delta = bool(delta)
    ids, points = np.asarray(kf.map_point_ids, np.uint32), np.asarray(kf.map_points, np.float32)
    if signature is not None:
        msg.signature_only = True
        if signature.counts is not None:
            if len(signature.counts) != len(signature.bow):
                raise KeyframeError(
                    f"keyframe {kf.keyframe_id}: {len(signature.counts)} feature counts for "
                    f"{len(signature.bow)} words"
                )
            msg.bow_word_gaps = encode_word_ids(signature.bow)
            msg.bow_counts = np.asarray(signature.counts, np.uint8).tobytes()
        else:
            gaps, weights, weight_max = encode_signature(signature.bow)
            msg.bow_word_gaps, msg.bow_weights = gaps, weights
            msg.bow_weight_max = weight_max
    elif not delta:
        uv = np.asarray(kf.uv_px, np.float32)
        # (a removal, or a keyframe without keypoints, has none to encode)
        coded = encode_uv(uv, cam.width, cam.height) if compact and len(uv) else None
        if coded is None:
            msg.keypoints = uv.ravel().tolist()
        else:
            msg.keypoints_uv, msg.keypoint_step_px = coded[0].ravel().tolist(), coded[1]
        msg.octaves = np.asarray(kf.octaves, np.uint8).tobytes()
        descriptors = np.asarray(kf.descriptors, np.uint8)
        if refs is not None:
            msg.ref_keyframes = np.asarray(refs[0], np.uint32).tolist()
            msg.descriptor_refs = np.asarray(refs[1], np.uint8).tobytes()
            descriptors = descriptors[np.asarray(refs[1]) == 0]
        msg.descriptors = descriptors.tobytes()
        depths = encode_depths(kf.depths_m) if compact else None
        if depths is None:
            msg.depths_m = np.asarray(kf.depths_m, np.float32).tolist()
        else:
            msg.depths_f16 = depths
        offsets = encode_point_offsets(_as_decoded(kf, msg)) if compact else None
        if offsets is not None:
            msg.map_point_offsets_f16, points = offsets
    if delta and patched is not None:
        ids, points = patch_of(kf, patched)
        msg.patched = np.asarray(patched, np.uint32).tolist()
        if moves is not None:
            msg.moved = np.asarray(moves[0], np.uint16).tolist()
            msg.moves_q = move_steps(moves[1]).ravel().tolist()
    if compact and not (delta and patched is not None):
        msg.map_point_id_codes = encode_map_point_ids(ids)
    else:
        msg.map_point_ids = ids.tolist()
    msg.map_points = np.asarray(points, np.float32).ravel().tolist()
    msg.covisible_ids = np.asarray(kf.covisible_ids, np.uint32).tolist()
    msg.covisible_weights = np.asarray(kf.covisible_weights, np.uint16).tolist()
    if compact:
        _pack(msg)
    return msg


def _pack(msg) -> None:
    """Moves the message's integer arrays into ``packed`` where that makes it smaller."""
    arrays = {name: getattr(msg, name) for name, _ in PACKED_FIELDS}
    plain = sum(
        len(v) * np.dtype(dtype).itemsize for (_, dtype), v in zip(PACKED_FIELDS, arrays.values())
    )
    if not plain:
        return
    blob = pack_fields(arrays)
    if len(blob) < plain:
        msg.packed = blob
        for name, dtype in PACKED_FIELDS:
            setattr(msg, name, b"" if np.dtype(dtype).itemsize == 1 else [])


def unpacked(msg):
    """A KeyFrame message with the arrays it packs (``packed``) in their own fields: a copy, or
    the message itself when it packs none; raises MessageError."""
    blob = field_array(getattr(msg, "packed", b""))
    if not len(blob):
        return msg
    where = f"keyframe {msg.keyframe_id} of robot {msg.robot_id}"
    given = [name for name, _ in PACKED_FIELDS if len(getattr(msg, name, ()))]
    if given:
        raise MessageError(f"{where}: {', '.join(given)} given beside packed")
    try:
        arrays = unpack_fields(blob.tobytes())
    except PackError as exc:
        raise MessageError(f"{where}: {exc}") from None
    out = copy.copy(msg)
    for name, values in arrays.items():
        setattr(out, name, values.tobytes() if values.dtype.itemsize == 1 else values.tolist())
    out.packed = b""
    return out


def _as_decoded(kf: KeyframeRecord, msg) -> KeyframeRecord:
    """``kf`` with its keypoints, depths and pose as the server decodes them from ``msg`` (which
    :func:`keyframe_to_msg` wrote: u, v per keypoint)."""
    flat, depths = keypoints_and_depths(msg, "keyframe")
    uv = flat.reshape(-1, 2)
    keypoints = np.column_stack([uv, np.zeros(len(uv)), np.full(len(uv), -1.0)])
    return dataclasses.replace(
        kf, keypoints=keypoints, depths_m=depths, T_map_cam=pose_from_msg(msg.pose)
    )


def keypoints_and_depths(msg, where: str) -> tuple[np.ndarray, np.ndarray]:
    """A KeyFrame message's keypoints (flat float32: u, v per keypoint, or u, v, size, angle)
    and depths [m], from whichever encoding it carries them in (packed too); raises
    KeyframeError or MessageError."""
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
        keypoints = decode_uv(coded, step).ravel()
    elif float(getattr(msg, "keypoint_step_px", 0.0)):
        raise KeyframeError(f"{where}: keypoint_step_px is given without keypoints_uv")
    depths = np.asarray(msg.depths_m, np.float32)
    half = field_array(getattr(msg, "depths_f16", b""))
    if len(half):
        if depths.size:
            raise KeyframeError(f"{where}: depths_m and depths_f16 are both given")
        depths = decode_depths(half.tobytes())
    return keypoints, depths


def needs_stored(msg) -> bool:
    """Whether a KeyFrame message is completed from keyframes the server holds (a delta update,
    or descriptors taken from other keyframes): when the server takes it, in order, not when it
    arrives. Raises MessageError for arrays packed wrong."""
    msg = unpacked(msg)
    return bool(getattr(msg, "delta", False)) or len(getattr(msg, "descriptor_refs", ())) > 0


def keyframe_from_msg(
    msg,
    known_robots: set[int] | None = None,
    stored: Callable[[int], KeyframeRecord | None] | None = None,
    word_idf: np.ndarray | None = None,
) -> KeyframeRecord | PlaceSignature:
    """Validated :class:`KeyframeRecord` from a KeyFrame message; raises MessageError.
    ``stored(keyframe_id)`` gives a keyframe of the message's robot and map segment as the server
    holds it (None: not held): a delta update takes keypoints, octaves, descriptors and depths
    from the keyframe's own, and, when it carries a patch, the observations it leaves out; a
    message with ``descriptor_refs`` the descriptors it leaves out from the keyframes it names
    (see :func:`needs_stored`). A message with ``signature_only`` gives a
    :class:`PlaceSignature` (``word_idf``: the vocabulary's ``word_weights``, which a signature
    of feature counts needs)."""
    msg = unpacked(msg)
    try:
        if msg.camera.sensor_type >= len(SENSORS):
            raise KeyframeError(f"camera sensor_type {msg.camera.sensor_type} unknown")
        cam = camera_from_fields(
            width=msg.camera.width,
            height=msg.camera.height,
            fx=msg.camera.fx,
            fy=msg.camera.fy,
            cx=msg.camera.cx,
            cy=msg.camera.cy,
            sensor=SENSORS[msg.camera.sensor_type],
            baseline_m=msg.camera.baseline_m,
        )
        where = f"keyframe {msg.keyframe_id} of robot {msg.robot_id}"
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
            raise KeyframeError(
                f"{where}: map_points holds {map_points.size} floats, not 3 per point"
            )
        o = msg.pose.orientation
        q = np.array([o.x, o.y, o.z, o.w])
        if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise KeyframeError(f"{where}: pose orientation is not a unit quaternion")
        p = msg.pose.position
        if not np.all(np.isfinite([p.x, p.y, p.z])):
            raise KeyframeError(f"{where}: pose position contains NaN or inf")
        static = dict(
            keypoints=keypoints.reshape(-1, 4),
            octaves=field_array(msg.octaves),
            descriptors=descriptors.reshape(-1, 32),
            depths_m=depths,
        )
        refs = field_array(getattr(msg, "descriptor_refs", b""))
        if len(getattr(msg, "ref_keyframes", ())) and not len(refs):
            raise KeyframeError(f"{where}: ref_keyframes is given without descriptor_refs")
        if len(refs):
            if getattr(msg, "delta", False) or getattr(msg, "signature_only", False):
                raise KeyframeError(
                    f"{where}: only a full message may refer to other keyframes' descriptors"
                )
            if stored is None:
                raise KeyframeError(
                    f"{where}: refers to other keyframes' descriptors, but the keyframes the "
                    "server holds are not given"
                )
            static["descriptors"] = shared_descriptors(
                ids,
                static["descriptors"],
                refs,
                np.asarray(getattr(msg, "ref_keyframes", ()), np.int64),
                stored,
                where,
            )
        base = None
        if getattr(msg, "delta", False):
            if msg.action != ACTION_UPDATE:
                raise KeyframeError(f"{where}: only an update may leave out what it saw (delta)")
            if any(len(v) for v in static.values()):
                raise KeyframeError(f"{where}: a delta update carries no keypoints or descriptors")
            base = stored(msg.keyframe_id) if stored is not None else None
            if base is None:
                raise KeyframeError(
                    f"{where}: a delta update of a keyframe the server does not hold"
                )
        patched = np.asarray(getattr(msg, "patched", ()), np.int64)
        is_patch = bool(getattr(msg, "delta", False)) and len(ids) == len(patched)
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
            T_map_cam=se3_from_quat([p.x, p.y, p.z], q),
            **static,
            map_point_ids=ids,
            map_points=map_points.reshape(-1, 3),
            covisible_ids=np.asarray(msg.covisible_ids, np.uint32),
            covisible_weights=np.asarray(msg.covisible_weights, np.uint16),
            map_segment=msg.map_segment,
            action=msg.action,
        )
        moved = np.asarray(getattr(msg, "moved", ()), np.int64)
        moves = None
        steps = np.asarray(getattr(msg, "moves_q", ()), np.int16)
        half = field_array(getattr(msg, "moves_f16", b""))  # (before moves_q: recorded runs)
        if len(steps) and len(half):
            raise KeyframeError(f"{where}: moves_q and moves_f16 are both given")
        if (len(steps) or len(half)) and not len(moved):
            raise KeyframeError(f"{where}: moves are given without moved")
        if len(moved):
            if not is_patch:
                raise KeyframeError(f"{where}: only a delta update with a patch moves map points")
            if len(half):
                if len(half) != 6 * len(moved):
                    raise KeyframeError(
                        f"{where}: moves_f16 holds {len(half)} bytes for {len(moved)} moved "
                        "keypoints (6 each)"
                    )
                moves_m = np.frombuffer(half.tobytes(), "<f2").astype(np.float32)
            elif len(steps) != 3 * len(moved):
                raise KeyframeError(
                    f"{where}: moves_q holds {len(steps)} values for {len(moved)} moved "
                    "keypoints (3 each)"
                )
            else:
                moves_m = moves_from_steps(steps)
            moves = (moved, moves_m.reshape(-1, 3))
        offsets = field_array(getattr(msg, "map_point_offsets_f16", b""))
        if len(offsets):
            if getattr(msg, "delta", False):
                raise KeyframeError(f"{where}: only a full message carries map point offsets")
            points = decode_point_offsets(rec, offsets.tobytes(), rec.map_points)
            rec = dataclasses.replace(rec, map_points=points)
        if getattr(msg, "delta", False):
            rec = complete_update(rec, base, patched if is_patch else None, moves)
        if getattr(msg, "signature_only", False):
            if msg.action != ACTION_NEW or getattr(msg, "delta", False):
                raise KeyframeError(f"{where}: only a new keyframe goes as a place signature")
            gaps, counts = field_array(msg.bow_word_gaps), field_array(
                getattr(msg, "bow_counts", b"")
            )
            if not len(counts):
                bow = decode_signature(
                    gaps.tobytes(),
                    field_array(msg.bow_weights).tobytes(),
                    float(msg.bow_weight_max),
                )
            elif len(msg.bow_weights):
                raise KeyframeError(f"{where}: bow_weights and bow_counts are both given")
            elif word_idf is None:
                raise KeyframeError(
                    f"{where}: a signature of feature counts needs the server's vocabulary"
                )
            else:
                bow = decode_counted_signature(gaps.tobytes(), counts.tobytes(), word_idf)
            return PlaceSignature(rec, bow).validate(known_robots)
        return rec.validate(known_robots)
    except (KeyframeError, GeometryError, SignatureError) as exc:
        raise MessageError(str(exc)) from None


# --- point clouds ---------------------------------------------------------------------------------
def cloud_to_msg(points: np.ndarray, frame_id: str, stamp=None, rgb: np.ndarray | None = None):
    """PointCloud2 (x, y, z float32 [+ rgb packed float32]) built with numpy, no per-point loop."""
    from sensor_msgs.msg import PointCloud2, PointField

    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [
        PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
        for i, n in enumerate("xyz")
    ]
    if rgb is not None:
        rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
        packed = (
            (rgb[:, 0].astype(np.uint32) << 16)
            | (rgb[:, 1].astype(np.uint32) << 8)
            | rgb[:, 2].astype(np.uint32)
        )
        data = np.empty((len(points), 4), np.float32)
        data[:, :3] = points
        data[:, 3] = packed.view(np.float32)
        fields.append(PointField(name="rgb", offset=12, datatype=PointField.FLOAT32, count=1))
    else:
        data = points
    msg = PointCloud2()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, len(points)
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = 4 * data.shape[1] if len(points) else 4 * len(fields)
    msg.row_step = msg.point_step * len(points)
    msg.is_dense = True
    msg.data = np.ascontiguousarray(data).tobytes()
    return msg


def cloud_from_msg(msg) -> np.ndarray:
    """(N, 3) xyz of a PointCloud2 with float32 x, y, z fields."""
    offsets = {f.name: f.offset for f in msg.fields}
    if not all(k in offsets for k in "xyz") or msg.point_step == 0:
        raise MessageError("point cloud lacks float32 x, y, z fields")
    n = msg.width * msg.height
    if len(msg.data) < n * msg.point_step:
        raise MessageError(f"point cloud data holds {len(msg.data)} bytes for {n} points")
    raw = np.frombuffer(msg.data, np.uint8, count=n * msg.point_step).reshape(n, msg.point_step)
    return np.stack(
        [raw[:, offsets[k] : offsets[k] + 4].copy().view(np.float32)[:, 0] for k in "xyz"], axis=1
    )


def cloud_colours_from_msg(msg) -> np.ndarray:
    """(N, 3) uint8 red, green, blue of a PointCloud2's packed ``rgb`` field (zeros without one)."""
    n = msg.width * msg.height
    offsets = {f.name: f.offset for f in msg.fields}
    if "rgb" not in offsets or n == 0 or len(msg.data) < n * msg.point_step:
        return np.zeros((n, 3), np.uint8)
    raw = np.frombuffer(msg.data, np.uint8, count=n * msg.point_step).reshape(n, msg.point_step)
    packed = raw[:, offsets["rgb"] : offsets["rgb"] + 4].copy().view(np.uint32)[:, 0]
    return np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], 1).astype(np.uint8)


def transform_stamped(T: np.ndarray, parent: str, child: str, stamp):
    from geometry_msgs.msg import TransformStamped

    msg = TransformStamped(transform=transform_to_msg(T))
    msg.header.stamp = stamp
    msg.header.frame_id = parent
    msg.child_frame_id = child
    return msg
