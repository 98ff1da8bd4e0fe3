"""Tracking a frame against the local map: the map points of the keyframes that share points with
the last frame (and their best covisible keyframes), projected with the predicted pose, matched by
descriptor in a window around each projection, and a robust motion-only pose optimization
(:mod:`.pose_opt`) -- twice: a wide search around the prediction, then a narrow one around the
first estimate."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import chain

import numpy as np

from ..geometry import invert
from .config import VoConfig
from .features import FrameFeatures, inv_sigma2
from .map import Map
from .matching import project_points, search_by_projection
from .pose_opt import optimize_pose
from .sensor import Sensor
from .shared_work import shared_worker


@dataclass
class Tracked:
    """Outcome of a local-map search: pose and the (keypoint, map point) inliers."""

    T_map_cam: np.ndarray
    kp_idx: np.ndarray  # keypoint indices of the frame
    point_ids: np.ndarray  # map point ids they matched
    ref_kf_id: int  # the keyframe sharing most points with the frame (0 = unknown)

    @property
    def n(self) -> int:
        return len(self.kp_idx)


@dataclass
class LocalMap:
    """Copied arrays of the local map's points (ids (P,) and their attributes)."""

    ref_kf_id: int
    ids: np.ndarray
    xyz: np.ndarray
    desc: np.ndarray
    angle: np.ndarray
    normal: np.ndarray
    max_dist: np.ndarray


class LocalMapTracker:
    def __init__(self, config: VoConfig, sensor: Sensor, scales: np.ndarray):
        self.config = config
        self.sensor = sensor
        self.camera = sensor.camera
        self.K = sensor.camera.K
        self.bf = sensor.bf
        self.scales = scales

    def local_map(self, vmap: Map, seed_point_ids: np.ndarray, ref_kf_id: int) -> LocalMap | None:
        """Local keyframes (sharing points with the seed points, plus their best covisibles; the
        reference keyframe, else the newest, when no seed point is alive) and their map points."""
        cfg = self.config
        with vmap.lock:
            pts = vmap.points
            seed = (
                seed_point_ids[pts.is_alive(seed_point_ids)]
                if len(seed_point_ids)
                else seed_point_ids
            )
            obs = pts.obs
            sharing = np.fromiter(chain.from_iterable([obs[p] for p in seed.tolist()]), np.int64)
            if len(sharing) == 0:
                fallback = (
                    ref_kf_id if ref_kf_id in vmap.keyframes else max(vmap.keyframes, default=0)
                )
                if fallback == 0:
                    return None
                sharing = np.array([fallback], np.int64)
            # By points shared, ties to the keyframe met first (as Counter.most_common ranks).
            kf_ids, first, counts = np.unique(sharing, return_index=True, return_counts=True)
            ranked = kf_ids[np.lexsort((first, -counts))].tolist()
            ref = ranked[0]
            local = ranked[: cfg.tracking.local_keyframes]
            chosen = set(local)
            for k in list(local):
                if len(local) >= cfg.tracking.local_keyframes:
                    break
                for c in vmap.best_covisible(k, 10):
                    if c not in chosen:
                        chosen.add(c)
                        local.append(c)
                        if len(local) >= cfg.tracking.local_keyframes:
                            break
            # A mask over the point store rather than np.unique's sort of ~10^4 ids.
            member = np.zeros(len(pts.alive), bool)
            for k in local:
                member[vmap.keyframes[k].map_point_ids] = True
            member[0] = False
            ids = np.flatnonzero(member & pts.alive)
            return LocalMap(
                ref,
                ids,
                pts.xyz[ids].copy(),
                pts.desc[ids].copy(),
                pts.angle[ids].copy(),
                pts.normal[ids].copy(),
                pts.max_dist[ids].copy(),
            )

    def track(
        self,
        vmap: Map,
        feats: FrameFeatures,
        T_map_cam_pred: np.ndarray,
        seed_point_ids,
        ref_kf_id: int,
    ) -> Tracked | None:
        """The frame's pose from the local map around the seed points, starting from the
        predicted pose; None when too few points track."""
        cfg = self.config
        # The search's KD tree is built in the worker thread (without Python's lock) while this
        # one gathers the local map.
        tree = shared_worker().submit(feats.tree)
        local = self.local_map(vmap, np.asarray(seed_point_ids, dtype=np.int64), ref_kf_id)
        if not tree.cancel():
            tree.result()
        if local is None or len(feats) == 0:
            return None
        ids, xyz = local.ids, local.xyz
        info = inv_sigma2(cfg, feats.octaves)
        size = (self.camera.width, self.camera.height)
        T_cam_map = invert(T_map_cam_pred)
        best = None
        for stage, radius in enumerate(
            (cfg.tracking.search_radius_px, cfg.tracking.search_radius_refine_px)
        ):
            proj = project_points(
                T_cam_map, xyz, self.K, self.bf, size, self.scales, local.max_dist, local.normal
            )
            radii = (radius, 2.0 * radius) if stage == 0 else (radius,)
            for r in radii:
                pi, kj, _ = search_by_projection(
                    proj,
                    local.desc,
                    feats,
                    r,
                    self.scales,
                    cfg.tracking.max_descriptor_distance,
                    cfg.tracking.ratio_test,
                    point_angle_deg=local.angle,
                    check_orientation=cfg.tracking.check_orientation and stage == 0,
                )
                if len(pi) < cfg.tracking.min_tracked:
                    continue
                rows = proj.index[pi]
                T_opt, inl = optimize_pose(
                    T_cam_map,
                    xyz[rows],
                    feats.uv_px[kj],
                    feats.u_right_px[kj],
                    info[kj],
                    self.K,
                    self.bf,
                    cfg.tracking.pose_rounds,
                    cfg.tracking.pose_iterations,
                    cfg.tracking.chi2_mono,
                    cfg.tracking.chi2_stereo,
                )
                if inl.sum() >= cfg.tracking.min_tracked:
                    cand = (T_opt, kj[inl], rows[inl], proj)
                    if best is None or len(cand[1]) >= 0.9 * len(best[1]):
                        best = cand
                    T_cam_map = T_opt
                    break
            if best is None:
                return None
        T_cam_map, kp_idx, rows, proj = best
        with vmap.lock:
            pts = vmap.points
            seen = ids[proj.index]
            pts.visible[seen] += 1
            pts.found[ids[rows]] += 1
        return Tracked(invert(T_cam_map), kp_idx, ids[rows], local.ref_kf_id)
