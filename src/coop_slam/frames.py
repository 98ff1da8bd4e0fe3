"""A robot's TF frames (REP-105) and how the client's pose fits a base that has its own odometry.

By default the client owns the chain ``robot_k/map -> robot_k/odom -> robot_k/base_link ->
robot_k/camera_optical``: ``odom -> base_link`` is the visual odometry, ``map -> odom`` the team
map's correction. Almost every ROS base already publishes ``odom -> base_link`` (wheel odometry),
and a second publisher of one TF edge makes the tree flicker between two answers. With
``external_odom`` the client publishes only ``map -> odom`` (REP-105's localization edge): the
robot's pose in its map (visual, with the team's correction) composed with the inverse of the
base's own ``odom -> base_link`` at the same stamp. The names of odom, base and camera frames are
the robot's own; ``robot_k/map`` stays (the server's ``world -> robot_k/map`` edge names it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import require
from .geometry import invert


@dataclass
class FrameConfig:
    """A client's frame names ('' = ``robot_k/odom``, ``robot_k/base_link``,
    ``robot_k/camera_optical``) and who publishes which edge."""

    odom_frame: str = ""
    base_frame: str = ""
    camera_frame: str = ""
    # The base publishes odom -> base_link itself: the client publishes map -> odom only.
    external_odom: bool = False
    # base_link -> camera as a static transform from ~T_base_cam; false where the robot's
    # description (URDF, robot_state_publisher) publishes it already.
    publish_camera_tf: bool = True

    def validate(self) -> None:
        for name in ("odom_frame", "base_frame", "camera_frame"):
            value = getattr(self, name)
            require(
                value == value.strip() and not value.startswith("/"),
                f"~{name} '{value}' must be a TF frame id without a leading '/' or spaces",
            )

    def names(self, robot_id: int) -> "FrameNames":
        prefix = f"robot_{robot_id}"
        names = FrameNames(
            f"{prefix}/map",
            self.odom_frame or f"{prefix}/odom",
            self.base_frame or f"{prefix}/base_link",
            self.camera_frame or f"{prefix}/camera_optical",
        )
        require(
            len({names.map, names.odom, names.base, names.camera}) == 4,
            f"robot {robot_id}'s frames must differ: {names}",
        )
        return names


@dataclass(frozen=True)
class FrameNames:
    map: str
    odom: str
    base: str
    camera: str


def T_map_odom_over(T_map_base: np.ndarray, T_odom_base: np.ndarray) -> np.ndarray:
    """The ``map -> odom`` edge that puts the base where the map says it is, over a base whose
    own odometry says ``T_odom_base`` at the same stamp."""
    return np.asarray(T_map_base, float) @ invert(np.asarray(T_odom_base, float))
