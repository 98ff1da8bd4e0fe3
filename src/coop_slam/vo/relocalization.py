"""Finding the camera again without a motion prior: PnP RANSAC of the frame's keypoints against a
keyframe's map points (brute-force descriptor matching, :func:`coop_slam.registration.pnp_ransac`,
then the odometry's own pose optimization), and relocalization against the robot's recent
keyframes, a few per frame so the time per frame stays bounded."""

from __future__ import annotations

import numpy as np

from ..descriptors import match_ratio
from ..geometry import invert
from ..registration.camera import RegistrationError
from ..registration.pnp import pnp_ransac
from .config import VoConfig
from .features import FrameFeatures, inv_sigma2
from .map import Map
from .pose_opt import optimize_pose
from .sensor import Sensor
from .tracking import LocalMapTracker, Tracked


def pnp_against_keyframe(
    vmap: Map, feats: FrameFeatures, kf_id: int, config: VoConfig, sensor: Sensor
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(T_map_cam, matched map point ids) of the frame from a keyframe's map points, or
    (None, None)."""
    with vmap.lock:
        kf = vmap.keyframes.get(kf_id)
        if kf is None:
            return None, None
        idx = np.flatnonzero(kf.map_point_ids)
        pids = kf.map_point_ids[idx].astype(np.int64)
        alive = vmap.points.is_alive(pids)
        idx, pids = idx[alive], pids[alive]
        xyz = vmap.points.xyz[pids].copy()
        desc = kf.descriptors[idx]
    T_map_cam, matched = pnp_against_points(feats, xyz, desc, config, sensor)
    return (None, None) if T_map_cam is None else (T_map_cam, pids[matched])


def pnp_against_points(
    feats: FrameFeatures, xyz: np.ndarray, desc: np.ndarray, config: VoConfig, sensor: Sensor
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(T_map_cam, indices of the points it matched) of the frame from 3D points in a map frame
    and their descriptors, or (None, None): brute-force matching, EPnP RANSAC, pose
    optimization."""
    cfg = config
    if (
        len(xyz) < cfg.relocalization.pnp_min_inliers
        or len(feats) < cfg.relocalization.pnp_min_inliers
    ):
        return None, None
    m = match_ratio(
        feats.descriptors,
        desc,
        ratio=cfg.relocalization.pnp_ratio,
        max_distance=cfg.tracking.max_descriptor_distance,
    )
    if len(m) < cfg.relocalization.pnp_min_inliers:
        return None, None
    obj = np.asarray(xyz, np.float64)[m[:, 1]]
    img = feats.uv_px[m[:, 0]].astype(np.float64)
    K = sensor.camera.K
    try:
        res = pnp_ransac(
            obj,
            img,
            K,
            reprojection_px=cfg.relocalization.pnp_reprojection_px,
            max_iterations=cfg.relocalization.pnp_iterations,
            confidence=0.99,
            method="epnp",
            min_inliers=cfg.relocalization.pnp_min_inliers,
            refine=False,
        )
    except RegistrationError:  # degenerate points: no pose, as RANSAC finding none
        return None, None
    if res.T_camB_camA is None:
        return None, None
    inl = np.flatnonzero(res.inliers)
    kp = m[inl, 0]
    T_cam_map, good = optimize_pose(
        res.T_camB_camA,
        obj[inl],
        feats.uv_px[kp],
        feats.u_right_px[kp],
        inv_sigma2(cfg, feats.octaves[kp]),
        K,
        sensor.bf,
    )
    if good.sum() < cfg.relocalization.pnp_min_inliers:
        return None, None
    return invert(T_cam_map), m[inl[good], 1]


class Relocalizer:
    """Tries the robot's ``reloc_keyframes`` newest keyframes in turn,
    ``reloc_keyframes_per_frame`` per lost frame."""

    def __init__(self, config: VoConfig, sensor: Sensor, tracker: LocalMapTracker):
        self.config = config
        self.sensor = sensor
        self.tracker = tracker
        self._cursor = 0

    def reset(self) -> None:
        self._cursor = 0

    def try_frame(
        self, vmap: Map, feats: FrameFeatures, ref_kf_id: int
    ) -> tuple[Tracked, int] | None:
        """(tracked, keyframe it relocalized against), or None after this frame's attempts."""
        cfg = self.config
        with vmap.lock:
            candidates = sorted(vmap.keyframes, reverse=True)[: cfg.relocalization.keyframes]
        n_try = min(cfg.relocalization.keyframes_per_frame, len(candidates))
        for i in range(n_try):
            kf_id = candidates[(self._cursor + i) % len(candidates)]
            T0, pids = pnp_against_keyframe(vmap, feats, kf_id, cfg, self.sensor)
            if T0 is None:
                continue
            tracked = self.tracker.track(vmap, feats, T0, pids, ref_kf_id)
            if tracked is not None and tracked.n >= cfg.relocalization.min_inliers:
                return tracked, kf_id
        self._cursor += n_try
        return None
