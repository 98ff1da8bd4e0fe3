"""The keyframe record clients send to the server (the pure-core twin of ``msg/KeyFrame.msg``).

:class:`KeyframeRecord` holds numpy arrays shaped for computation; :func:`KeyframeRecord.validate`
is the one place where an incoming keyframe is checked (sizes, types, NaN/inf, robot ids,
descriptor bytes, and physical bounds: intrinsics, positions, depths, stamps, keypoints), so every
node rejects bad input the same way and nothing malformed or absurd reaches a map.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field

import numpy as np

from .bow.vocabulary import BowVector
from .datasets.base import CameraModel, DatasetError
from .descriptors import DESCRIPTOR_BYTES
from .errors import CoopSlamError
from .geometry import GeometryError, check_se3, transform_points
from .varint import VarintError, decode_varints, encode_varints

ACTION_NEW, ACTION_UPDATE, ACTION_REMOVE = 0, 1, 2
STATIC_ARRAYS = ("keypoints", "octaves", "descriptors", "depths_m")  # see static_digest
# Every array of a keyframe record, in field order
ARRAY_FIELDS = STATIC_ARRAYS + (
    "map_point_ids",
    "map_points",
    "covisible_ids",
    "covisible_weights",
)

# Physical bounds of a keyframe. Values beyond them are finite yet absurd (a corrupted or hostile
# message): accepted, they poison the team map for the rest of the run (a focal length of 1e-300
# px makes every later global BA refuse, a pose 1e300 m away breaks the pose graph).
# Keypoints per keyframe: clients send 1000 (config/client.yaml vo.n_features), ORB-SLAM's largest
# presets 2000 (stereo KITTI); 5 x that leaves room for dense stereo / RGB-D extractors. Matching
# two keyframes costs time in the product of their sizes: 1 s at this limit, 5 s at 20,000.
MAX_KEYPOINTS = 10000  # (below 65536: KeyFrame.moved indexes keypoints in uint16)
# Covisible keyframes listed per keyframe: each shares map points with this one; ORB-SLAM keeps
# tens. This many is hours of keyframes at 1 Hz all seeing one scene.
MAX_COVISIBLE = 10000
MAX_IMAGE_SIDE_PX = 16384  # 16K: above any camera a robot streams keyframes from
MIN_FOCAL_PX = 1.0  # a focal length below one pixel images the world onto a pixel or two
MAX_FOCAL_PER_SIDE = 100.0  # focal length / image size: 100 is a 0.6 deg field of view
MAX_POSITION_M = 1e5  # poses and map points: within 100 km of the robot's map origin
MAX_DEPTH_M = 1000.0  # depth cameras reach ~10 m, stereo ~100 m
MAX_STAMP_S = 1e10  # seconds since 1970 (the year 2286) or since the sim clock started
MAX_OCTAVE = 31  # pyramid level; clients use at most 16 (vo.n_levels)
KEYPOINT_ANGLE_DEG = (-1.0, 360.0)  # OpenCV: [0, 360), -1 = no orientation
_MAX_UINT32 = (1 << 32) - 1
_MAX_KEYFRAME_ID = _MAX_UINT32  # KeyFrame.msg: uint32 keyframe_id
_HALF = np.finfo(np.float16)
HALF_FLOAT_MAX = float(_HALF.max)
HALF_FLOAT_NORMAL_MIN = float(_HALF.tiny)  # below it a half float loses relative precision
MAX_REF_KEYFRAMES = 255  # KeyFrame.msg: uint8 descriptor_refs
# A moved map point's move travels in steps of 2^-12 m (0.24 mm: exact in float32) as int16
# (KeyFrame.msg moves_q), up to 8 m; the client sends no move below uplink.point_move_m (2 mm).
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


class KeyframeError(CoopSlamError):
    """An incoming keyframe is malformed; the message says which field and why."""


@dataclass
class KeyframeRecord:
    robot_id: int
    keyframe_id: int
    stamp_s: float
    camera: CameraModel
    T_map_cam: np.ndarray  # (4, 4) camera optical frame in the robot's map frame
    keypoints: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 4), np.float32)
    )  # u, v, size (0 = not given), angle (-1 = none)
    octaves: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    depths_m: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # 0 = none
    map_point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))  # 0 = none
    map_points: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 3), np.float32)
    )  # (M, 3) map
    covisible_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    covisible_weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))
    map_segment: int = 0
    action: int = ACTION_NEW

    def static_digest(self) -> bytes:
        """Digest of what the keyframe saw (keypoints, octaves, descriptors, depths), which an
        update after local BA does not change: equal digests need not travel or be stored
        again."""
        h = hashlib.blake2b(digest_size=16)
        for name in STATIC_ARRAYS:
            a = np.ascontiguousarray(getattr(self, name))
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        return h.digest()

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoints)

    @property
    def uv_px(self) -> np.ndarray:
        return self.keypoints[:, :2]

    def points_cam(self) -> np.ndarray:
        """(N, 3) camera-frame points back-projected from depth; NaN rows where there is no
        depth."""
        z = self.depths_m.astype(float)
        cam = self.camera
        x = (self.keypoints[:, 0] - cam.cx) / cam.fx * z
        y = (self.keypoints[:, 1] - cam.cy) / cam.fy * z
        pts = np.stack([x, y, z], axis=1)
        pts[z <= 0] = np.nan
        return pts

    def map_points_per_keypoint(self) -> np.ndarray:
        """(N, 3) map-frame positions of the observed map points; NaN rows where there is none."""
        out = np.full((self.num_keypoints, 3), np.nan)
        out[self.map_point_ids != 0] = self.map_points
        return out

    def validate(self, known_robots: set[int] | None = None) -> "KeyframeRecord":
        """Check every field against its type, shape and physical bounds (module constants); raise
        KeyframeError naming the first problem. Returns self.

        A REMOVE is checked like the others up to the array sizes (its arrays may be empty, but are
        bounded as every keyframe's); what the arrays hold is not looked at, the server drops the
        keyframe."""
        rid = self.robot_id
        if not _is_int(rid) or rid < 1:
            raise KeyframeError(f"robot_id {rid!r} is invalid: robot ids are integers from 1")
        if known_robots is not None and rid not in known_robots:
            raise KeyframeError(
                f"robot_id {rid} is unknown to this node (known: {sorted(known_robots)})"
            )
        if not _is_int(self.keyframe_id) or not 1 <= self.keyframe_id <= _MAX_KEYFRAME_ID:
            raise KeyframeError(
                f"keyframe_id {self.keyframe_id!r} of robot {rid} is invalid: keyframe ids are "
                f"integers in [1, {_MAX_KEYFRAME_ID}]"
            )
        where = f"keyframe {self.keyframe_id} of robot {rid}"
        try:
            stamp_ok = bool(0.0 <= float(self.stamp_s) < MAX_STAMP_S)
        except (TypeError, ValueError):
            stamp_ok = False
        if not stamp_ok:
            raise KeyframeError(
                f"{where}: stamp {self.stamp_s!r} s is not a valid time (finite, in "
                f"[0, {MAX_STAMP_S:g}) s)"
            )
        if not _is_int(self.action) or self.action not in (
            ACTION_NEW,
            ACTION_UPDATE,
            ACTION_REMOVE,
        ):
            raise KeyframeError(f"{where}: unknown action {self.action!r}")
        if not _is_int(self.map_segment) or self.map_segment < 0:
            raise KeyframeError(
                f"{where}: map_segment {self.map_segment!r} must be an integer >= 0"
            )
        self._validate_camera(where)
        try:
            with np.errstate(over="ignore", invalid="ignore"):  # a rotation of 1e300: overflow
                check_se3(_numeric(self.T_map_cam, "pose", where), "pose")
        except GeometryError as exc:
            raise KeyframeError(f"{where}: {exc}") from None
        far = float(np.abs(self.T_map_cam[:3, 3]).max())
        if far > MAX_POSITION_M:
            raise KeyframeError(
                f"{where}: pose position {far:.3g} m from the map origin is beyond the "
                f"{MAX_POSITION_M:g} m any map spans"
            )
        self._validate_sizes(where)
        if self.action == ACTION_REMOVE:
            return self
        self._validate_contents(where)
        return self

    def _validate_camera(self, where: str) -> None:
        """Intrinsics within physical bounds (CameraModel itself only asks for finite, fx, fy > 0):
        every later use of the keyframe divides by them or projects with them."""
        cam = self.camera
        if not isinstance(cam, CameraModel):
            raise KeyframeError(f"{where}: camera must be a CameraModel, got {type(cam).__name__}")
        w, h = cam.width, cam.height
        if not all(
            isinstance(x, (int, float, np.number)) and float(x).is_integer() for x in (w, h)
        ):
            raise KeyframeError(f"{where}: camera image size {w!r}x{h!r} is not in whole pixels")
        if max(w, h) > MAX_IMAGE_SIDE_PX:
            raise KeyframeError(
                f"{where}: camera image {w}x{h} px exceeds {MAX_IMAGE_SIDE_PX} px per side"
            )
        f_max = MAX_FOCAL_PER_SIDE * max(w, h)
        for name in ("fx", "fy"):
            f = getattr(cam, name)
            if not MIN_FOCAL_PX <= f <= f_max:
                raise KeyframeError(
                    f"{where}: camera {name} = {f:.6g} px is outside [{MIN_FOCAL_PX:g}, "
                    f"{f_max:g}] px ({MAX_FOCAL_PER_SIDE:g} x the image size): not a camera "
                    "calibration"
                )
        if not (-w <= cam.cx <= 2 * w and -h <= cam.cy <= 2 * h):
            raise KeyframeError(
                f"{where}: camera principal point ({cam.cx:.6g}, {cam.cy:.6g}) px lies outside "
                f"the {w}x{h} image extended by its size on every side"
            )

    def _validate_sizes(self, where: str) -> None:
        """Array types and sizes, before anything looks at their contents."""
        shapes = {  # name: (ndim, columns, limit on rows)
            "keypoints": (2, 4, MAX_KEYPOINTS),
            "octaves": (1, None, MAX_KEYPOINTS),
            "descriptors": (2, DESCRIPTOR_BYTES, MAX_KEYPOINTS),
            "depths_m": (1, None, MAX_KEYPOINTS),
            "map_point_ids": (1, None, MAX_KEYPOINTS),
            "map_points": (2, 3, MAX_KEYPOINTS),
            "covisible_ids": (1, None, MAX_COVISIBLE),
            "covisible_weights": (1, None, MAX_COVISIBLE),
        }
        for name, (ndim, cols, limit) in shapes.items():
            arr = _numeric(getattr(self, name), name, where)
            if arr.ndim != ndim or (cols is not None and arr.shape[1] != cols):
                layout = f"(N, {cols})" if cols is not None else "(N,)"
                raise KeyframeError(f"{where}: {name} has shape {arr.shape}, expected {layout}")
            if len(arr) > limit:
                raise KeyframeError(
                    f"{where}: {name} holds {len(arr)} entries, above the limit of {limit}"
                )

    def _validate_contents(self, where: str) -> None:
        n = len(self.keypoints)
        if self.descriptors.shape != (n, DESCRIPTOR_BYTES) or self.descriptors.dtype != np.uint8:
            raise KeyframeError(
                f"{where}: descriptors must be {n} x {DESCRIPTOR_BYTES} bytes, got "
                f"{self.descriptors.size} {self.descriptors.dtype} values"
            )
        for name in ("octaves", "depths_m", "map_point_ids"):
            if len(getattr(self, name)) != n:
                raise KeyframeError(
                    f"{where}: {name} has {len(getattr(self, name))} entries, "
                    f"expected one per keypoint ({n})"
                )
        if len(self.covisible_ids) != len(self.covisible_weights):
            raise KeyframeError(f"{where}: covisible_ids and covisible_weights differ in length")
        for name in ("octaves", "map_point_ids", "covisible_ids", "covisible_weights"):
            arr = getattr(self, name)
            if arr.dtype.kind not in "ui":
                raise KeyframeError(f"{where}: {name} must be integers, got {arr.dtype}")
            if len(arr) and arr.min() < 0:
                raise KeyframeError(f"{where}: {name} holds a negative value")
        m = int(np.count_nonzero(self.map_point_ids))
        if self.map_points.shape != (m, 3):
            raise KeyframeError(
                f"{where}: map_points holds {self.map_points.size} floats, expected 3 x {m} "
                "(one point per non-zero map_point_id)"
            )
        for name in ("keypoints", "depths_m", "map_points"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise KeyframeError(f"{where}: {name} contains NaN or inf")
        if m and np.abs(self.map_points).max() > MAX_POSITION_M:
            raise KeyframeError(
                f"{where}: a map point lies {float(np.abs(self.map_points).max()):.3g} m from the "
                f"map origin, beyond the {MAX_POSITION_M:g} m any map spans"
            )
        if n and (self.depths_m.min() < 0 or self.depths_m.max() > MAX_DEPTH_M):
            raise KeyframeError(
                f"{where}: depths must be in [0, {MAX_DEPTH_M:g}] m (0 = none), got "
                f"[{float(self.depths_m.min()):.3g}, {float(self.depths_m.max()):.3g}]"
            )
        if n and self.octaves.max() > MAX_OCTAVE:
            raise KeyframeError(
                f"{where}: octave {int(self.octaves.max())} is above the limit of {MAX_OCTAVE}"
            )
        if n == 0:
            return
        cam = self.camera
        uv, size, angle = self.keypoints[:, :2], self.keypoints[:, 2], self.keypoints[:, 3]
        if uv.min() < -1 or uv[:, 0].max() > cam.width + 1 or uv[:, 1].max() > cam.height + 1:
            raise KeyframeError(f"{where}: keypoints outside the {cam.width}x{cam.height} image")
        diagonal = float(np.hypot(cam.width, cam.height))
        if size.min() < 0 or size.max() > diagonal:
            raise KeyframeError(
                f"{where}: keypoint sizes must be in [0, {diagonal:.0f}] px (the image "
                f"diagonal; 0 = not given), got [{float(size.min()):.3g}, "
                f"{float(size.max()):.3g}]"
            )
        lo, hi = KEYPOINT_ANGLE_DEG
        if angle.min() < lo or angle.max() > hi:
            raise KeyframeError(
                f"{where}: keypoint angles must be in [{lo:g}, {hi:g}] deg (-1 = none), got "
                f"[{float(angle.min()):.3g}, {float(angle.max()):.3g}]"
            )


@dataclass
class PlaceSignature:
    """A new keyframe in low-bandwidth mode (``uplink.mode: pull``): ``record`` without what the
    keyframe saw (no keypoints; pose, stamp, camera, covisible keyframes) and the keyframe's BoW
    vector. The server asks the robot for the whole keyframe when it needs it. ``counts``: the
    features on each of the vector's words, when they give it exactly (see
    :func:`coop_slam.bow.signature.word_counts`): then they travel instead of the weights."""

    record: KeyframeRecord
    bow: BowVector
    counts: np.ndarray | None = None

    @property
    def robot_id(self) -> int:
        return self.record.robot_id

    @property
    def keyframe_id(self) -> int:
        return self.record.keyframe_id

    def validate(self, known_robots: set[int] | None = None) -> "PlaceSignature":
        """As :meth:`KeyframeRecord.validate`, and the BoW vector's words and weights."""
        rec = self.record
        if rec.action != ACTION_NEW or rec.num_keypoints:
            raise KeyframeError(
                f"keyframe {rec.keyframe_id} of robot {rec.robot_id}: a place signature is a new "
                "keyframe without keypoints"
            )
        rec.validate(known_robots)
        words, weights = np.asarray(self.bow.words), np.asarray(self.bow.weights)
        if (
            len(words) != len(weights)
            or (len(words) > 1 and np.any(np.diff(words) <= 0))
            or (len(words) and words.min() < 0)
            or not np.all(np.isfinite(weights))
            or (len(weights) and weights.min() <= 0)
        ):
            raise KeyframeError(
                f"keyframe {rec.keyframe_id} of robot {rec.robot_id}: its place signature needs "
                "increasing word ids with positive weights"
            )
        return self


def observation_patch(
    held_ids: np.ndarray,
    held_points: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
    min_move_m: float,
) -> np.ndarray:
    """Indices of the keypoints whose observation differs from what the server holds
    (``held_ids``, ``held_points``: per keypoint, NaN rows where there is no map point): another
    map point or none, or the same point moved more than ``min_move_m``. ``ids``/``points`` are
    the keyframe's now, in the same per-keypoint form."""
    changed = np.asarray(held_ids) != np.asarray(ids)
    with np.errstate(invalid="ignore"):
        moved = np.linalg.norm(np.asarray(points) - held_points, axis=1) > min_move_m
    return np.flatnonzero(changed | moved).astype(np.uint32)


def patch_of(rec: KeyframeRecord, patched: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a patch of ``rec``'s observations carries for the keypoints ``patched``: their map
    point ids and, in that order, the (M, 3) positions of the non-zero ones."""
    patched = np.asarray(patched, np.int64)
    ids = np.asarray(rec.map_point_ids, np.uint32)[patched]
    return ids, rec.map_points_per_keypoint()[patched][ids != 0].astype(np.float32)


def apply_observation_patch(
    held_ids: np.ndarray,
    held_points: np.ndarray,
    patched: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The observations after a patch: (ids, per-keypoint points, NaN rows where none). The patch
    gives, for the keypoints ``patched``, their map point ids (0 = none now) and, in that order,
    the positions of the non-zero ones. Raises KeyframeError when it does not fit."""
    n = len(held_ids)
    patched = np.asarray(patched, np.int64)
    if len(ids) != len(patched):
        raise KeyframeError(
            f"an observation patch lists {len(patched)} keypoints but {len(ids)} map point ids"
        )
    if len(patched) and (patched.min() < 0 or patched.max() >= n):
        raise KeyframeError(
            f"an observation patch names keypoint {int(patched.max())} of a keyframe with {n}"
        )
    if len(np.unique(patched)) != len(patched):
        raise KeyframeError("an observation patch names a keypoint twice")
    seen = np.asarray(ids) != 0
    if len(points) != int(seen.sum()):
        raise KeyframeError(
            f"an observation patch gives {len(points)} map points for {int(seen.sum())} observed "
            "keypoints"
        )
    out_ids = np.array(held_ids, np.uint32, copy=True)
    out_points = np.array(held_points, float, copy=True)
    out_ids[patched] = ids
    out_points[patched] = np.nan
    out_points[patched[seen]] = points
    return out_ids, out_points


def split_moves(
    held_ids: np.ndarray,
    held_points: np.ndarray,
    patched: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
    min_move_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of the keypoints ``patched`` (see :func:`observation_patch`; ``ids``, ``points`` the
    keyframe's now, per keypoint), those whose map point only moved, by at most ``MOVE_MAX_M``
    per coordinate: ``(others, moved, moves)``, the rest of ``patched``, the moved keypoints and
    their (k, 3) float32 moves [m] since ``held_points``, rounded to ``MOVE_STEP_M`` (half a step
    off at most). ``min_move_m`` below a step: none (every position travels exact: the rounding
    would be above the moves left unsent)."""
    patched = np.asarray(patched, np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        move = np.asarray(points, float)[patched] - np.asarray(held_points, float)[patched]
        largest = np.abs(move).max(axis=1, initial=0.0)
        ok = (
            (np.asarray(held_ids)[patched] == np.asarray(ids)[patched])
            & (np.asarray(ids)[patched] != 0)
            & np.all(np.isfinite(move), axis=1)
            & (largest <= MOVE_MAX_M)
            & (min_move_m >= MOVE_STEP_M)
        )
    return (
        patched[~ok].astype(np.uint32),
        patched[ok].astype(np.uint32),
        moves_from_steps(move_steps(move[ok])).reshape(-1, 3),
    )


def apply_moves(
    held_ids: np.ndarray, held_points: np.ndarray, moved: np.ndarray, moves: np.ndarray
) -> np.ndarray:
    """The per-keypoint points after the keypoints ``moved``'s map points moved by ``moves``
    ((k, 3) [m], as the message carries them: see :func:`split_moves`), added in float32 as the
    message's points are (the client and the server add alike; the server's position differs
    from the client's by the rounding of a monocular map's scale at most). Raises KeyframeError
    when they do not fit."""
    n = len(held_ids)
    moved = np.asarray(moved, np.int64)
    moves = np.asarray(moves, np.float32).reshape(-1, 3)
    if len(moves) != len(moved):
        raise KeyframeError(f"{len(moves)} moves for {len(moved)} moved keypoints")
    if len(moved) and (moved.min() < 0 or moved.max() >= n):
        raise KeyframeError(f"moved names keypoint {int(moved.max())} of a keyframe with {n}")
    if len(np.unique(moved)) != len(moved):
        raise KeyframeError("moved names a keypoint twice")
    if np.any(np.asarray(held_ids)[moved] == 0):
        raise KeyframeError("moved names a keypoint that observes no map point")
    if not np.all(np.isfinite(moves)):
        raise KeyframeError("a move is NaN or inf")
    out = np.array(held_points, float, copy=True)
    out[moved] = np.asarray(out[moved], np.float32) + moves
    return out


def complete_update(
    sent: KeyframeRecord,
    base: KeyframeRecord,
    patched: np.ndarray | None = None,
    moves: tuple[np.ndarray, np.ndarray] | None = None,
) -> KeyframeRecord:
    """A delta update as the server holds it: what the keyframe saw from ``base`` (the keyframe
    as stored), and its observations from ``sent`` -- all of them (``patched`` None), or a patch
    of ``base``'s (see :func:`apply_observation_patch`) and ``moves`` of its map points (moved
    keypoints, their moves: see :func:`apply_moves`)."""
    static = {k: getattr(base, k) for k in STATIC_ARRAYS}
    if patched is None:
        return dataclasses.replace(sent, **static)
    if sent.keyframe_id != base.keyframe_id:  # (the server holds it under its map's id)
        raise KeyframeError(
            f"keyframe {sent.keyframe_id} of robot {sent.robot_id}: patched against keyframe "
            f"{base.keyframe_id}"
        )
    ids, per_keypoint = apply_observation_patch(
        base.map_point_ids,
        base.map_points_per_keypoint(),
        patched,
        sent.map_point_ids,
        np.asarray(sent.map_points).reshape(-1, 3),
    )
    if moves is not None:
        if len(np.intersect1d(np.asarray(moves[0], np.int64), np.asarray(patched, np.int64))):
            raise KeyframeError(
                f"keyframe {sent.keyframe_id} of robot {sent.robot_id}: a keypoint is both "
                "patched and moved"
            )
        per_keypoint = apply_moves(ids, per_keypoint, *moves)
    return dataclasses.replace(
        sent,
        **static,
        map_point_ids=ids,
        map_points=per_keypoint[ids != 0].astype(np.float32),
    )


# --- compact encodings of what a keyframe saw (KeyFrame.msg keypoints_uv, depths_f16) ----------
UV_CODE_MAX = 65535  # uint16


def uv_step_px(width: int, height: int) -> float:
    """The step keypoint positions travel in for an image of this size: the smallest power of two
    that spans the image and a pixel beyond in uint16 (1/64 px up to 1022 px a side)."""
    return float(2.0 ** np.ceil(np.log2((max(width, height) + 1) / UV_CODE_MAX)))


def encode_uv(uv_px: np.ndarray, width: int, height: int) -> tuple[np.ndarray, float] | None:
    """(N, 2) keypoint positions as uint16 steps and the step [px]; None when one does not fit
    (outside the image, not finite): they then travel as float32."""
    uv_px = np.asarray(uv_px, np.float64).reshape(-1, 2)
    step = uv_step_px(width, height)
    with np.errstate(invalid="ignore"):
        code = np.round(uv_px / step)
        if not np.all((code >= 0) & (code <= UV_CODE_MAX)):
            return None
    return code.astype(np.uint16), step


def decode_uv(code: np.ndarray, step_px: float) -> np.ndarray:
    """(N, 2) float32 keypoint positions [px] from :func:`encode_uv`'s steps."""
    return (np.asarray(code, np.float64).reshape(-1, 2) * float(step_px)).astype(np.float32)


def encode_depths(depths_m: np.ndarray) -> bytes | None:
    """Depths as little-endian IEEE half floats; None when one does not fit (not finite, beyond
    the half float's range, or so small it would lose its precision): they then travel as
    float32."""
    depths_m = np.asarray(depths_m, np.float64)
    small = (depths_m != 0) & (np.abs(depths_m) < HALF_FLOAT_NORMAL_MIN)
    if (
        not np.all(np.isfinite(depths_m))
        or np.abs(depths_m).max(initial=0.0) > HALF_FLOAT_MAX
        or np.any(small)
    ):
        return None
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


def observation_index(source_ids: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Per map point id of ``ids``, the index of the first keypoint observing it in a keyframe
    whose per-keypoint map point ids are ``source_ids``; -1 where none does (and for id 0)."""
    source_ids, ids = np.asarray(source_ids, np.int64), np.asarray(ids, np.int64)
    if not len(source_ids):
        return np.full(len(ids), -1, np.int64)
    order = np.argsort(source_ids, kind="stable")  # equal ids keep their keypoint order
    ranked = source_ids[order]
    pos = np.minimum(np.searchsorted(ranked, ids), len(ranked) - 1)
    return np.where((ranked[pos] == ids) & (ids != 0), order[pos], -1)


def shared_descriptors(
    map_point_ids: np.ndarray,
    own: np.ndarray,
    refs: np.ndarray,
    ref_keyframes: np.ndarray,
    stored,
    where: str,
) -> np.ndarray:
    """A keyframe's (N, 32) descriptors from a message that leaves some out (``KeyFrame``
    ``descriptor_refs``): ``own`` are the descriptors of the keypoints whose ``refs`` entry is 0;
    a keypoint with ``refs`` i >= 1 takes the descriptor of the keypoint observing its map point in
    keyframe ``ref_keyframes[i - 1]``, the record ``stored(keyframe_id)`` gives (None: not held).
    Raises KeyframeError naming what does not fit."""
    refs = np.asarray(refs, np.int64)
    ids = np.asarray(map_point_ids, np.int64)
    own = np.asarray(own, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
    if len(ref_keyframes) > MAX_REF_KEYFRAMES:
        raise KeyframeError(
            f"{where}: ref_keyframes lists {len(ref_keyframes)} keyframes, above the limit of "
            f"{MAX_REF_KEYFRAMES}"
        )
    if len(refs) != len(ids):
        raise KeyframeError(
            f"{where}: descriptor_refs has {len(refs)} entries, expected one per keypoint "
            f"({len(ids)})"
        )
    if len(own) != int(np.count_nonzero(refs == 0)):
        raise KeyframeError(
            f"{where}: descriptors hold {len(own)} descriptors for "
            f"{int(np.count_nonzero(refs == 0))} keypoints without a descriptor_refs entry"
        )
    if len(refs) and refs.max() > len(ref_keyframes):
        raise KeyframeError(
            f"{where}: descriptor_refs names reference {int(refs.max())} of "
            f"{len(ref_keyframes)} ref_keyframes"
        )
    if np.any((refs != 0) & (ids == 0)):
        raise KeyframeError(f"{where}: descriptor_refs names a keypoint that observes no map point")
    out = np.zeros((len(ids), DESCRIPTOR_BYTES), np.uint8)
    out[refs == 0] = own
    ref_keyframes = np.asarray(ref_keyframes, np.int64)
    for i in np.unique(refs[refs > 0]):
        mine, kf_id = np.flatnonzero(refs == i), int(ref_keyframes[i - 1])
        source = stored(kf_id)
        if source is None:
            raise KeyframeError(
                f"{where}: its descriptors refer to keyframe {kf_id}, which the server does not "
                "hold"
            )
        at = observation_index(source.map_point_ids, ids[mine])
        if np.any(at < 0):
            raise KeyframeError(
                f"{where}: descriptor_refs names map point {int(ids[mine][at < 0][0])} in "
                f"keyframe {kf_id}, which does not observe it"
            )
        out[mine] = source.descriptors[at]
    return out


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _numeric(arr, name: str, where: str) -> np.ndarray:
    """``arr`` if it is a numpy array of real numbers; KeyframeError otherwise."""
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "uif":
        kind = arr.dtype if isinstance(arr, np.ndarray) else type(arr).__name__
        raise KeyframeError(f"{where}: {name} must be a numeric array, got {kind}")
    return arr


def camera_from_fields(**kwargs) -> CameraModel:
    """CameraModel from message fields, turning its validation error into a KeyframeError."""
    try:
        return CameraModel(**kwargs)
    except DatasetError as exc:
        raise KeyframeError(f"camera model: {exc}") from None
