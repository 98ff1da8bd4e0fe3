"""The keyframe record clients send to the server (the pure-core twin of ``msg/KeyFrame.msg``).

:class:`KeyframeRecord` holds numpy arrays shaped for computation; :func:`KeyframeRecord.validate`
is the one place where an incoming keyframe is checked (sizes, NaN/inf, robot ids, descriptor
bytes), so every node rejects bad input the same way and nothing malformed reaches a map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .datasets.base import CameraModel, DatasetError
from .descriptors import DESCRIPTOR_BYTES
from .errors import CoopSlamError
from .geometry import GeometryError, check_se3

ACTION_NEW, ACTION_UPDATE, ACTION_REMOVE = 0, 1, 2
MAX_KEYPOINTS = 20000  # far above any real keyframe; guards the server against absurd messages


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
    )  # u, v, size, angle
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
        """Check every field; raise KeyframeError naming the first problem. Returns self."""
        rid = self.robot_id
        if rid < 1:
            raise KeyframeError(f"robot_id {rid} is invalid: robot ids start at 1")
        if known_robots is not None and rid not in known_robots:
            raise KeyframeError(
                f"robot_id {rid} is unknown to this node (known: {sorted(known_robots)})"
            )
        where = f"keyframe {self.keyframe_id} of robot {rid}"
        if self.keyframe_id < 1:
            raise KeyframeError(f"{where}: keyframe_id must be > 0")
        if not np.isfinite(self.stamp_s) or self.stamp_s < 0:
            raise KeyframeError(f"{where}: stamp {self.stamp_s} is not a valid time")
        if self.action not in (ACTION_NEW, ACTION_UPDATE, ACTION_REMOVE):
            raise KeyframeError(f"{where}: unknown action {self.action}")
        try:
            check_se3(self.T_map_cam, "pose")
        except GeometryError as exc:
            raise KeyframeError(f"{where}: {exc}") from None
        if self.action == ACTION_REMOVE:
            return self
        n = len(self.keypoints)
        if n > MAX_KEYPOINTS:
            raise KeyframeError(f"{where}: {n} keypoints exceed the limit of {MAX_KEYPOINTS}")
        if self.keypoints.ndim != 2 or self.keypoints.shape[1] != 4:
            raise KeyframeError(f"{where}: keypoints must be 4 floats each (u, v, size, angle)")
        if self.descriptors.shape != (n, DESCRIPTOR_BYTES) or self.descriptors.dtype != np.uint8:
            raise KeyframeError(
                f"{where}: descriptors must be {n} x {DESCRIPTOR_BYTES} bytes, got "
                f"{self.descriptors.size} bytes"
            )
        for name in ("octaves", "depths_m", "map_point_ids"):
            if len(getattr(self, name)) != n:
                raise KeyframeError(
                    f"{where}: {name} has {len(getattr(self, name))} entries, "
                    f"expected one per keypoint ({n})"
                )
        m = int(np.count_nonzero(self.map_point_ids))
        if self.map_points.shape != (m, 3):
            raise KeyframeError(
                f"{where}: map_points holds {self.map_points.size} floats, expected 3 x {m} "
                "(one point per non-zero map_point_id)"
            )
        for name in ("keypoints", "depths_m", "map_points"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise KeyframeError(f"{where}: {name} contains NaN or inf")
        if np.any(self.depths_m < 0):
            raise KeyframeError(f"{where}: negative depth")
        cam = self.camera
        uv = self.keypoints[:, :2]
        if n and (
            uv.min() < -1 or uv[:, 0].max() > cam.width + 1 or uv[:, 1].max() > cam.height + 1
        ):
            raise KeyframeError(f"{where}: keypoints outside the {cam.width}x{cam.height} image")
        if len(self.covisible_ids) != len(self.covisible_weights):
            raise KeyframeError(f"{where}: covisible_ids and covisible_weights differ in length")
        return self


def camera_from_fields(**kwargs) -> CameraModel:
    """CameraModel from message fields, turning its validation error into a KeyframeError."""
    try:
        return CameraModel(**kwargs)
    except DatasetError as exc:
        raise KeyframeError(f"camera model: {exc}") from None
