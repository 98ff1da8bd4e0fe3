"""Applying the server's optimized keyframe poses to a client's own map (pose-graph sharing back to
the robot).

After merges and loop closures the team map holds better poses for a robot's keyframes than its
own odometry. :func:`apply_keyframe_corrections` moves the client's map onto them, as ORB-SLAM's
loop correction does after its essential-graph optimization: each corrected keyframe takes its
new pose; keyframes newer than the newest corrected one (the server has not seen them yet) move
rigidly with it; every map point moves with its reference keyframe (the oldest keyframe that
observes it, normally the one that created it), so keyframes, points and the next frame's
tracking stay consistent. Keyframes the server did not correct (moved less than its threshold, or
unknown to it) stay where they are.

What the client sends the server stays in its *odometry frame*: each keyframe keeps the correction
applied to it (``MapKeyframe.T_odo_map``) and its snapshots undo it. Sending corrected poses
instead would turn the server's own estimate into the odometry measurements of its next
optimization, which then drifts (measured on the synthetic team world: both the server's and the
client's keyframe ATE got worse). The server reads the robot's map frame off its newest keyframe's
odometry pose (:meth:`coop_slam.team.server.TeamServer.pose_corrections`), so corrections bend the
past and leave where the robot is now (nearly) in place.

Pure core: numpy in, numpy out; the caller holds ``Map.lock``.
"""

from __future__ import annotations

import numpy as np

from ..geometry import invert
from .map import Map


def apply_keyframe_corrections(
    vmap: Map, T_map_cam_new: dict[int, np.ndarray]
) -> dict[int, np.ndarray]:
    """Move the map's keyframes to ``T_map_cam_new`` (keyframe id -> corrected pose, the map's own
    frame and units) and their points with them; returns the correction ``C_k`` applied to each
    moved keyframe (``T_map_cam_new = C_k @ T_map_cam_old``, a left multiplication in the map
    frame). Ids not in the map are ignored."""
    C: dict[int, np.ndarray] = {}
    for k, T_new in T_map_cam_new.items():
        kf = vmap.keyframes.get(int(k))
        if kf is not None:
            C[int(k)] = _orthonormal(np.asarray(T_new, float) @ invert(kf.T_map_cam))
    if not C:
        return {}
    newest = max(C)
    for k in vmap.keyframes:
        if k > newest:
            C[k] = C[newest]
    for k, Ck in C.items():
        kf = vmap.keyframes[k]
        kf.T_map_cam = _orthonormal(Ck @ kf.T_map_cam)
        kf.T_odo_map = _orthonormal(kf.T_odo_map @ invert(Ck))
    pts = vmap.points
    ids = pts.alive_ids()
    ids = ids[ids > 0]
    ref = np.fromiter(
        (min(pts.obs[int(p)], default=0) for p in ids), dtype=np.int64, count=len(ids)
    )
    for k, Ck in C.items():
        rows = ids[ref == k]
        if len(rows):
            pts.xyz[rows] = pts.xyz[rows] @ Ck[:3, :3].T + Ck[:3, 3]
            pts.normal[rows] = pts.normal[rows] @ Ck[:3, :3].T
    vmap.epoch += 1
    return C


def _orthonormal(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation projected onto SO(3): corrections compose with poses again and
    again, and round-off must not accumulate into a pose the server refuses."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    out = T.copy()
    out[:3, :3] = R
    return out
