"""Client visual odometry: ORB-SLAM-style RGB-D, stereo or monocular tracking and local mapping
(pure core, no rospy).

Entry point: :class:`VisualOdometry` (``track`` per frame, keyframes / map points / events out).
"""

from .config import VoConfig
from .map import MapKeyframe
from .pipeline import VisualOdometry
from .types import (
    EVENT_KEYFRAME_NEW,
    EVENT_KEYFRAME_REMOVE,
    EVENT_KEYFRAME_UPDATE,
    EVENT_NEW_SEGMENT,
    EVENT_WARNING,
    KEYFRAME_ACTIONS,
    STATE_INITIALIZING,
    STATE_LOST,
    STATE_NEW_SEGMENT,
    STATE_OK,
    STATE_RELOCALIZED,
    TrackResult,
    VoError,
    VoEvent,
)

__all__ = [
    "EVENT_KEYFRAME_NEW",
    "EVENT_KEYFRAME_REMOVE",
    "EVENT_KEYFRAME_UPDATE",
    "EVENT_NEW_SEGMENT",
    "EVENT_WARNING",
    "KEYFRAME_ACTIONS",
    "STATE_INITIALIZING",
    "STATE_LOST",
    "STATE_NEW_SEGMENT",
    "STATE_OK",
    "STATE_RELOCALIZED",
    "MapKeyframe",
    "VisualOdometry",
    "TrackResult",
    "VoConfig",
    "VoError",
    "VoEvent",
]
