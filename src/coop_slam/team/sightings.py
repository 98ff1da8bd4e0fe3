"""Marker sightings placed with the sighted robot's own description: its marker's size and mount
and its camera's mount (see :mod:`coop_slam.robot_description`), never one team-wide value."""

from __future__ import annotations

import logging

import numpy as np

from ..robot_description import MarkerSeen, RobotDescription

log = logging.getLogger(__name__)


class SightingPlacer:
    def __init__(self):
        self.descriptions: dict[int, RobotDescription] = {}
        self._undescribed_said: set[int] = set()

    def describe(self, description: RobotDescription) -> None:
        """A robot's own description (its latched ``/robot_k/description``); a new one replaces
        the old (a client restarted with another mount)."""
        old = self.descriptions.get(description.robot_id)
        self.descriptions[description.robot_id] = description
        if old is None or not np.allclose(old.T_base_cam, description.T_base_cam):
            log.info(
                "robot %d: %s camera%s at %s m in base_link, marker %.3f m",
                description.robot_id,
                description.sensor,
                f" ({description.camera})" if description.camera else "",
                np.round(description.T_base_cam[:3, 3], 3).tolist(),
                description.marker_size_m,
            )

    def place(self, robot_b: int, marker: MarkerSeen | None):
        """(robot b's body in the observer's camera, b's camera in its body) of a sighting of
        b's marker, from b's own description; (None, None) without one: the sighting then
        says only when."""
        if marker is None:
            return None, None
        d = self.descriptions.get(robot_b)
        if d is None:
            if robot_b not in self._undescribed_said:
                self._undescribed_said.add(robot_b)
                log.warning(
                    "robot %d has not described itself (no /robot_%d/description): sightings "
                    "of its marker say only when, not where (is its client older than the "
                    "server?)",
                    robot_b,
                    robot_b,
                )
            return None, None
        return d.T_cam_body(marker), d.T_base_cam
