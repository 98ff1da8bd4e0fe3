"""Server-assisted relocalization, DSM-SLAM's two steps: a lost robot that cannot relocalize in
its own map sends the place signature (BoW vector) of what its camera sees; the server finds the
place among the keyframes of the robot's group -- any robot's -- and answers with the local map
there: the map points those keyframes observe and their descriptors, in the robot's own map frame
and units. The client relocalizes into them (PnP) and carries on in its map, in the team's frame,
rather than starting a new map segment.

The robot's map frame is read off at its newest keyframe as the pose graph holds it, as the
server's pose corrections are (:meth:`TeamServer.client_frame`): points of another robot's
keyframe K go by K's optimized pose into the group frame, then into the robot's frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..bow.vocabulary import BowVector
from ..config import require
from ..geometry import invert, transform_points
from ..ids import KeyframeKey


@dataclass
class AssistConfig:
    """``config/server.yaml`` section ``assisted_relocalization``."""

    enabled: bool = True  # answer a lost robot's view with the team's local map there
    keyframes: int = 5  # the best-matching keyframe and its best covisible neighbours
    min_score: float = 0.02  # BoW L1 score below which no place is recognised [0, 1]

    def validate(self) -> None:
        require(self.keyframes >= 1, "assisted_relocalization.keyframes must be >= 1")
        require(0 <= self.min_score <= 1, "assisted_relocalization.min_score must be in [0, 1]")


@dataclass
class LocalMap:
    """What the server sends a lost robot: map points in the robot's map frame (its units)."""

    points_map: np.ndarray  # (M, 3) float32
    descriptors: np.ndarray  # (M, 32) uint8: the observing keyframe's descriptor of each point
    octaves: np.ndarray  # (M,) uint8: that keypoint's pyramid level
    keyframes: list[KeyframeKey] = field(default_factory=list)  # where they come from, best first
    score: float = 0.0  # BoW score of the best keyframe against the robot's view


def local_map_for(server, robot_id: int, bow: BowVector, config: AssistConfig) -> LocalMap | None:
    """The local map around the team keyframe that best matches ``bow`` among the keyframes of
    the group of the robot's current map (None: no place scores ``min_score``, or the server has
    no keyframe of the robot's map to place it by)."""
    config.validate()
    cur = server.current_map(robot_id)
    T_map_group = server.client_frame(cur)
    if T_map_group is None:
        return None
    db = server.store.database
    candidates = [
        c
        for c in db.query(bow, cur, 0, covisible=(), other_robots_only=False, min_score=0.0)
        if server.groups.same_group(c.key[0], cur) and c.score >= config.min_score
    ]
    if not candidates:
        return None
    best = max(candidates, key=lambda c: c.score)
    keys = [best.key] + [k for k in db.covisible(best.key) if k in server.store]
    keys = list(dict.fromkeys(keys))[: config.keyframes]
    points, descriptors, octaves, seen = [], [], [], set()
    scale = 1.0 / server.map_scale(cur)
    for key in keys:
        rec = server.store.record(key)
        observed = np.flatnonzero(rec.map_point_ids)
        fresh = [i for i in observed if (key[0], int(rec.map_point_ids[i])) not in seen]
        seen.update((key[0], int(rec.map_point_ids[i])) for i in fresh)
        if not fresh:
            continue
        # The map point of keypoint i, by the keyframe's optimized pose into the group frame.
        T_group_kfmap = server.T_group_cam(*key) @ invert(rec.T_map_cam)
        per_keypoint = rec.map_points_per_keypoint()[fresh]
        pts = transform_points(T_map_group @ T_group_kfmap, per_keypoint)
        points.append(pts * scale)
        descriptors.append(rec.descriptors[fresh])
        octaves.append(rec.octaves[fresh])
    if not points:
        return None
    return LocalMap(
        np.concatenate(points).astype(np.float32),
        np.concatenate(descriptors),
        np.concatenate(octaves),
        keys,
        float(best.score),
    )
