"""A client's odometry keyframes as the records it sends the server, expressed in the robot's map
frame.

The odometry's own map frame is its first camera frame. The robot's ``robot_k/map`` is the robot
body at start (z up, REP-103), so poses and points are moved by ``T_base_cam`` on the way out.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..camera import CameraModel
from ..geometry import transform_points
from ..vo.map import MapKeyframe
from ..vo.types import KEYFRAME_ACTIONS, VoEvent
from ..wire.bow_signature import word_counts
from ..wire.record import ACTION_NEW, ACTION_REMOVE, KeyframeRecord, PlaceSignature


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
        depth_image=np.frombuffer(kf.depth_image, np.uint8),
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


def signature_of(rec: KeyframeRecord, vocabulary) -> PlaceSignature:
    """The place signature of a new keyframe (low-bandwidth mode): its record without what it saw
    and its BoW vector in ``vocabulary`` (the server's)."""
    bow, _ = vocabulary.transform(rec.descriptors)
    counts = word_counts(bow, vocabulary.word_weights)
    bare = dataclasses.replace(
        rec,
        keypoints=np.zeros((0, 4), np.float32),
        octaves=np.zeros(0, np.uint8),
        descriptors=np.zeros((0, 32), np.uint8),
        depths_m=np.zeros(0, np.float32),
        map_point_ids=np.zeros(0, np.uint32),
        map_points=np.zeros((0, 3), np.float32),
        depth_image=np.zeros(0, np.uint8),
    )
    return PlaceSignature(bare, bow, counts)
