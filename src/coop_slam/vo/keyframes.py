"""When a tracked frame becomes a keyframe (ORB-SLAM2's NeedNewKeyFrame for RGB-D, with a floor on
the tracked points; for a monocular camera its monocular rules) and how: the keyframe keeps the
frame's keypoints, its tracked map points, and new map points from depth for the keypoints that
matched none (a monocular keyframe has no depth: local mapping triangulates its new points)."""

from __future__ import annotations

from concurrent.futures import Future

import numpy as np

from ..geometry import transform_points
from .config import VoConfig
from .features import FrameFeatures
from .map import Map, MapKeyframe
from .tracking import Tracked


class KeyframePolicy:
    """The keyframe decision (see module docstring); caches the reference keyframe's point count
    for a few frames, since counting observations is a Python loop. ``close_depth_m``: the
    sensor's depth of reliable points.

    ``monocular`` (no depth): ORB-SLAM2's monocular rules. There are no close points; the
    reference keyframe's points count when 3 keyframes see them (2 while the map has 2
    keyframes); a frame tracking fewer than ``keyframes.ref_ratio`` (monocular) of them becomes a
    keyframe when ``keyframes.max_frames`` passed or local mapping is free and
    ``keyframes.min_frames`` (monocular) passed. The floor
    ``keyframes.min_tracked`` does not apply: every weakly tracked frame would become a keyframe,
    with baselines too short to triangulate from."""

    def __init__(self, config: VoConfig, close_depth_m: float, monocular: bool = False):
        self.config = config.for_sensor("mono") if monocular else config
        self.close_depth_m = close_depth_m
        self.monocular = monocular
        self._n_ref_cache: tuple = (None, 0)

    def reset(self) -> None:
        self._n_ref_cache = (None, 0)

    def needed(
        self,
        vmap: Map,
        feats: FrameFeatures,
        tracked: Tracked,
        ref_kf_id: int,
        frames_since_kf: int,
        frames_processed: int,
        mapping_free: bool,
    ) -> bool:
        """Whether the tracked frame becomes a keyframe. ``mapping_free``: local mapping is idle
        or has few keyframes queued (RGB-D and stereo insert even while mapping is busy)."""
        cfg = self.config
        if frames_since_kf + 1 < cfg.keyframes.min_frames:
            return False
        with vmap.lock:
            # ORB-SLAM2 counts an observation with depth twice and asks for 3 (2 with <= 2
            # keyframes): in keyframes, that is 2 (1). Monocular observations count once.
            min_obs = 2 if len(vmap.keyframes) > 2 else 1
            if self.monocular:
                min_obs += 1
            ref = vmap.keyframes.get(tracked.ref_kf_id) or vmap.keyframes.get(ref_kf_id)
            n_ref = 0
            if ref is not None:
                key = (ref.keyframe_id, min_obs, frames_processed // 5)
                if self._n_ref_cache[0] == key:
                    n_ref = self._n_ref_cache[1]
                else:
                    obs = vmap.points.obs
                    pids = ref.map_point_ids[ref.map_point_ids > 0].tolist()
                    n_ref = sum(1 for p in pids if len(obs.get(p, ())) >= min_obs)
                    self._n_ref_cache = (key, n_ref)
        if self.monocular:
            c1a = frames_since_kf + 1 >= cfg.keyframes.max_frames
            c2 = tracked.n < cfg.keyframes.ref_ratio * n_ref and (
                tracked.n > cfg.keyframes.min_inliers
            )
            c1b = mapping_free and frames_since_kf + 1 >= cfg.keyframes.min_frames
            return (c1a or c1b) and c2
        d = feats.depths_m
        close = (d > 0) & (d <= self.close_depth_m)
        tracked_mask = np.zeros(len(feats), bool)
        tracked_mask[tracked.kp_idx] = True
        n_tracked_close = int((close & tracked_mask).sum())
        n_untracked_close = int((close & ~tracked_mask).sum())
        need_close = (
            n_tracked_close < cfg.keyframes.close_tracked
            and n_untracked_close > cfg.keyframes.close_untracked
        )
        c1a = frames_since_kf + 1 >= cfg.keyframes.max_frames
        c1b = mapping_free
        c1c = tracked.n < 0.25 * n_ref or need_close
        # Besides ORB-SLAM2's ratio, a floor on the tracked points: with few keyframes, few points
        # have two observations, and the ratio alone lets tracking thin out to the frames that
        # carry most of the per-frame error (docs/tuning.md).
        weak = tracked.n < cfg.keyframes.min_tracked
        c2 = (tracked.n < cfg.keyframes.ref_ratio * n_ref or need_close or weak) and (
            tracked.n > cfg.keyframes.min_inliers
        )
        return (c1a or c1b or c1c) and c2


def add_keyframe(
    vmap: Map,
    kf_id: int,
    stamp_s: float,
    map_segment: int,
    feats: FrameFeatures,
    T_map_cam: np.ndarray,
    kp_idx,
    point_ids,
    config: VoConfig,
    scales: np.ndarray,
    depth_image: bytes | Future = b"",
) -> MapKeyframe:
    """Create keyframe ``kf_id`` from the frame in ``vmap``: its tracked map points (``kp_idx``
    -> ``point_ids``) and new map points from depth for unmatched keypoints, closest first."""
    n = len(feats)
    with vmap.lock:
        pts = vmap.points
        mp_ids = np.zeros(n, np.uint32)
        point_ids = np.asarray(point_ids, dtype=np.int64)
        kp_idx = np.asarray(kp_idx, dtype=np.int64)
        alive = pts.is_alive(point_ids)
        kp_idx, point_ids = kp_idx[alive], point_ids[alive]
        _, first = np.unique(point_ids, return_index=True)  # a point is observed once per keyframe
        mp_ids[kp_idx[first]] = point_ids[first]
        # New points: unmatched keypoints with depth, closest (best depth) first. Points beyond
        # close_depth_m still help as monocular observations.
        d = feats.depths_m
        cand = np.flatnonzero((d > 0) & (mp_ids == 0))
        cand = cand[np.argsort(d[cand], kind="stable")][: config.mapping.new_points_max]
        if len(cand):
            xyz = transform_points(T_map_cam, feats.points_cam[cand])
            ray = xyz - T_map_cam[:3, 3]
            dist = np.linalg.norm(ray, axis=1)
            new_ids = pts.add(
                xyz,
                feats.descriptors[cand],
                feats.angle_deg[cand],
                ray / dist[:, None],
                dist * scales[feats.octaves[cand].astype(int)],
                vmap.kf_seq + 1,
            )
            mp_ids[cand] = new_ids.astype(np.uint32)
        kf = MapKeyframe(
            keyframe_id=kf_id,
            stamp_s=float(stamp_s),
            map_segment=map_segment,
            T_map_cam=np.array(T_map_cam, dtype=float),
            uv_px=feats.uv_px.astype(np.float32),
            size_px=feats.size_px,
            angle_deg=feats.angle_deg,
            octaves=feats.octaves,
            descriptors=feats.descriptors,
            depths_m=feats.depths_m,
            map_point_ids=mp_ids,
            depth_image=depth_image,
        )
        vmap.add_keyframe(kf)
        vmap.update_covisibility(kf_id)
    return kf
