"""Who is who: a *robot* is a client started with its id (``robot_k``); a *map* is one map
segment of a robot as the server holds it. A robot's first map has the robot's id; a later map
segment (tracking lost for good, a restarted client) gets a map id of its own above every
robot's (:mod:`coop_slam.team.segments`). Groups, the pose graph, scales and the keyframe store
work on map ids; what a user sees is per robot. The two are distinct types, so a signature says
which it takes."""

from __future__ import annotations

from typing import NewType

RobotId = NewType("RobotId", int)
MapId = NewType("MapId", int)
# gtsam.Symbol keys a map by one character: a byte from 'a' (see team.pose_graph)
MAX_MAP_ID = 255 - ord("a")
MAX_ROBOT_ID = MAX_MAP_ID  # a robot's first map has its id (robot ids travel as uint16)
KeyframeKey = tuple[MapId, int]  # (map, keyframe id): a keyframe on the server
