"""Keyframe messages as recorded (a run's bag, or live on the topic): today's, and those of runs
recorded before each kind had its own message type, as the server's worker and a run's report
take them."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..camera import SENSORS
from ..errors import CoopSlamError
from ..registration.camera import backproject
from ..wire import legacy
from ..wire.codec import keypoints_and_depths, pose_of
from ..wire.legacy import is_legacy
from ..wire.messages import KIND_DELTA, KIND_KEYFRAME, KIND_REMOVAL, KIND_SIGNATURE, KeyframeMessage
from ..wire.record import ACTION_REMOVE
from .wire_bridge import from_ros

KEYFRAME_TOPIC = "/robot_{}/keyframes"


def keyframe_message(msg):
    """A recorded keyframe message for :meth:`coop_slam.team.worker.ServerWorker.intake`:
    today's as a wire message, an older one as it is (the worker reads it with
    :mod:`coop_slam.wire.legacy`)."""
    return (
        msg
        if is_legacy(msg) or isinstance(msg, KeyframeMessage)
        else from_ros(msg, KeyframeMessage)
    )


def is_removal(msg) -> bool:
    """A removal (it carries no stamp)."""
    if is_legacy(msg):
        return msg.action == ACTION_REMOVE
    return msg.kind == KIND_REMOVAL


class KeyframeSeen(NamedTuple):
    """What a run's report takes from a keyframe message."""

    keyframe_id: int
    map_segment: int
    stamp_s: float
    removal: bool
    T_map_cam: np.ndarray | None  # None: not readable
    sensor: str | None  # None: the message does not say (a delta update)
    points_cam: np.ndarray | None  # keypoints with depth, camera frame; None: not carried
    kind: str  # what it carried: whole, delta, signature or removal


_KIND_NAMES = {
    KIND_KEYFRAME: "whole",
    KIND_DELTA: "delta",
    KIND_SIGNATURE: "signature",
    KIND_REMOVAL: "removal",
}


def keyframe_seen(msg) -> KeyframeSeen:
    """A recorded keyframe message (either format) as a run's report sees it."""
    msg = keyframe_message(msg)
    stamp_s = msg.header.stamp.to_sec()
    if is_removal(msg):
        return KeyframeSeen(
            msg.keyframe_id, msg.map_segment, stamp_s, True, None, None, None, "removal"
        )
    if is_legacy(msg):
        delta = getattr(msg, "delta", False)
        body, sensor_type, kind = msg, msg.camera.sensor_type, "delta" if delta else "whole"
        points = None if delta else _legacy_points(msg)
    else:
        kind = _KIND_NAMES.get(msg.kind, "whole")
        body = (msg.keyframe or msg.delta or msg.signature)[0]
        camera = getattr(body, "camera", None)
        sensor_type = None if camera is None else camera.sensor_type
        points = _points(body) if msg.kind == KIND_KEYFRAME else None
        if msg.signature:
            points = np.zeros((0, 3), np.float32)
    try:
        T = pose_of(body.pose, "pose")
    except CoopSlamError:
        T = None
    sensor = (
        SENSORS[sensor_type] if sensor_type is not None and sensor_type < len(SENSORS) else None
    )
    return KeyframeSeen(msg.keyframe_id, msg.map_segment, stamp_s, False, T, sensor, points, kind)


def _backprojected(uv: np.ndarray, z: np.ndarray, c) -> np.ndarray:
    ok = (z > 0) & np.isfinite(z)
    if len(z) != len(uv) or not (c.fx > 0 and c.fy > 0):
        return np.zeros((0, 3), np.float32)
    K = np.array([[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])
    return backproject(uv[ok, :2], z[ok], K).astype(np.float32)


def _points(body) -> np.ndarray:
    """(N, 3) float32 points of a whole keyframe's keypoints with depth, in its camera frame
    (empty when the message is malformed: the report then leaves the keyframe out)."""
    try:
        uv, z = keypoints_and_depths(body)
        return _backprojected(uv, z, body.camera)
    except (ValueError, TypeError, CoopSlamError):
        return np.zeros((0, 3), np.float32)


def _legacy_points(msg) -> np.ndarray:
    try:
        kp, z = legacy.keypoints_and_depths(msg, "keyframe")
        kp = kp.reshape(-1, 2 if kp.size == 2 * len(z) else 4)  # u, v (or + size, angle)
        return _backprojected(kp, z, msg.camera)
    except (ValueError, TypeError, CoopSlamError):
        return np.zeros((0, 3), np.float32)
