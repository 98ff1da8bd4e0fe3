"""Compact encodings of a keyframe's arrays on the wire: keypoint positions in uint16 steps,
depths and map point offsets as half floats, map point ids as varint steps, map point moves in
int16 steps. Each pair is exact where it says so, and bounded where it rounds."""

from __future__ import annotations

import numpy as np

from ..geometry import transform_points
from .record import KeyframeError, KeyframeRecord
from .varint import VarintError, decode_varints, encode_varints

_MAX_UINT32 = (1 << 32) - 1
_HALF = np.finfo(np.float16)
HALF_FLOAT_MAX = float(_HALF.max)
HALF_FLOAT_NORMAL_MIN = float(_HALF.tiny)  # below it a half float loses relative precision
# A moved map point's move travels in steps of 2^-12 m (0.24 mm: exact in float32) as int16
# (a delta's moves_q), up to 8 m; the client sends no move below uplink.point_move_m (2 mm).
MOVE_STEP_M = 2.0**-12
MOVE_MAX_M = 32767 * MOVE_STEP_M


def move_steps(moves_m: np.ndarray) -> np.ndarray:
    """Moves [m] as int16 steps of MOVE_STEP_M (the nearest); KeyframeError beyond MOVE_MAX_M."""
    steps = np.round(np.asarray(moves_m, float) / MOVE_STEP_M)
    if len(steps) and not np.all(np.abs(steps) <= 32767):
        raise KeyframeError(f"a move beyond {MOVE_MAX_M:.1f} m (or not finite) has no int16 steps")
    return steps.astype(np.int16)


def moves_from_steps(steps: np.ndarray) -> np.ndarray:
    """The float32 moves [m] of int16 steps (exact: steps are powers of two apart)."""
    return np.asarray(steps, np.int16).astype(np.float32) * np.float32(MOVE_STEP_M)


# A map point offset from its keypoint's depth travels as a half float up to this [m] (0.5 mm
# error at most); local BA moves points mm to cm from where the depth put them.
MAX_POINT_OFFSET_M = 1.0
_MAX_ID_VARINT_BYTES = 5  # a zigzag step between uint32 ids takes 33 bits


# --- what a keyframe saw: keypoint positions and depths ---------------------------------------
UV_CODE_MAX = 65535  # uint16
# Keypoints travel from one pixel left of / above the image: a keypoint's position may lie up
# to a pixel outside it (see KeyframeRecord.validate).
UV_OFFSET_PX = 1.0


def uv_step_px(width: int, height: int) -> float:
    """The step keypoint positions travel in for an image of this size: the smallest power of two
    that spans the image and a pixel on either side in uint16 (1/64 px up to 1021 px a side)."""
    return float(2.0 ** np.ceil(np.log2((max(width, height) + 2 * UV_OFFSET_PX) / UV_CODE_MAX)))


def encode_uv(uv_px: np.ndarray, width: int, height: int) -> tuple[np.ndarray, float]:
    """(N, 2) keypoint positions as uint16 steps from (-1, -1) px and the step [px] (half a step
    off at most); KeyframeError for a position more than a pixel outside the image."""
    uv_px = np.asarray(uv_px, np.float64).reshape(-1, 2)
    step = uv_step_px(width, height)
    with np.errstate(invalid="ignore"):
        code = np.round((uv_px + UV_OFFSET_PX) / step)
        if not np.all((code >= 0) & (code <= UV_CODE_MAX)):
            raise KeyframeError(
                f"a keypoint lies more than {UV_OFFSET_PX:g} px outside the {width}x{height} "
                "image (or is not finite)"
            )
    return code.astype(np.uint16), step


def decode_uv(code: np.ndarray, step_px: float, offset_px: float = UV_OFFSET_PX) -> np.ndarray:
    """(N, 2) float32 keypoint positions [px] from :func:`encode_uv`'s steps (``offset_px`` 0:
    the steps of recorded runs, from (0, 0))."""
    return (np.asarray(code, np.float64).reshape(-1, 2) * float(step_px) - offset_px).astype(
        np.float32
    )


def encode_depths(depths_m: np.ndarray) -> bytes:
    """Depths as little-endian IEEE half floats (relative error <= 2^-11: 1.5 mm at 3 m);
    KeyframeError for one that does not fit (not finite, beyond the half float's range, or so
    small it would lose its precision)."""
    depths_m = np.asarray(depths_m, np.float64)
    small = (depths_m != 0) & (np.abs(depths_m) < HALF_FLOAT_NORMAL_MIN)
    if (
        not np.all(np.isfinite(depths_m))
        or np.abs(depths_m).max(initial=0.0) > HALF_FLOAT_MAX
        or np.any(small)
    ):
        raise KeyframeError(
            f"depths must be 0 or within [{HALF_FLOAT_NORMAL_MIN:.3g}, {HALF_FLOAT_MAX:g}] m to "
            "travel as half floats"
        )
    return depths_m.astype("<f2").tobytes()


def decode_depths(raw: bytes) -> np.ndarray:
    """float32 depths [m] from :func:`encode_depths`' bytes."""
    if len(raw) % 2:
        raise KeyframeError(f"depths_f16 holds {len(raw)} bytes, not 2 per keypoint")
    return np.frombuffer(raw, "<f2").astype(np.float32)


def encode_map_point_ids(ids: np.ndarray) -> bytes:
    """Per keypoint a varint: 0 where it observes no map point, else the zigzag of its map point
    id minus the previous keypoint's non-zero one (0 before the first), plus 1. Ids made together
    follow each other: most take a byte (four as uint32)."""
    ids = np.asarray(ids, np.int64)
    seen = ids != 0
    step = np.diff(np.concatenate([[0], ids[seen]]))
    code = np.zeros(len(ids), np.int64)
    code[seen] = np.where(step >= 0, 2 * step, -2 * step - 1) + 1
    return encode_varints(code)


def decode_map_point_ids(raw: bytes) -> np.ndarray:
    """The uint32 map point ids of :func:`encode_map_point_ids`' bytes; KeyframeError if they are
    none."""
    try:
        code = decode_varints(raw, _MAX_ID_VARINT_BYTES)
    except VarintError as exc:
        raise KeyframeError(f"map_point_id_codes: {exc}") from None
    seen = code != 0
    z = code[seen] - 1
    ids = np.cumsum(np.where(z % 2 == 0, z // 2, -(z + 1) // 2))
    if len(ids) and (ids.min() < 1 or ids.max() > _MAX_UINT32):
        raise KeyframeError("map_point_id_codes give an id outside [1, 2^32)")
    out = np.zeros(len(code), np.uint32)
    out[seen] = ids
    return out


def _depth_points(rec: KeyframeRecord) -> np.ndarray:
    """(N, 3) map-frame points of the keypoints at their depths; NaN rows where there is none."""
    with np.errstate(invalid="ignore"):
        return transform_points(rec.T_map_cam, rec.points_cam())


def encode_point_offsets(rec: KeyframeRecord) -> tuple[bytes, np.ndarray] | None:
    """The map points of a keyframe as half-float offsets [m] from where its keypoints' depths put
    them (observed keypoints with a depth, in keypoint order; NaN where the offset is beyond
    ``MAX_POINT_OFFSET_M``), and the (K, 3) float32 points of the other observed keypoints and of
    those NaN ones, in keypoint order; None when that is no shorter than float32 points alone.
    ``rec`` is the keyframe as the server will decode it (keypoints, depths and pose as they
    travel)."""
    seen = np.asarray(rec.map_point_ids) != 0
    with_depth = seen & (np.asarray(rec.depths_m) > 0)
    per_keypoint = rec.map_points_per_keypoint()
    offsets = np.full((len(seen), 3), np.nan)
    with np.errstate(invalid="ignore"):
        offsets[with_depth] = per_keypoint[with_depth] - _depth_points(rec)[with_depth]
        near = np.all(np.abs(offsets) <= MAX_POINT_OFFSET_M, axis=1)
    offsets[~near] = np.nan
    exact = seen & ~near
    if 6 * with_depth.sum() + 12 * exact.sum() >= 12 * seen.sum():
        return None
    return offsets[with_depth].astype("<f2").tobytes(), per_keypoint[exact].astype(np.float32)


def decode_point_offsets(rec: KeyframeRecord, raw: bytes, rest: np.ndarray) -> np.ndarray:
    """The (M, 3) float32 map points of :func:`encode_point_offsets`' offsets ``raw`` and
    points ``rest``, for ``rec`` (its keypoints, depths, pose and map point ids as decoded);
    KeyframeError when they do not fit."""
    if not len(rec.map_point_ids) == len(rec.depths_m) == len(rec.keypoints):
        raise KeyframeError(
            f"{len(rec.keypoints)} keypoints, {len(rec.depths_m)} depths and "
            f"{len(rec.map_point_ids)} map point ids: map point offsets need one of each"
        )
    seen = np.asarray(rec.map_point_ids) != 0
    with_depth = seen & (np.asarray(rec.depths_m) > 0)
    if len(raw) != 6 * int(with_depth.sum()):
        raise KeyframeError(
            f"map_point_offsets_f16 holds {len(raw)} bytes for {int(with_depth.sum())} observed "
            "keypoints with a depth (6 each)"
        )
    offsets = np.full((len(seen), 3), np.nan, np.float32)
    offsets[with_depth] = np.frombuffer(raw, "<f2").reshape(-1, 3)
    if np.any(np.isinf(offsets)):
        raise KeyframeError("map_point_offsets_f16 holds inf")
    exact = seen & np.any(np.isnan(offsets), axis=1)  # no depth, or an offset beyond range
    rest = np.asarray(rest, np.float32).reshape(-1, 3)
    if len(rest) != int(exact.sum()):
        raise KeyframeError(
            f"map_points holds {len(rest)} points for {int(exact.sum())} observed keypoints "
            "without a depth or an offset (the others' go as offsets)"
        )
    per_keypoint = np.full((len(seen), 3), np.nan, np.float32)
    per_keypoint[seen] = _depth_points(rec)[seen].astype(np.float32) + offsets[seen]
    per_keypoint[exact] = rest
    return per_keypoint[seen]
