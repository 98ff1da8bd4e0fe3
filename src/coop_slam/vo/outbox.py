"""What a client sends the server: its odometry's keyframe events as :class:`KeyframeRecord` s,
expressed in the robot's map frame.

The odometry's own map frame is its first camera frame. The robot's ``robot_k/map`` is the robot
body at start (z up, REP-103), so poses and points are moved by ``T_base_cam`` on the way out.
"""

from __future__ import annotations

import numpy as np

from ..datasets.base import CameraModel
from ..geometry import transform_points
from ..keyframe_record import ACTION_NEW, ACTION_REMOVE, ACTION_UPDATE, KeyframeRecord
from .map import MapKeyframe
from .types import KEYFRAME_ACTIONS, VoEvent


def keyframe_record(
    kf: MapKeyframe,
    robot_id: int,
    camera: CameraModel,
    T_base_cam: np.ndarray | None = None,
    action: int = ACTION_NEW,
) -> KeyframeRecord:
    """The record of one keyframe snapshot (NEW or UPDATE), in the robot's map frame."""
    T_base_cam = np.eye(4) if T_base_cam is None else T_base_cam
    pts = (
        transform_points(T_base_cam, kf.map_points_xyz)
        if len(kf.map_points_xyz)
        else np.zeros((0, 3))
    )
    return KeyframeRecord(
        robot_id=robot_id,
        keyframe_id=int(kf.keyframe_id),
        stamp_s=float(kf.stamp_s),
        camera=camera,
        T_map_cam=T_base_cam @ kf.T_map_cam,
        keypoints=kf.keypoints_flat().reshape(-1, 4),
        octaves=kf.octaves,
        descriptors=kf.descriptors,
        depths_m=kf.depths_m,
        map_point_ids=kf.map_point_ids,
        map_points=pts.astype(np.float32),
        covisible_ids=kf.covisible_ids,
        covisible_weights=kf.covisible_weights,
        map_segment=int(kf.map_segment),
        action=action,
    )


def event_record(
    ev: VoEvent, robot_id: int, camera: CameraModel, T_base_cam: np.ndarray | None = None
) -> KeyframeRecord:
    """The record of a keyframe event (NEW, UPDATE or REMOVE); see :data:`KEYFRAME_ACTIONS`."""
    action = KEYFRAME_ACTIONS[ev.kind]
    if action == ACTION_REMOVE:
        return KeyframeRecord(
            robot_id=robot_id,
            keyframe_id=ev.keyframe_id,
            stamp_s=0.0,
            camera=camera,
            T_map_cam=np.eye(4),
            map_segment=ev.map_segment,
            action=action,
        )
    return keyframe_record(ev.keyframe, robot_id, camera, T_base_cam, action)


class DeltaUpdates:
    """Which updates go without what the keyframe saw (``KeyFrame.delta``): those whose keypoints,
    octaves, descriptors and depths are the ones sent with the keyframe as new (the server has
    them). ``enabled`` False: every update goes in full."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self._sent_static: dict[int, bytes] = {}  # keyframe id -> digest sent with it as new

    def delta(self, rec: KeyframeRecord) -> bool:
        """Whether ``rec`` (about to be sent) may leave out what the keyframe saw."""
        if rec.action == ACTION_NEW:
            self._sent_static[rec.keyframe_id] = rec.static_digest()
            return False
        if rec.action == ACTION_UPDATE and self.enabled:
            return self._sent_static.get(rec.keyframe_id) == rec.static_digest()
        self._sent_static.pop(rec.keyframe_id, None)
        return False
