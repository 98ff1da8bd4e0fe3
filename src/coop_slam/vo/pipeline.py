"""ORB-SLAM-style RGB-D visual odometry of one client (pure core, no rospy).

``RgbdOdometry.track(stamp_s, image, depth_m)`` runs, per frame:

1. grid-bucketed ORB features with depth (:mod:`.features`);
2. prediction with a constant-velocity model, projection matching of the local map (the points of
   the keyframes that share points with the last frame, and their best covisible keyframes) and a
   robust motion-only pose optimization with a stereo-like depth residual (:mod:`.pose_opt`), twice:
   a wide search around the prediction, then a narrow one around the first estimate;
3. if that fails, PnP RANSAC against the reference keyframe, then the local-map search again;
4. the keyframe decision of ORB-SLAM2 (RGB-D): tracked points below a ratio of the reference
   keyframe's, or too few tracked close points while many are untracked; the keyframe gets new map
   points from depth at once (so the next frames can track them) and goes to local mapping
   (:mod:`.local_mapping`: fusion, point culling, GTSAM local BA, keyframe culling).

When tracking fails the odometry is *lost*: it tries to relocalize against its own recent keyframes
(brute-force descriptor matching + PnP RANSAC + local-map search), a few keyframes per frame so the
time per frame stays bounded; after ``max_lost_frames`` failures it starts a new map segment (new
map frame, ``map_segment`` + 1, EVENT_NEW_SEGMENT). It never reports a pose it did not verify.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections import Counter
from typing import Self

import cv2
import numpy as np

from ..datasets.base import CameraModel
from ..descriptors import match_ratio
from ..geometry import invert, rotation_angle_deg, transform_points
from .config import VoConfig
from .features import FrameFeatures, OrbExtractor, inv_sigma2, level_scales
from .local_mapping import LocalMapper
from .map import Keyframe, Map
from .matching import project_points, search_by_projection
from .pose_opt import optimize_pose
from .types import (
    EVENT_NEW_SEGMENT,
    EVENT_WARNING,
    STATE_INITIALIZING,
    STATE_LOST,
    STATE_NEW_SEGMENT,
    STATE_OK,
    STATE_RELOCALIZED,
    TrackResult,
    VoError,
    VoEvent,
)

log = logging.getLogger(__name__)


class _Tracked:
    """Outcome of a local-map search: pose and the (keypoint, map point) inliers."""

    def __init__(self, T_map_cam, kp_idx, point_ids, ref_kf_id):
        self.T_map_cam = T_map_cam
        self.kp_idx = kp_idx
        self.point_ids = point_ids
        self.ref_kf_id = ref_kf_id

    @property
    def n(self) -> int:
        return len(self.kp_idx)


class RgbdOdometry:
    """Visual odometry of one RGB-D camera (see module docstring). Not thread-safe: call ``track``
    from one thread; ``drain_events`` may be called from another."""

    def __init__(self, config: VoConfig | None = None, camera: CameraModel | None = None):
        if camera is None:
            raise VoError("RgbdOdometry needs the camera model (intrinsics and image size)")
        self.config = config or VoConfig()
        self.config.validate()
        # The colour camera the keypoints come from (KeyFrame.camera should carry this one).
        self.camera = camera = self.config.color_camera(camera)
        self.K = camera.K
        self.bf = camera.fx * self.config.virtual_baseline_m
        self.scales = level_scales(self.config)
        self._extractor = OrbExtractor(self.config, camera)
        self._events: collections.deque = collections.deque()
        self._events_lock = threading.Lock()
        self.map_segment = 0
        self._map = Map(self.map_segment)
        self._next_kf_id = 1
        self._mapper = LocalMapper(self.config, camera, lambda: self._map, self._emit)
        self._clear_tracking()
        self._last_stamp: float | None = None
        self.frames_processed = 0
        self._ignored: list[tuple[np.ndarray, float]] = []  # (corners_map (N, 3), until [s])

    # --- public API -------------------------------------------------------------------------------
    def track(self, stamp_s: float, image: np.ndarray, depth_m: np.ndarray) -> TrackResult:
        """Track one frame. Raises VoError on malformed input; a frame it cannot use is a lost
        result."""
        t0 = time.perf_counter()
        c0 = time.thread_time()
        gray, depth = self._check_inputs(stamp_s, image, depth_m)
        stamp_s = float(stamp_s)
        if self._last_stamp is not None and stamp_s == self._last_stamp:
            raise VoError(f"duplicate timestamp {stamp_s:.6f} s: frame ignored")
        if self._last_stamp is not None and stamp_s < self._last_stamp:
            msg = (
                f"timestamp {stamp_s:.6f} s is not after the previous "
                f"{self._last_stamp:.6f} s: map reset"
            )
            log.warning(msg)
            self._emit(VoEvent(EVENT_WARNING, self.map_segment, message=msg))
            self.reset()
        self._last_stamp = stamp_s
        self.frames_processed += 1
        feats = self._drop_ignored(stamp_s, self._extractor.extract(gray, depth))
        if self._state == STATE_INITIALIZING:
            result = self._initialize(stamp_s, feats)
        elif self._state == STATE_LOST:
            result = self._relocalize_or_restart(stamp_s, feats)
        else:
            result = self._track_frame(stamp_s, feats)
        result.n_features = len(feats)
        result.n_keyframes = len(self._map.keyframes)
        result.track_ms = (time.perf_counter() - t0) * 1e3
        result.cpu_ms = (time.thread_time() - c0) * 1e3
        return result

    def ignore_region(self, corners_map: np.ndarray, until_s: float) -> None:
        """Keypoints that fall inside the image of these 3D points (e.g. the corners of another
        robot's body, in the current map frame [m]) are not used, up to frame time ``until_s``: a
        moving object tracked as a landmark drags the pose along and leaves false map points."""
        corners = np.asarray(corners_map, dtype=float)
        if corners.ndim != 2 or corners.shape[1] != 3 or len(corners) < 2:
            raise VoError(f"ignore_region: corners must be (N >= 2, 3), got {corners.shape}")
        if not np.all(np.isfinite(corners)) or not np.isfinite(until_s):
            raise VoError("ignore_region: corners and until_s must be finite")
        self._ignored.append((corners, float(until_s)))

    def _drop_ignored(self, stamp_s: float, feats: FrameFeatures) -> FrameFeatures:
        self._ignored = [(c, t) for c, t in self._ignored if t >= stamp_s]
        if not self._ignored or not len(feats):
            return feats
        # Where the camera will be: the tracker's own constant-velocity prediction.
        T_cam_map = invert(self._T_map_cam @ self._velocity)
        keep = np.ones(len(feats), bool)
        for corners, _ in self._ignored:
            points_cam = transform_points(T_cam_map, corners)
            front = points_cam[:, 2] > 0.05
            if not front.any():
                continue  # behind the camera
            uv = points_cam[front, :2] / points_cam[front, 2:] * self.K[[0, 1], [0, 1]]
            uv += self.K[[0, 1], [2, 2]]
            (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
            u, v = feats.uv_px[:, 0], feats.uv_px[:, 1]
            keep &= ~((u >= u0) & (u <= u1) & (v >= v0) & (v <= v1))
        return feats if keep.all() else feats.subset(keep)

    def keyframes(self) -> list[Keyframe]:
        """Snapshots of the current segment's keyframes, by id (with map_points_xyz filled in)."""
        with self._map.lock:
            return [self._map.snapshot(k) for k in sorted(self._map.keyframes)]

    def keyframe(self, keyframe_id: int) -> Keyframe | None:
        with self._map.lock:
            if keyframe_id not in self._map.keyframes:
                return None
            return self._map.snapshot(keyframe_id)

    def map_points(self) -> dict[int, np.ndarray]:
        """Map point id -> xyz in the map frame [m] (current segment)."""
        ids, xyz = self.map_point_arrays()
        return {int(i): p for i, p in zip(ids, xyz)}

    def map_point_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (P,), xyz (P, 3)) of the current segment's map points."""
        with self._map.lock:
            ids = self._map.points.alive_ids()
            return ids.astype(np.uint32), self._map.points.xyz[ids].copy()

    def drain_events(self) -> list[VoEvent]:
        """Keyframe and segment events since the last call, oldest first."""
        with self._events_lock:
            out = list(self._events)
            self._events.clear()
        return out

    def flush(self, timeout_s: float = 60.0) -> None:
        """Wait until local mapping has processed every keyframe (threaded mode)."""
        self._mapper.flush(timeout_s)

    def reset(self) -> None:
        """Drop the map; the next frame starts a new map segment (keyframe/point ids keep
        growing)."""
        self._mapper.flush()
        if self._map.keyframes:
            self.map_segment += 1
            self._emit(VoEvent(EVENT_NEW_SEGMENT, self.map_segment, message="map reset"))
        self._map = Map(self.map_segment, first_point_id=self._map.points.next_id)
        self._clear_tracking()
        self._ignored = []  # given in the dropped map's frame

    def close(self) -> None:
        """Stop the local-mapping thread and worker process."""
        self._mapper.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def state(self) -> str:
        return self._state

    @property
    def mapping_stats(self) -> dict:
        return self._mapper.stats

    @property
    def vo_map(self) -> Map:
        """The live map (hold ``vo_map.lock`` while reading it in threaded mode)."""
        return self._map

    # --- input checks -----------------------------------------------------------------------------
    def _check_inputs(self, stamp_s, image, depth_m):
        cam = self.camera
        try:
            stamp_ok = np.isfinite(float(stamp_s))
        except (TypeError, ValueError):
            stamp_ok = False
        if not stamp_ok:
            raise VoError(f"timestamp {stamp_s!r} is not a finite number of seconds")
        if not isinstance(image, np.ndarray) or image.size == 0:
            raise VoError("empty image: expected a BGR or grey uint8 array")
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise VoError(
                f"image must be uint8 grey or BGR, got dtype {image.dtype} shape {image.shape}"
            )
        if image.shape[:2] != (cam.height, cam.width):
            raise VoError(
                f"image is {image.shape[1]}x{image.shape[0]} "
                f"but the camera model is {cam.width}x{cam.height}"
            )
        if image.ndim == 3:
            if image.shape[2] == 3:
                gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            elif image.shape[2] == 4:
                gray = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
            elif image.shape[2] == 1:
                gray = image[:, :, 0]
            else:
                raise VoError(f"image has {image.shape[2]} channels, expected 1, 3 or 4")
        else:
            gray = image
        if depth_m is None or not isinstance(depth_m, np.ndarray) or depth_m.size == 0:
            raise VoError("no depth image: RGB-D odometry needs a depth image in metres")
        if depth_m.ndim != 2 or depth_m.shape != gray.shape:
            raise VoError(f"depth image has shape {depth_m.shape}, expected {gray.shape}")
        if depth_m.dtype == np.uint16:
            depth = depth_m.astype(np.float32) / np.float32(cam.depth_scale)
        elif np.issubdtype(depth_m.dtype, np.floating):
            depth = depth_m
        else:
            raise VoError(f"depth image must be float metres or uint16, got {depth_m.dtype}")
        return np.ascontiguousarray(gray), depth

    # --- states -----------------------------------------------------------------------------------
    def _clear_tracking(self) -> None:
        self._state = STATE_INITIALIZING
        self._T_map_cam = np.eye(4)
        self._velocity = np.eye(4)  # T_prev_cur of the last frame pair
        self._last_point_ids = np.zeros(0, np.int64)
        self._ref_kf_id = 0
        self._frames_since_kf = 0
        self._lost_count = 0
        self._reloc_cursor = 0
        self._n_ref_cache = (None, 0)

    def _result(self, stamp_s, ok, state, tracked: _Tracked | None = None, kf_id=0, message=""):
        return TrackResult(
            stamp_s=stamp_s,
            T_map_cam=self._T_map_cam.copy(),
            ok=ok,
            state=state,
            map_segment=self.map_segment,
            track_ms=0.0,
            n_tracked=tracked.n if tracked is not None else 0,
            new_keyframe_id=kf_id,
            message=message,
        )

    def _initialize(
        self, stamp_s: float, feats: FrameFeatures, state: str | None = None
    ) -> TrackResult:
        n_depth = int(feats.has_depth.sum())
        if n_depth < self.config.min_init_points:
            return self._result(
                stamp_s,
                False,
                STATE_INITIALIZING,
                message=f"waiting for a frame with depth: {n_depth} keypoints with depth, "
                f"{self.config.min_init_points} needed",
            )
        self._T_map_cam = np.eye(4)  # the first keyframe defines the map frame
        kf_id = self._insert_keyframe(
            stamp_s, feats, self._T_map_cam, np.zeros(0, int), np.zeros(0, int)
        )
        self._state = STATE_OK
        self._velocity = np.eye(4)
        kf = self._map.keyframes[kf_id]
        self._last_point_ids = kf.map_point_ids[kf.map_point_ids > 0].astype(np.int64)
        state = state or (STATE_NEW_SEGMENT if self.map_segment > 0 else STATE_OK)
        return self._result(stamp_s, True, state, kf_id=kf_id, message="map initialized")

    def _track_frame(self, stamp_s: float, feats: FrameFeatures) -> TrackResult:
        T_pred = self._T_map_cam @ self._velocity
        tracked = self._track_local_map(feats, T_pred, self._last_point_ids)
        message = ""
        if tracked is None or not self._plausible(tracked.T_map_cam):
            # Motion model failed: PnP against the reference and the newest keyframe, no prior.
            tracked = None
            with self._map.lock:
                candidates = [self._ref_kf_id, max(self._map.keyframes, default=0)]
            for kf_id in dict.fromkeys(candidates):
                T0, pids = self._pnp(feats, kf_id)
                if T0 is None:
                    continue
                tracked = self._track_local_map(feats, T0, pids)
                if tracked is not None and self._plausible(tracked.T_map_cam):
                    message = f"recovered with PnP against keyframe {kf_id}"
                    break
                tracked = None
        if tracked is None:
            self._state = STATE_LOST
            self._lost_count = 1
            return self._result(stamp_s, False, STATE_LOST, message="tracking lost")
        self._velocity = invert(self._T_map_cam) @ tracked.T_map_cam
        self._accept(tracked)
        kf_id = 0
        if self._need_keyframe(feats, tracked):
            kf_id = self._insert_keyframe(
                stamp_s, feats, tracked.T_map_cam, tracked.kp_idx, tracked.point_ids
            )
        else:
            self._frames_since_kf += 1
        self._state = STATE_OK
        return self._result(stamp_s, True, STATE_OK, tracked, kf_id, message)

    def _relocalize_or_restart(self, stamp_s: float, feats: FrameFeatures) -> TrackResult:
        cfg = self.config
        with self._map.lock:
            candidates = sorted(self._map.keyframes, reverse=True)[: cfg.reloc_keyframes]
        n_try = min(cfg.reloc_keyframes_per_frame, len(candidates))
        for i in range(n_try):
            kf_id = candidates[(self._reloc_cursor + i) % len(candidates)]
            T0, pids = self._pnp(feats, kf_id)
            if T0 is None:
                continue
            tracked = self._track_local_map(feats, T0, pids)
            if tracked is not None and tracked.n >= cfg.reloc_min_inliers:
                self._velocity = np.eye(4)
                self._accept(tracked)
                self._lost_count = 0
                self._frames_since_kf += 1
                self._state = STATE_OK
                return self._result(
                    stamp_s,
                    True,
                    STATE_RELOCALIZED,
                    tracked,
                    message=f"relocalized against keyframe {kf_id}",
                )
        self._reloc_cursor += n_try
        self._lost_count += 1
        if self._lost_count > cfg.max_lost_frames:
            log.warning(
                "lost for %d frames: starting map segment %d",
                self._lost_count,
                self.map_segment + 1,
            )
            self.reset()
            result = self._initialize(stamp_s, feats, STATE_NEW_SEGMENT)
            if not result.ok:
                result.message = "new map segment started; " + result.message
            return result
        return self._result(
            stamp_s, False, STATE_LOST, message=f"lost for {self._lost_count} frames"
        )

    def _accept(self, tracked: _Tracked) -> None:
        self._T_map_cam = tracked.T_map_cam
        self._last_point_ids = tracked.point_ids
        if tracked.ref_kf_id:
            self._ref_kf_id = tracked.ref_kf_id

    def _plausible(self, T_map_cam: np.ndarray) -> bool:
        """Reject jumps no camera makes between frames (a wrong PnP or a bad local minimum)."""
        if self._state in (STATE_LOST, STATE_INITIALIZING):
            return True
        step = invert(self._T_map_cam) @ T_map_cam
        return (
            np.linalg.norm(step[:3, 3]) <= self.config.max_frame_motion_m
            and rotation_angle_deg(step[:3, :3]) <= self.config.max_frame_rotation_deg
        )

    # --- tracking ---------------------------------------------------------------------------------
    def _local_map(self, seed_point_ids: np.ndarray):
        """Local keyframes (sharing points with the seed points, plus their best covisibles) and the
        copied arrays of their map points.
        Returns (ref_kf_id, ids, xyz, desc, angle, normal, max_dist).
        """
        cfg = self.config
        vmap = self._map
        with vmap.lock:
            pts = vmap.points
            seed = (
                seed_point_ids[pts.is_alive(seed_point_ids)]
                if len(seed_point_ids)
                else seed_point_ids
            )
            obs = pts.obs
            counts = Counter([k for p in seed.tolist() for k in obs[p]])
            if not counts:
                fallback = (
                    self._ref_kf_id
                    if self._ref_kf_id in vmap.keyframes
                    else max(vmap.keyframes, default=0)
                )
                if fallback == 0:
                    return None
                counts[fallback] = 1
            ranked = [k for k, _ in counts.most_common()]
            ref = ranked[0]
            local = ranked[: cfg.local_keyframes]
            chosen = set(local)
            for k in list(local):
                if len(local) >= cfg.local_keyframes:
                    break
                for c in vmap.best_covisible(k, 10):
                    if c not in chosen:
                        chosen.add(c)
                        local.append(c)
                        if len(local) >= cfg.local_keyframes:
                            break
            ids = np.unique(
                np.concatenate([vmap.keyframes[k].map_point_ids for k in local]).astype(np.int64)
            )
            ids = ids[(ids > 0) & pts.is_alive(ids)]
            return (
                ref,
                ids,
                pts.xyz[ids].copy(),
                pts.desc[ids].copy(),
                pts.angle[ids].copy(),
                pts.normal[ids].copy(),
                pts.max_dist[ids].copy(),
            )

    def _track_local_map(
        self, feats: FrameFeatures, T_map_cam_pred: np.ndarray, seed_point_ids
    ) -> _Tracked | None:
        cfg = self.config
        local = self._local_map(np.asarray(seed_point_ids, dtype=np.int64))
        if local is None or len(feats) == 0:
            return None
        ref, ids, xyz, desc, angle, normal, max_dist = local
        info = inv_sigma2(cfg, feats.octaves)
        size = (self.camera.width, self.camera.height)
        T_cam_map = invert(T_map_cam_pred)
        best = None
        for stage, radius in enumerate((cfg.search_radius_px, cfg.search_radius_refine_px)):
            proj = project_points(
                T_cam_map, xyz, self.K, self.bf, size, self.scales, max_dist, normal
            )
            radii = (radius, 2.0 * radius) if stage == 0 else (radius,)
            for r in radii:
                pi, kj, _ = search_by_projection(
                    proj,
                    desc,
                    feats,
                    r,
                    self.scales,
                    cfg.max_descriptor_distance,
                    cfg.ratio_test,
                    point_angle_deg=angle,
                    check_orientation=cfg.check_orientation and stage == 0,
                )
                if len(pi) < cfg.min_tracked:
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
                    cfg.pose_rounds,
                    cfg.pose_iterations,
                    cfg.chi2_mono,
                    cfg.chi2_stereo,
                )
                if inl.sum() >= cfg.min_tracked:
                    cand = (T_opt, kj[inl], rows[inl], proj)
                    if best is None or len(cand[1]) >= 0.9 * len(best[1]):
                        best = cand
                    T_cam_map = T_opt
                    break
            if best is None:
                return None
        T_cam_map, kp_idx, rows, proj = best
        with self._map.lock:
            pts = self._map.points
            seen = ids[proj.index]
            pts.visible[seen] += 1
            pts.found[ids[rows]] += 1
        return _Tracked(invert(T_cam_map), kp_idx, ids[rows], ref)

    def _pnp(self, feats: FrameFeatures, kf_id: int):
        """Pose from brute-force matches to a keyframe's map points + PnP RANSAC
        (or (None, None))."""
        cfg = self.config
        with self._map.lock:
            kf = self._map.keyframes.get(kf_id)
            if kf is None:
                return None, None
            idx = np.flatnonzero(kf.map_point_ids)
            pids = kf.map_point_ids[idx].astype(np.int64)
            alive = self._map.points.is_alive(pids)
            idx, pids = idx[alive], pids[alive]
            xyz = self._map.points.xyz[pids].copy()
            desc = kf.descriptors[idx]
        if len(pids) < cfg.pnp_min_inliers or len(feats) < cfg.pnp_min_inliers:
            return None, None
        m = match_ratio(
            feats.descriptors, desc, ratio=cfg.pnp_ratio, max_distance=cfg.max_descriptor_distance
        )
        if len(m) < cfg.pnp_min_inliers:
            return None, None
        obj = xyz[m[:, 1]].astype(np.float64)
        img = feats.uv_px[m[:, 0]].astype(np.float64)
        try:
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                obj,
                img,
                self.K,
                None,
                iterationsCount=cfg.pnp_iterations,
                reprojectionError=cfg.pnp_reprojection_px,
                confidence=0.99,
                flags=cv2.SOLVEPNP_EPNP,
            )
        except cv2.error:
            return None, None
        if not ok or inliers is None or len(inliers) < cfg.pnp_min_inliers:
            return None, None
        T_cam_map = np.eye(4)
        T_cam_map[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_cam_map[:3, 3] = tvec.ravel()
        inl = inliers.ravel()
        kp = m[inl, 0]
        T_cam_map, good = optimize_pose(
            T_cam_map,
            obj[inl],
            feats.uv_px[kp],
            feats.u_right_px[kp],
            inv_sigma2(cfg, feats.octaves[kp]),
            self.K,
            self.bf,
        )
        if good.sum() < cfg.pnp_min_inliers:
            return None, None
        return invert(T_cam_map), pids[m[inl[good], 1]]

    # --- keyframes --------------------------------------------------------------------------------
    def _need_keyframe(self, feats: FrameFeatures, tracked: _Tracked) -> bool:
        """ORB-SLAM2's NeedNewKeyFrame for RGB-D."""
        cfg = self.config
        if self._frames_since_kf + 1 < cfg.keyframe_min_frames:
            return False
        vmap = self._map
        with vmap.lock:
            # ORB-SLAM2 counts an observation with depth twice and asks for 3 (2 with <= 2
            # keyframes): in keyframes, that is 2 (1).
            min_obs = 2 if len(vmap.keyframes) > 2 else 1
            ref = vmap.keyframes.get(tracked.ref_kf_id) or vmap.keyframes.get(self._ref_kf_id)
            n_ref = 0
            if ref is not None:
                # Counting observations is a Python loop: reuse it for a few frames per reference.
                key = (ref.keyframe_id, min_obs, self.frames_processed // 5)
                if self._n_ref_cache[0] == key:
                    n_ref = self._n_ref_cache[1]
                else:
                    obs = vmap.points.obs
                    pids = ref.map_point_ids[ref.map_point_ids > 0].tolist()
                    n_ref = sum(1 for p in pids if len(obs.get(p, ())) >= min_obs)
                    self._n_ref_cache = (key, n_ref)
        d = feats.depths_m
        close = (d > 0) & (d <= cfg.close_depth_m)
        tracked_mask = np.zeros(len(feats), bool)
        tracked_mask[tracked.kp_idx] = True
        n_tracked_close = int((close & tracked_mask).sum())
        n_untracked_close = int((close & ~tracked_mask).sum())
        need_close = (
            n_tracked_close < cfg.keyframe_close_tracked
            and n_untracked_close > cfg.keyframe_close_untracked
        )
        c1a = self._frames_since_kf + 1 >= cfg.keyframe_max_frames
        c1b = (
            self._mapper.idle or self._mapper.pending < 3
        )  # RGB-D: insert even while mapping is busy
        c1c = tracked.n < 0.25 * n_ref or need_close
        # Besides ORB-SLAM2's ratio, a floor on the tracked points: with few keyframes, few points
        # have two observations, the ratio then lets tracking thin out to ~150 points (measured:
        # those frames carry most of the per-frame error on RedKitchen).
        weak = tracked.n < cfg.keyframe_min_tracked
        c2 = (tracked.n < cfg.keyframe_ref_ratio * n_ref or need_close or weak) and (
            tracked.n > cfg.keyframe_min_inliers
        )
        return (c1a or c1b or c1c) and c2

    def _insert_keyframe(self, stamp_s, feats: FrameFeatures, T_map_cam, kp_idx, point_ids) -> int:
        """Create a keyframe from the frame, with new map points from depth for unmatched
        keypoints."""
        cfg = self.config
        vmap = self._map
        kf_id = self._next_kf_id
        self._next_kf_id += 1
        n = len(feats)
        with vmap.lock:
            pts = vmap.points
            mp_ids = np.zeros(n, np.uint32)
            point_ids = np.asarray(point_ids, dtype=np.int64)
            kp_idx = np.asarray(kp_idx, dtype=np.int64)
            alive = pts.is_alive(point_ids)
            kp_idx, point_ids = kp_idx[alive], point_ids[alive]
            _, first = np.unique(
                point_ids, return_index=True
            )  # a point is observed once per keyframe
            mp_ids[kp_idx[first]] = point_ids[first]
            # New points: unmatched keypoints with depth, closest (best depth) first. Points beyond
            # close_depth_m still help as monocular observations.
            d = feats.depths_m
            cand = np.flatnonzero((d > 0) & (mp_ids == 0))
            cand = cand[np.argsort(d[cand], kind="stable")][: cfg.new_points_max]
            if len(cand):
                xyz = transform_points(T_map_cam, feats.points_cam[cand])
                ray = xyz - T_map_cam[:3, 3]
                dist = np.linalg.norm(ray, axis=1)
                new_ids = pts.add(
                    xyz,
                    feats.descriptors[cand],
                    feats.angle_deg[cand],
                    ray / dist[:, None],
                    dist * self.scales[feats.octaves[cand].astype(int)],
                    vmap.kf_seq + 1,
                )
                mp_ids[cand] = new_ids.astype(np.uint32)
            kf = Keyframe(
                keyframe_id=kf_id,
                stamp_s=float(stamp_s),
                map_segment=self.map_segment,
                T_map_cam=np.array(T_map_cam, dtype=float),
                uv_px=feats.uv_px.astype(np.float32),
                size_px=feats.size_px,
                angle_deg=feats.angle_deg,
                octaves=feats.octaves,
                descriptors=feats.descriptors,
                depths_m=feats.depths_m,
                map_point_ids=mp_ids,
            )
            vmap.add_keyframe(kf)
            vmap.update_covisibility(kf_id)
        self._ref_kf_id = kf_id
        self._frames_since_kf = 0
        self._mapper.submit(kf_id)
        return kf_id

    def _emit(self, event: VoEvent) -> None:
        with self._events_lock:
            self._events.append(event)
