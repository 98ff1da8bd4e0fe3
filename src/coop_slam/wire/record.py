"""The keyframe record clients send to the server, as the core computes with it (what travels
is :mod:`coop_slam.wire.messages`; :mod:`coop_slam.wire.codec` turns one into the other).

:class:`KeyframeRecord` holds numpy arrays shaped for computation; :func:`KeyframeRecord.validate`
is the one place where an incoming keyframe is checked (sizes, types, NaN/inf, robot ids,
descriptor bytes, and physical bounds: intrinsics, positions, depths, stamps, keypoints), so every
node rejects bad input the same way and nothing malformed or absurd reaches a map.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from ..bow.vocabulary import BowVector
from ..camera import CameraError, CameraModel
from ..descriptors import DESCRIPTOR_BYTES
from ..errors import CoopSlamError
from ..geometry import GeometryError, check_se3

ACTION_NEW, ACTION_UPDATE, ACTION_REMOVE = 0, 1, 2
# What a keyframe saw (see static_digest); depth_image: the dense.depth_image blob (empty = none)
STATIC_ARRAYS = ("keypoints", "octaves", "descriptors", "depths_m", "depth_image")
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
# Keypoints per keyframe: clients send 1000 (vo.features.n_features), ORB-SLAM's largest
# presets 2000 (stereo KITTI); 5 x that leaves room for dense stereo / RGB-D extractors. Matching
# two keyframes costs time in the product of their sizes: 1 s at this limit, 5 s at 20,000.
MAX_KEYPOINTS = 10000  # (below 65536: a delta's moved keypoints are uint16)
# Covisible keyframes listed per keyframe: each shares map points with this one; ORB-SLAM keeps
# tens. This many is hours of keyframes at 1 Hz all seeing one scene.
MAX_COVISIBLE = 10000
MAX_IMAGE_SIDE_PX = 16384  # 16K: above any camera a robot streams keyframes from
MIN_FOCAL_PX = 1.0  # a focal length below one pixel images the world onto a pixel or two
MAX_FOCAL_PER_SIDE = 100.0  # focal length / image size: 100 is a 0.6 deg field of view
MAX_POSITION_M = 1e5  # poses and map points: within 100 km of the robot's map origin
MAX_DEPTH_M = 1000.0  # depth cameras reach ~10 m, stereo ~100 m
# Seconds since 1970 (the year 2106) or since the sim clock started: a ROS stamp's seconds are a
# uint32, and a stamp beyond it cannot be serialized at all.
MAX_STAMP_S = float(2**32 - 1)
MAX_OCTAVE = 31  # pyramid level; clients use at most 16 (vo.n_levels)
KEYPOINT_ANGLE_DEG = (-1.0, 360.0)  # OpenCV: [0, 360), -1 = no orientation
_MAX_UINT32 = (1 << 32) - 1
_MAX_KEYFRAME_ID = _MAX_UINT32  # keyframe ids travel as uint32
MAX_REF_KEYFRAMES = 255  # a new keyframe's descriptor references are uint8
# A keyframe's compressed depth image: 160 x 120 takes 5-20 kB; this is a full VGA image's worth.
MAX_DEPTH_IMAGE_BYTES = 1 << 20


class KeyframeError(CoopSlamError):
    """An incoming keyframe is malformed; the message says which field and why."""


@dataclass
class KeyframeRecord:
    robot_id: int
    keyframe_id: int
    stamp_s: float
    camera: CameraModel | None  # None: a removal (it needs no camera)
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
    depth_image: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))  # blob bytes

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
        if not (self.action == ACTION_REMOVE and self.camera is None):  # a removal needs none
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
            "depth_image": (1, None, MAX_DEPTH_IMAGE_BYTES),
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
    :func:`coop_slam.wire.bow_signature.word_counts`): then they travel instead of the weights."""

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
    except CameraError as exc:
        raise KeyframeError(f"camera model: {exc}") from None
