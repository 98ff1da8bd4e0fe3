"""What a robot tells the team about its own body: where its camera is mounted (``T_base_cam``),
the marker it carries (dictionary, size, mount) and its body's size, its camera and preset.

Each client publishes its description (latched, ``/robot_k/description``); the server places a
marker sighting of robot b with b's own description, never with one team-wide value: robots with
different camera mounts or markers are each described by themselves.

A sighting carries the marker's pose as the observer measured it, with the marker size the
observer assumed (:class:`MarkerSeen`). A square marker's pose from its four corners scales with
the size assumed (same rotation, translation proportional to the size), so the server rescales it
to the observed robot's true size and adds that robot's marker mount (:meth:`RobotDescription.
T_cam_body`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import CoopSlamError, GeometryError
from .geometry import check_se3, invert
from .markers import MarkerConfig

SENSORS = ("rgbd", "stereo", "mono")


class RobotDescriptionError(CoopSlamError):
    """A robot description the server cannot use (it names the robot and the field)."""


@dataclass(frozen=True)
class MarkerSeen:
    """A marker as an observer saw it: its pose in the observer's camera optical frame, computed
    with the marker side the observer assumed."""

    T_cam_marker: np.ndarray  # (4, 4)
    assumed_size_m: float


@dataclass(frozen=True)
class RobotDescription:
    robot_id: int
    sensor: str  # rgbd, stereo or mono
    T_base_cam: np.ndarray  # (4, 4) camera optical frame in base_link
    marker_dictionary: str  # ArUco dictionary of its marker (id = robot id)
    marker_size_m: float  # side of the marker's black square [m]
    T_base_marker: np.ndarray  # (4, 4) front-face marker centre in base_link
    body_size_m: tuple[float, float, float]  # box (x, y, z) around base_link, on the floor [m]
    camera: str = ""  # camera preset name ("" = none)

    def __post_init__(self) -> None:
        self.validate()  # a description that exists is one the server can use

    def validate(self) -> None:
        who = f"robot {self.robot_id}'s description"
        if self.robot_id < 1:
            raise RobotDescriptionError(f"{who}: robot_id must be >= 1")
        if self.sensor not in SENSORS:
            raise RobotDescriptionError(f"{who}: sensor {self.sensor!r} is not one of {SENSORS}")
        for name in ("T_base_cam", "T_base_marker"):
            try:
                check_se3(getattr(self, name), name)
            except GeometryError as exc:
                raise RobotDescriptionError(f"{who}: {exc}") from None
        if not np.isfinite(self.marker_size_m) or self.marker_size_m <= 0:
            raise RobotDescriptionError(f"{who}: marker_size_m must be > 0 [m]")
        if len(self.body_size_m) != 3 or min(self.body_size_m) <= 0:
            raise RobotDescriptionError(f"{who}: body_size_m needs 3 sizes > 0 [m]")

    def T_cam_body(self, seen: MarkerSeen) -> np.ndarray:
        """This robot's base_link in an observer's camera frame from a sighting of its marker
        (assuming its front face was seen; see :func:`coop_slam.markers.body_hypotheses`)."""
        if seen.assumed_size_m <= 0:
            raise RobotDescriptionError("a sighting's assumed marker size must be > 0 [m]")
        T = np.array(seen.T_cam_marker, float, copy=True)
        T[:3, 3] *= self.marker_size_m / seen.assumed_size_m
        return T @ invert(self.T_base_marker)


def describe(
    robot_id: int, sensor: str, T_base_cam: np.ndarray, markers: MarkerConfig, camera: str = ""
) -> RobotDescription:
    """A client's description of its robot from its own configuration."""
    return RobotDescription(
        robot_id=robot_id,
        sensor=sensor,
        T_base_cam=np.asarray(T_base_cam, float),
        marker_dictionary=markers.dictionary,
        marker_size_m=float(markers.marker_size_m),
        T_base_marker=markers.base_marker(),
        body_size_m=tuple(float(v) for v in markers.body_size_m),
        camera=camera,
    )
