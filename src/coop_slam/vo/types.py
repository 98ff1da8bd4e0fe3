"""Results, events and the exception of the visual odometry."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import CoopSlamError
from .map import MapKeyframe


class VoError(CoopSlamError):
    """Input the visual odometry cannot process
    (empty or mis-sized image, wrong depth type, ...)."""


# Tracking states of TrackResult.state.
STATE_INITIALIZING = "initializing"  # no map yet (waiting for a frame with enough depth)
STATE_OK = "ok"
STATE_LOST = "lost"  # pose unknown; T_map_cam is the last good one
STATE_RELOCALIZED = "relocalized"  # tracking recovered against the robot's own keyframes
STATE_NEW_SEGMENT = "new_segment"  # a new map was started: T_map_cam is in a new map frame

# Kinds of VoEvent. The first three map onto the records' ACTION_NEW / _UPDATE / _REMOVE.
EVENT_KEYFRAME_NEW = "keyframe_new"
EVENT_KEYFRAME_UPDATE = "keyframe_update"
EVENT_KEYFRAME_REMOVE = "keyframe_remove"
EVENT_NEW_SEGMENT = "new_segment"  # all later keyframes belong to map_segment; earlier ones do not
EVENT_WARNING = "warning"  # e.g. timestamps going backwards (the map was reset)

KEYFRAME_ACTIONS = {EVENT_KEYFRAME_NEW: 0, EVENT_KEYFRAME_UPDATE: 1, EVENT_KEYFRAME_REMOVE: 2}


@dataclass
class TrackResult:
    stamp_s: float
    T_map_cam: np.ndarray  # (4, 4); last good pose while lost
    ok: bool
    state: str  # one of STATE_*
    map_segment: int
    track_ms: float  # wall time of track() [ms]
    cpu_ms: float = 0.0  # CPU time of the calling thread in track() [ms] (load-independent)
    n_features: int = 0
    n_tracked: int = 0  # map points matched and inlying after pose optimization
    new_keyframe_id: int = 0  # id of the keyframe created from this frame, 0 = none
    n_keyframes: int = 0  # keyframes in the current map segment
    message: str = ""


@dataclass
class VoEvent:
    kind: str  # one of EVENT_*
    map_segment: int
    keyframe_id: int = 0
    keyframe: MapKeyframe | None = None  # snapshot for NEW / UPDATE (None for REMOVE)
    message: str = ""
    extra: dict = field(default_factory=dict)
