"""The pinhole camera model every part of coop_slam shares: datasets read it, the odometry
projects with it, keyframes carry it over the radio and the server registers with it."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .errors import CoopSlamError

SENSORS = ("rgbd", "stereo", "mono")


class CameraError(CoopSlamError):
    """A camera model's values do not describe a camera (size, intrinsics, sensor, baseline)."""


@dataclass(frozen=True)
class CameraModel:
    """Pinhole model of rectified images (REP-103 units: pixels and metres)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    sensor: str = "rgbd"  # one of SENSORS
    depth_scale: float = 5000.0  # raw 16-bit depth units per metre (TUM: 5000)
    baseline_m: float = 0.0  # stereo baseline [m]

    def __post_init__(self):
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"camera image size {self.width}x{self.height} must be positive")
        vals = (self.fx, self.fy, self.cx, self.cy, self.depth_scale, self.baseline_m)
        if not all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"camera intrinsics must be finite with fx, fy > 0, got {self}")
        if self.sensor not in SENSORS:
            raise CameraError(f"camera sensor '{self.sensor}' unknown; use one of {SENSORS}")
        if self.sensor == "stereo" and self.baseline_m <= 0:
            raise CameraError("a stereo camera needs baseline_m > 0")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
