"""ORB-SLAM-style visual odometry of one client's RGB-D, stereo or monocular camera (pure core, no
rospy): the tracking state machine. Each stage is a module of its own.

``VisualOdometry.track(stamp_s, image, second)`` (``second``: the depth image of an RGB-D camera,
the right image of a stereo pair, None for a monocular camera) runs, per frame:

1. the input checks and what the sensor measures per keypoint (:mod:`.sensor`) on grid-bucketed
   ORB features (:mod:`.features`);
2. prediction with a constant-velocity model and tracking against the local map
   (:mod:`.tracking`);
3. if that fails, PnP RANSAC against the reference keyframe, then the local-map search again
   (:mod:`.relocalization`);
4. the keyframe decision (:mod:`.keyframes`); the keyframe gets new map points from depth at once
   (so the next frames can track them) and goes to local mapping (:mod:`.local_mapping`: fusion,
   point culling, GTSAM local BA, keyframe culling).

A monocular camera measures no depth. Its map starts from two views (:mod:`.initialization`): the
first frame with enough keypoints becomes the reference; each later frame is matched with it and
the two-view initialization tried, until it succeeds (enough parallax, a clear motion) -- while it
waits the state is ``initializing`` and the message says why ("initializing: not enough parallax:
keep moving"); a homography, poorly conditioned with little translation, needs more parallax
(``mono_init_min_parallax_homography_deg``). The reference is replaced when too few matches remain
or it is older than ``mono_init_max_age_s``. The map then holds the reference frame as its first
keyframe (the map frame), the current frame as the second, and the triangulated points, scaled so
their median depth in the first keyframe is 1: the map has no metric scale
(:attr:`VisualOdometry.metric_scale`).
Later keyframes get their new points from triangulation in local mapping.

When tracking fails the odometry is *lost*: it tries to relocalize against its own recent keyframes
(brute-force descriptor matching + PnP RANSAC + local-map search), a few keyframes per frame so the
time per frame stays bounded; after ``max_lost_frames`` failures it starts a new map segment (new
map frame, ``map_segment`` + 1, EVENT_NEW_SEGMENT). It never reports a pose it did not verify.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from typing import Self

import numpy as np

from ..camera import CameraModel
from ..geometry import invert, rotation_angle_deg, transform_points
from .config import VoConfig
from .dense_depth import KeyframeDepthImages
from .features import FrameFeatures, OrbExtractor, level_scales
from .initialization import (
    MODEL_HOMOGRAPHY,
    MonoInitConfig,
    TwoViewResult,
    initialize_two_view,
    match_for_initialization,
    scale_to_median_depth,
)
from .kernels import warm_up
from .keyframes import KeyframePolicy, add_keyframe
from .local_mapping import LocalMapper
from .map import Map, MapKeyframe
from .relocalization import Relocalizer, pnp_against_keyframe, pnp_against_points
from .sensor import make_sensor
from .tracking import LocalMapTracker, Tracked
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


class VisualOdometry:
    """Visual odometry of one RGB-D, stereo or monocular camera (see module docstring). Not
    thread-safe: call ``track`` from one thread; ``drain_events`` may be called from another."""

    def __init__(self, config: VoConfig | None = None, camera: CameraModel | None = None):
        if camera is None:
            raise VoError("VisualOdometry needs the camera model (intrinsics and image size)")
        config = config or VoConfig()
        config.validate()
        warm_up()  # the compiled kernels, before the first frame
        # This camera kind's values (a monocular camera's keyframe rule, its wider local BA, ...)
        self.config = config.for_sensor(camera.sensor)
        # The colour camera the keypoints come from (keyframe messages carry this one).
        self.camera = camera = self.config.calibration.color_camera(camera)
        self.K = camera.K
        self.scales = level_scales(self.config)
        self._sensor = make_sensor(self.config, camera)
        self._extractor = OrbExtractor(self.config, camera)
        self._frame_images = (None, None)  # the current frame's (grey, depth or right image)
        self._depth_images = KeyframeDepthImages(
            self.config.dense,
            self._sensor.kind,
            self.camera,
            self.config.calibration.depth_registered,
        )
        self._tracker = LocalMapTracker(self.config, self._sensor, self.scales)
        self._relocalizer = Relocalizer(self.config, self._sensor, self._tracker)
        self._keyframe_policy = KeyframePolicy(
            self.config, self._sensor.close_depth_m, monocular=self._sensor.monocular
        )
        self._mono_init = MonoInitConfig(
            min_median_parallax_deg=self.config.mono_init.min_parallax_deg
        )
        self._init_ref: tuple[float, FrameFeatures] | None = None  # monocular: (stamp, features)
        self._events: collections.deque = collections.deque()
        self._events_lock = threading.Lock()
        self.map_segment = 0
        self._map = Map(self.map_segment)
        self._next_kf_id = 1
        self._mapper = LocalMapper(self.config, self._sensor, lambda: self._map, self._emit)
        self._clear_tracking()
        self._last_stamp: float | None = None
        # The frame that reset the map after a jump back in time; until time moves forward from
        # it, older frames are dropped rather than reset the map again (one reset per jump).
        self._jumped_to: float | None = None
        self.frames_processed = 0
        self._ignored: list[tuple[np.ndarray, float]] = []  # (corners_map (N, 3), until [s])

    # --- public API -------------------------------------------------------------------------------
    def track(
        self, stamp_s: float, image: np.ndarray, second: np.ndarray | None = None
    ) -> TrackResult:
        """Track one frame (``second``: depth or right image, None for a monocular camera). Raises
        VoError on malformed input; a frame it cannot use is a lost result. The images are read
        after the call returns (a keyframe's depth image is made beside tracking): pass arrays
        the caller does not change afterwards."""
        with self.frame_in_progress():
            return self._track(stamp_s, image, second)

    @contextlib.contextmanager
    def frame_in_progress(self):
        """Marks a frame's work: local mapping's steps wait until it is done, at most
        ``mapping_yield_max_s`` (tracking comes first; see :mod:`.local_mapping`)."""
        self._mapper.frame_started()
        try:
            yield
        finally:
            self._mapper.frame_finished()

    def _track(self, stamp_s: float, image: np.ndarray, second: np.ndarray | None) -> TrackResult:
        t0 = time.perf_counter()
        c0 = time.thread_time()
        try:
            stamp_ok = np.isfinite(float(stamp_s))
        except (TypeError, ValueError):
            stamp_ok = False
        if not stamp_ok:
            raise VoError(f"timestamp {stamp_s!r} is not a finite number of seconds")
        gray, second = self._sensor.check_input(image, second)
        self._frame_images = (gray, second)  # for a keyframe's depth image (vo.dense_depth)
        stamp_s = float(stamp_s)
        if self._last_stamp is not None and stamp_s == self._last_stamp:
            raise VoError(f"duplicate timestamp {stamp_s:.6f} s: frame ignored")
        if self._last_stamp is not None and stamp_s < self._last_stamp:
            if self._jumped_to == self._last_stamp:
                raise VoError(
                    f"timestamp {stamp_s:.6f} s is before {self._last_stamp:.6f} s, where time "
                    "jumped back and the map was reset: frame ignored"
                )
            msg = (
                f"timestamp {stamp_s:.6f} s is not after the previous "
                f"{self._last_stamp:.6f} s: map reset"
            )
            self._emit(VoEvent(EVENT_WARNING, self.map_segment, message=msg))
            self.reset()
            self._jumped_to = stamp_s
        self._frame_dt_s = stamp_s - self._last_stamp if self._last_stamp is not None else 0.0
        self._last_stamp = stamp_s
        self.frames_processed += 1
        # A stereo pair's two images extracted together (their levels over the threads).
        both = self._sensor.extracts_second
        extracted = self._extractor.extract_images([gray, second] if both else [gray])
        kps, levels = extracted[0]
        feats = self._sensor.features(kps, gray, second, levels, *extracted[1:])
        if self._sensor.warning:
            self._emit(VoEvent(EVENT_WARNING, self.map_segment, message=self._sensor.warning))
            self._sensor.warning = None
        feats = self._drop_ignored(stamp_s, feats)
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

    def lost_view(self) -> np.ndarray | None:
        """While lost: the descriptors of the newest frame (what the camera sees), for a
        server-assisted relocalization (see :meth:`offer_local_map`); None when tracking."""
        return self._lost_view if self._state == STATE_LOST else None

    def expect_local_map(self) -> None:
        """A local map was asked of the server: keep trying for up to ``assist_wait_frames`` more
        lost frames before starting a new map segment."""
        self._awaiting_map = True

    def offer_local_map(self, points_map: np.ndarray | None, descriptors=None) -> None:
        """The server's local map around where a lost camera is (points in this odometry's map
        frame, and their descriptors), or None (it found no place). The next lost frames try PnP
        against it; a pose found carries the map on from a new keyframe there, in this map
        segment (RGB-D and stereo: the keyframe's points come from depth)."""
        self._awaiting_map = False
        self._offered = None
        if points_map is not None and len(points_map):
            self._offered = (np.asarray(points_map, float), np.asarray(descriptors, np.uint8))

    def keyframes(self) -> list[MapKeyframe]:
        """Snapshots of the current segment's keyframes, by id (with map_points_xyz filled in)."""
        with self._map.lock:
            return [self._map.snapshot(k) for k in sorted(self._map.keyframes)]

    def keyframe(self, keyframe_id: int) -> MapKeyframe | None:
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

    def map_points_with_reference(self) -> tuple[np.ndarray, np.ndarray]:
        """(xyz (P, 3), reference keyframe id (P,)) of the current segment's map points: the
        oldest keyframe observing each (normally the one that made it; 0: none left)."""
        with self._map.lock:
            pts = self._map.points
            ids = pts.alive_ids()
            # From the keyframes' side (their map_point_ids mirror the points' observations): the
            # newest first, so each point keeps the oldest keyframe that observes it.
            oldest = np.zeros(pts.next_id, np.int64)
            for kf_id in sorted(self._map.keyframes, reverse=True):
                seen = self._map.keyframes[kf_id].map_point_ids
                oldest[seen[seen > 0]] = kf_id
            return pts.xyz[ids].copy(), oldest[ids]

    def drain_events(self) -> list[VoEvent]:
        """Keyframe and segment events since the last call, oldest first."""
        with self._events_lock:
            out = list(self._events)
            self._events.clear()
        return out

    def flush(self, timeout_s: float = 60.0) -> None:
        """Wait until local mapping has processed every keyframe (threaded mode)."""
        self._mapper.flush(timeout_s)

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """The current map's keyframe poses, id -> T_map_cam."""
        with self._map.lock:
            return {k: kf.T_map_cam.copy() for k, kf in self._map.keyframes.items()}

    @property
    def keyframes_made(self) -> int:
        """Keyframe ids this odometry has given out (1 .. this), culled ones included."""
        return self._next_kf_id - 1

    @property
    def mapping_backlog(self) -> int:
        """Keyframes local mapping has not finished (queued or in process); more than one means
        it falls behind the camera."""
        return self._mapper.backlog

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
        self._depth_images.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def state(self) -> str:
        return self._state

    @property
    def metric_scale(self) -> bool:
        """Whether the map is in metres: False for a monocular camera, whose map unit is the
        median depth of the first two keyframes' points (fixed at initialization, and drifting
        with the odometry)."""
        return not self._sensor.monocular

    @property
    def mapping_stats(self) -> dict:
        return self._mapper.stats

    @property
    def vo_map(self) -> Map:
        """The live map (hold ``vo_map.lock`` while reading it in threaded mode)."""
        return self._map

    # --- states -----------------------------------------------------------------------------------
    def _clear_tracking(self) -> None:
        self._state = STATE_INITIALIZING
        self._T_map_cam = np.eye(4)
        self._velocity = np.eye(4)  # T_prev_cur of the last frame pair
        self._last_point_ids = np.zeros(0, np.int64)
        self._ref_kf_id = 0
        self._frames_since_kf = 0
        self._lost_count = 0
        self._init_ref = None
        self._lost_view: np.ndarray | None = None  # descriptors of the newest lost frame
        self._offered: tuple[np.ndarray, np.ndarray] | None = None  # a team local map
        self._awaiting_map = False
        self._relocalizer.reset()
        self._keyframe_policy.reset()

    def _result(self, stamp_s, ok, state, tracked: Tracked | None = None, kf_id=0, message=""):
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
        if self._sensor.monocular:
            return self._initialize_mono(stamp_s, feats, state)
        n_depth = int(feats.has_depth.sum())
        if n_depth < self.config.keyframes.min_init_points:
            return self._result(
                stamp_s,
                False,
                STATE_INITIALIZING,
                message=f"waiting for a frame with depth: {n_depth} keypoints with depth, "
                f"{self.config.keyframes.min_init_points} needed",
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

    def _initialize_mono(
        self, stamp_s: float, feats: FrameFeatures, state: str | None
    ) -> TrackResult:
        """Two-view initialization of a monocular camera (see module docstring)."""
        cfg, icfg = self.config, self._mono_init
        ref = self._init_ref
        if ref is None:
            return self._new_init_reference(stamp_s, feats, "reference frame set: keep moving")
        if stamp_s - ref[0] > cfg.mono_init.max_age_s:
            return self._new_init_reference(
                stamp_s,
                feats,
                f"no initialization within {cfg.mono_init.max_age_s:g} s of the reference frame:"
                " new reference frame",
            )
        pairs = match_for_initialization(ref[1], feats, icfg)
        if len(pairs) < icfg.min_matches:
            return self._new_init_reference(
                stamp_s,
                feats,
                f"{len(pairs)} matches with the reference frame ({icfg.min_matches} needed): "
                "new reference frame",
            )
        two_view = initialize_two_view(
            ref[1].uv_px[pairs[:, 0]], feats.uv_px[pairs[:, 1]], self.K, icfg
        )
        if not two_view.success:
            return self._waiting(stamp_s, two_view.reason)
        need_h = cfg.mono_init.min_parallax_homography_deg
        if two_view.model == MODEL_HOMOGRAPHY and two_view.median_parallax_deg < need_h:
            return self._waiting(
                stamp_s,
                f"not enough parallax for the homography: keep moving (median parallax "
                f"{two_view.median_parallax_deg:.2f} deg < {need_h:g} deg)",
            )
        if two_view.n_points < cfg.keyframes.min_init_points:
            return self._waiting(
                stamp_s,
                f"{two_view.n_points} points triangulated, {cfg.keyframes.min_init_points} needed: "
                "keep moving",
            )
        two_view = scale_to_median_depth(two_view)
        kf_id = self._create_two_view_map(stamp_s, feats, pairs, two_view)
        self._init_ref = None
        self._state = STATE_OK
        self._velocity = np.eye(4)
        state = state or (STATE_NEW_SEGMENT if self.map_segment > 0 else STATE_OK)
        message = (
            f"map initialized from two views ({two_view.model}, {two_view.n_points} points, "
            f"median parallax {two_view.median_parallax_deg:.1f} deg, "
            f"{stamp_s - ref[0]:.2f} s after the reference frame; no metric scale)"
        )
        return self._result(stamp_s, True, state, kf_id=kf_id, message=message)

    def _waiting(self, stamp_s: float, reason: str) -> TrackResult:
        return self._result(stamp_s, False, STATE_INITIALIZING, message=f"initializing: {reason}")

    def _new_init_reference(self, stamp_s: float, feats: FrameFeatures, reason: str) -> TrackResult:
        """Make the frame the reference of the two-view initialization (if it has keypoints
        enough to match)."""
        need = self._mono_init.min_matches
        if len(feats) < need:
            self._init_ref = None
            return self._waiting(stamp_s, f"{len(feats)} keypoints, {need} needed")
        self._init_ref = (stamp_s, feats)
        return self._waiting(stamp_s, reason)

    def _create_two_view_map(
        self, stamp_s: float, feats: FrameFeatures, pairs: np.ndarray, two_view: TwoViewResult
    ) -> int:
        """The map of a successful two-view initialization: the reference frame as the first
        keyframe (the map frame), the current one as the second, the triangulated points observed
        by both; both keyframes go to local mapping (local BA). Returns the second's id."""
        ref_stamp, ref_feats = self._init_ref
        i_ref = pairs[two_view.match_index, 0]
        i_cur = pairs[two_view.match_index, 1]
        xyz = two_view.points_ref  # the reference camera frame is the map frame
        with self._map.lock:
            dist = np.linalg.norm(xyz, axis=1)
            point_ids = self._map.points.add(
                xyz,
                ref_feats.descriptors[i_ref],
                ref_feats.angle_deg[i_ref],
                xyz / dist[:, None],
                dist * self.scales[ref_feats.octaves[i_ref].astype(int)],
                self._map.kf_seq + 1,
            )
        T_map_cur = invert(two_view.T_cur_ref)
        kf_ref = self._insert_keyframe(ref_stamp, ref_feats, np.eye(4), i_ref, point_ids, False)
        kf_cur = self._insert_keyframe(stamp_s, feats, T_map_cur, i_cur, point_ids, False)
        with self._map.lock:
            self._map.update_point_stats(point_ids, self.scales)
        self._T_map_cam = T_map_cur
        self._last_point_ids = point_ids.astype(np.int64)
        self._mapper.submit(kf_ref)
        self._mapper.submit(kf_cur)
        return kf_cur

    def _track_frame(self, stamp_s: float, feats: FrameFeatures) -> TrackResult:
        T_pred = self._T_map_cam @ self._velocity
        tracked = self._tracker.track(
            self._map, feats, T_pred, self._last_point_ids, self._ref_kf_id
        )
        message = ""
        if tracked is None or not self._plausible(tracked.T_map_cam):
            # Motion model failed: PnP against the reference and the newest keyframe, no prior.
            tracked = None
            with self._map.lock:
                candidates = [self._ref_kf_id, max(self._map.keyframes, default=0)]
            for kf_id in dict.fromkeys(candidates):
                T0, pids = pnp_against_keyframe(self._map, feats, kf_id, self.config, self._sensor)
                if T0 is None:
                    continue
                tracked = self._tracker.track(self._map, feats, T0, pids, self._ref_kf_id)
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
        if self._keyframe_policy.needed(
            self._map,
            feats,
            tracked,
            self._ref_kf_id,
            self._frames_since_kf,
            self.frames_processed,
            # RGB-D and stereo insert while mapping is busy, monocular (ORB-SLAM2) only when
            # it is idle: its keyframes cost triangulation as well.
            self._mapper.idle or (self._mapper.pending < 3 and not self._sensor.monocular),
        ):
            kf_id = self._insert_keyframe(
                stamp_s, feats, tracked.T_map_cam, tracked.kp_idx, tracked.point_ids
            )
        else:
            self._frames_since_kf += 1
        self._state = STATE_OK
        return self._result(stamp_s, True, STATE_OK, tracked, kf_id, message)

    def _relocalize_or_restart(self, stamp_s: float, feats: FrameFeatures) -> TrackResult:
        cfg = self.config
        if len(feats) < cfg.relocalization.pnp_min_inliers:
            # A covered or black camera: it can neither relocalize nor start a map, so its
            # frames do not count towards a new segment.
            return self._result(
                stamp_s, False, STATE_LOST, message=f"lost: the camera sees {len(feats)} features"
            )
        self._lost_view = feats.descriptors
        found = self._relocalizer.try_frame(self._map, feats, self._ref_kf_id)
        if found is None and self._offered is not None:
            result = self._relocalize_in_offered(stamp_s, feats)
            if result is not None:
                return result
        if found is not None:
            tracked, kf_id = found
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
        self._lost_count += 1
        limit = cfg.relocalization.max_lost_frames + (
            cfg.relocalization.assist_wait_frames if self._awaiting_map else 0
        )
        if self._lost_count > limit:
            # reset() announces the new segment (EVENT_NEW_SEGMENT); the node logs it.
            self.reset()
            result = self._initialize(stamp_s, feats, STATE_NEW_SEGMENT)
            if not result.ok:
                result.message = "new map segment started; " + result.message
            return result
        return self._result(
            stamp_s, False, STATE_LOST, message=f"lost for {self._lost_count} frames"
        )

    def _relocalize_in_offered(self, stamp_s: float, feats: FrameFeatures) -> TrackResult | None:
        """PnP against the server's local map; a pose found starts a keyframe there."""
        if self._sensor.monocular:  # no depth for the new keyframe's points
            return None
        xyz, desc = self._offered
        T_map_cam, matched = pnp_against_points(feats, xyz, desc, self.config, self._sensor)
        if T_map_cam is None:
            return None
        self._offered = None
        self._T_map_cam = T_map_cam
        kf_id = self._insert_keyframe(stamp_s, feats, T_map_cam, np.zeros(0, int), np.zeros(0, int))
        kf = self._map.keyframes[kf_id]
        self._last_point_ids = kf.map_point_ids[kf.map_point_ids > 0].astype(np.int64)
        self._velocity = np.eye(4)
        self._lost_count = 0
        self._state = STATE_OK
        return self._result(
            stamp_s,
            True,
            STATE_RELOCALIZED,
            kf_id=kf_id,
            message=f"relocalized in the team map ({len(matched)} points of the server's local "
            "map)",
        )

    def _accept(self, tracked: Tracked) -> None:
        self._T_map_cam = tracked.T_map_cam
        self._last_point_ids = tracked.point_ids
        if tracked.ref_kf_id:
            self._ref_kf_id = tracked.ref_kf_id

    def _plausible(self, T_map_cam: np.ndarray) -> bool:
        """Reject jumps no camera makes since the previous frame (a wrong PnP or a bad local
        minimum): faster than ``max_speed_m_s`` or ``max_turn_rate_deg_s``."""
        if self._state in (STATE_LOST, STATE_INITIALIZING):
            return True
        step = invert(self._T_map_cam) @ T_map_cam
        dt = self._frame_dt_s
        return (
            np.linalg.norm(step[:3, 3]) <= self.config.tracking.max_speed_m_s * dt
            and rotation_angle_deg(step[:3, :3]) <= self.config.tracking.max_turn_rate_deg_s * dt
        )

    # --- keyframes --------------------------------------------------------------------------------
    def _insert_keyframe(
        self, stamp_s, feats: FrameFeatures, T_map_cam, kp_idx, point_ids, submit: bool = True
    ) -> int:
        """Create a keyframe from the frame and (``submit``) hand it to local mapping."""
        kf_id = self._next_kf_id
        self._next_kf_id += 1
        add_keyframe(
            self._map,
            kf_id,
            stamp_s,
            self.map_segment,
            feats,
            T_map_cam,
            kp_idx,
            point_ids,
            self.config,
            self.scales,
            self._depth_images.make(*self._frame_images),
        )
        self._ref_kf_id = kf_id
        self._frames_since_kf = 0
        if submit:
            self._mapper.submit(kf_id)
        return kf_id

    def _emit(self, event: VoEvent) -> None:
        with self._events_lock:
            self._events.append(event)
