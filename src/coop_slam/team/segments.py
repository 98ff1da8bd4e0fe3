"""A robot's map segments as maps of their own on the server.

A client starts a new map segment when tracking is lost for good or when it restarts: a new map
frame that nothing relates to the one before (its keyframe poses are in a different frame). The
server treats each (robot, segment) as a map of its own with a *map id*: a robot's first segment
has the robot's id, later ones get ids above every robot's, in order of arrival. Everything that
holds maps (groups, pose graph keys, scales, the keyframe store) works on map ids, so a new
segment merges back into its robot's group by place recognition or rendezvous like any other
robot's map; what the server shows per robot is its newest segment's map and the keyframes of
its segments in that map's group.
"""

from __future__ import annotations

from ..errors import CoopSlamError
from ..ids import MAX_MAP_ID, MapId, RobotId


class SegmentError(CoopSlamError):
    """More map segments than the server can key."""


class MapSegments:
    def __init__(self, robots):
        self.robots = sorted(int(r) for r in robots)
        self._ids: dict[tuple[int, int], int] = {}
        self._robot: dict[int, int] = {}
        self._current: dict[int, int] = {}  # robot -> map id of its newest segment
        self._next = max(self.robots, default=0) + 1

    def map_id(self, robot_id: RobotId, segment: int) -> tuple[MapId, bool]:
        """The map id of a robot's segment, and whether it is new."""
        key = (int(robot_id), int(segment))
        if key in self._ids:
            return self._ids[key], False
        if robot_id not in self._current:
            mid = int(robot_id)  # the robot's first segment (whatever its number)
        else:
            if self._next > MAX_MAP_ID:
                raise SegmentError(
                    f"robot {robot_id} started map segment {segment}: the server keys at most "
                    f"{MAX_MAP_ID} maps"
                )
            mid, self._next = self._next, self._next + 1
        self._ids[key] = mid
        self._robot[mid] = int(robot_id)
        if segment >= max((s for (r, s) in self._ids if r == robot_id), default=segment):
            self._current[int(robot_id)] = mid
        return mid, True

    def find(self, robot_id: RobotId, segment: int) -> MapId | None:
        """The map id of a robot's segment, None when it has not been seen."""
        return self._ids.get((int(robot_id), int(segment)))

    def robot_of(self, map_id: MapId) -> RobotId:
        return self._robot.get(int(map_id), int(map_id))

    def current(self, robot_id: RobotId) -> MapId:
        """The map id of the robot's newest segment (its id before it sent anything)."""
        return self._current.get(int(robot_id), int(robot_id))

    def maps_of(self, robot_id: RobotId) -> list[MapId]:
        return sorted(m for m, r in self._robot.items() if r == robot_id) or [int(robot_id)]

    def segment_of(self, map_id: MapId) -> int:
        return next((s for (r, s), m in self._ids.items() if m == map_id), 0)
