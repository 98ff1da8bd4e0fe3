"""Local mapping: what ORB-SLAM's LocalMapping thread does after tracking inserted a keyframe.

For each new keyframe: refresh the statistics of the points it observes, (monocular cameras only)
triangulate new points with its covisible keyframes, fuse duplicate points with its covisible
keyframes (projection search both ways), cull recent points that tracking rarely finds, run local
BA over the covisible window (when no other keyframe is waiting), then cull redundant keyframes.
RGB-D and stereo keyframes got their new points from depth when tracking inserted them; a
monocular camera measures no depth, so its new points come from ORB-SLAM's CreateNewMapPoints
(:meth:`LocalMapper.triangulate_new_points`). Keyframe events (new / update / remove) are emitted
from here, so a NEW keyframe is sent after its points were fused and its covisibility is known.

With ``threaded`` the steps run in a background thread and the BA itself in a worker process (GTSAM
holds the GIL); every map access holds ``Map.lock`` for a short, bounded section, and each such step
first lets the frame being tracked finish (tracking comes first, as in ORB-SLAM: the camera does not
wait; mapping catches up between frames). Without it, :meth:`LocalMapper.process` runs
synchronously, which makes results deterministic (tests).
"""

from __future__ import annotations

import contextlib
import logging
import pickle
import queue
import threading
import time
from collections.abc import Callable

import numpy as np

from ..geometry import transform_error
from ..optim.bundle import BaProblem, BaResult, BaWorker, run_local_ba, take_worker
from .config import VoConfig
from .dense_depth import resolved
from .features import FrameFeatures, level_scales
from .map import Map, MapKeyframe
from .matching import project_points, search_by_projection
from .sensor import Sensor
from .triangulation import triangulation_pairs, triangulation_view
from .types import EVENT_KEYFRAME_NEW, EVENT_KEYFRAME_REMOVE, EVENT_KEYFRAME_UPDATE, VoEvent

log = logging.getLogger(__name__)


def keyframe_features(kf: MapKeyframe, sensor: Sensor) -> FrameFeatures:
    """The keyframe's keypoints as FrameFeatures (cached on the keyframe for its KD-tree)."""
    if kf.features is None:
        kf.features = FrameFeatures(
            uv_px=kf.uv_px.astype(float),
            size_px=kf.size_px,
            angle_deg=kf.angle_deg,
            octaves=kf.octaves,
            descriptors=kf.descriptors,
            depths_m=kf.depths_m,
            points_cam=np.full((len(kf), 3), np.nan),
            u_right_px=sensor.u_right(kf.uv_px[:, 0], kf.depths_m.astype(float)),
        )
    return kf.features


class LocalMapper:
    """Local mapping steps on a :class:`Map`; ``submit`` queues a keyframe (see module
    docstring)."""

    def __init__(
        self,
        config: VoConfig,
        sensor: Sensor,
        get_map: Callable[[], Map],
        emit: Callable[[VoEvent], None],
    ):
        self.config = config.for_sensor(sensor.camera.sensor)
        self.sensor = sensor
        self.camera = camera = sensor.camera
        self.K = camera.K
        self.bf = sensor.bf
        self.scales = level_scales(config)
        self._get_map = get_map
        self._emit = emit
        self.stats = {
            "ba_runs": 0,
            "ba_ms": [],
            "kf_culled": 0,
            "points_culled": 0,
            "fused": 0,
            "triangulated": 0,
        }
        self._queue: queue.Queue = queue.Queue()
        # Keyframes announced (NEW; only those may be culled or updated) -> T_map_cam last sent.
        self._sent_pose: dict[int, np.ndarray] = {}
        self._idle = threading.Event()
        self._idle.set()
        # Cleared while tracking works on a frame: the mapping thread's steps wait for it (see
        # _step).
        self._frame_done = threading.Event()
        self._frame_done.set()
        self._frames_open = 0
        self._stop = False
        self._thread: threading.Thread | None = None
        self._worker: BaWorker | None = None
        if config.threaded:
            if config.ba.enabled:
                try:
                    self._worker = take_worker()
                    self._worker.lower_priority(config.ba.worker_nice)
                except OSError as exc:
                    log.warning(
                        "local BA worker process unavailable (%s); BA runs in the thread", exc
                    )
            self._thread = threading.Thread(target=self._loop, name="vo_local_mapping", daemon=True)
            self._thread.start()

    # --- public -----------------------------------------------------------------------------------
    @property
    def idle(self) -> bool:
        return self._idle.is_set() and self._queue.empty()

    @property
    def pending(self) -> int:
        return self._queue.qsize()

    @property
    def backlog(self) -> int:
        """Keyframes handed over and not finished: queued, plus the one in process."""
        return self._queue.unfinished_tasks

    def submit(self, kf_id: int) -> None:
        """Hand a new keyframe to local mapping (processed now unless threaded)."""
        if self._thread is None:
            self.process(kf_id, run_ba=True)
        else:
            self._idle.clear()
            self._queue.put(kf_id)

    def flush(self, timeout_s: float = 60.0) -> None:
        """Wait until every queued keyframe is processed (threaded mode)."""
        if self._thread is None:
            return
        self._frame_done.set()  # the caller waits for mapping: nothing to yield to
        t_end = time.monotonic() + timeout_s
        while not (self._queue.empty() and self._idle.is_set()) and time.monotonic() < t_end:
            time.sleep(0.005)
        if self._frames_open:  # called within a frame (a reset while tracking)
            self._frame_done.clear()

    def frame_started(self) -> None:
        """Tracking works on a frame: mapping steps wait until the matching
        :meth:`frame_finished` (calls nest). Both from the tracking thread."""
        self._frames_open += 1
        self._frame_done.clear()

    def frame_finished(self) -> None:
        self._frames_open = max(0, self._frames_open - 1)
        if self._frames_open == 0:
            self._frame_done.set()

    @contextlib.contextmanager
    def _step(self, vmap: Map):
        """One bounded step of mapping work under the map lock. In the mapping thread it first
        waits (at most ``mapping_yield_max_s``) for the frame being tracked: both are Python in
        one interpreter, so a step running beside tracking takes the interpreter lock from it
        in 5 ms slices, and a frame's time doubled whenever a keyframe was being mapped."""
        if self._thread is not None and threading.current_thread() is self._thread:
            self._frame_done.wait(self.config.mapping.yield_max_s)
        with vmap.lock:
            yield

    def close(self) -> None:
        self._stop = True
        if self._thread is not None:
            self._thread.join(timeout=30.0)
            self._thread = None
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    # --- the steps --------------------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop:
            try:
                kf_id = self._queue.get(timeout=0.05)
            except queue.Empty:
                self._idle.set()
                continue
            self._idle.clear()
            try:
                # BA only when no other keyframe waits, as ORB-SLAM: the newest one is more useful.
                self.process(kf_id, run_ba=self._queue.empty())
            except Exception:  # never let the mapping thread die silently
                log.exception("local mapping failed on keyframe %d", kf_id)
            finally:
                self._queue.task_done()
            if self._queue.empty():
                self._idle.set()

    def process(self, kf_id: int, run_ba: bool) -> None:
        # The map lock is taken step by step (one fuse target, one culling candidate at a time),
        # never for a whole keyframe: tracking waits for it, and a hold per keyframe shows in the
        # tracking thread's worst frame times (docs/tuning.md). Tracking only adds keyframes,
        # points and observations, never removes any, so each step re-checks what it uses is still
        # alive and stays consistent.
        vmap = self._get_map()
        if kf_id not in vmap.keyframes:
            return
        self._process_new_keyframe(vmap, kf_id)
        kf = vmap.keyframes.get(kf_id)
        if kf is not None:  # a stereo keyframe's depth image: waited for without the map lock
            kf.depth_image = resolved(kf.depth_image)
        with self._step(vmap):
            self._cull_points(vmap)
            if kf_id not in vmap.keyframes:
                return
            self._announce(EVENT_KEYFRAME_NEW, vmap, kf_id)
        if run_ba and self.config.ba.enabled:
            with self._step(vmap):
                problem = self.build_ba_problem(vmap, kf_id)
                epoch = vmap.epoch
            if problem is not None:
                result = self._run_ba(problem)
                with self._step(vmap):
                    if vmap is self._get_map() and vmap.epoch == epoch:
                        self.apply_ba_result(vmap, result)
        if self.config.keyframes.culling and vmap is self._get_map():
            self.cull_keyframes(vmap, kf_id)

    def _run_ba(self, problem: BaProblem) -> BaResult:
        if self._worker is not None:
            try:
                return self._worker.run(problem)
            except (OSError, EOFError, pickle.UnpicklingError) as exc:
                # A dead worker: BA goes on in-process (slower tracking, but still a map).
                log.warning("local BA worker failed (%s); running BA in-process", exc)
                self._worker.close()
                self._worker = None
        return run_local_ba(problem)

    def _process_new_keyframe(self, vmap: Map, kf_id: int) -> None:
        with self._step(vmap):
            kf = vmap.keyframes[kf_id]
            vmap.update_covisibility(kf_id, propagate=False)
            neighbours = vmap.best_covisible(kf_id, self.config.mapping.fuse_neighbors)
            touched = {int(p) for p in kf.map_point_ids[kf.map_point_ids > 0]}
        if self.sensor.monocular:
            touched |= self.triangulate_new_points(vmap, kf_id)
        if neighbours:
            touched |= self._fuse(vmap, kf, neighbours)
        touched_ids = np.array(sorted(touched), dtype=np.int64)
        for chunk in np.array_split(touched_ids, max(1, len(touched_ids) // 256)):
            with self._step(vmap):  # in chunks: see process()
                vmap.update_point_stats(chunk, self.scales)
        with self._step(vmap):
            if kf_id in vmap.keyframes:
                vmap.update_covisibility(kf_id)

    def _fuse(self, vmap: Map, kf: MapKeyframe, neighbours: list[int]) -> set[int]:
        """Project points between the keyframe and its neighbours; merge duplicates, add
        observations."""
        touched: set[int] = set()
        with self._step(vmap):
            pts = vmap.points
            own = kf.map_point_ids[kf.map_point_ids > 0].astype(np.int64)
            others = np.unique(
                np.concatenate([vmap.keyframes[n].map_point_ids for n in neighbours]).astype(
                    np.int64
                )
            )
            others = others[(others > 0) & pts.is_alive(others)]
            others = np.setdiff1d(others, own)
            targets = [(vmap.keyframes[n], own) for n in neighbours] + [(kf, others)]
        for target, pids in targets:
            with self._step(vmap):
                touched |= self._fuse_into(vmap, target, pids)
        return touched  # may hold points fused away since: update_point_stats skips dead ones

    def _fuse_into(self, vmap: Map, target: MapKeyframe, pids: np.ndarray) -> set[int]:
        """Fuse points ``pids`` into keyframe ``target`` (map lock held)."""
        pts = vmap.points
        touched: set[int] = set()
        if target.keyframe_id not in vmap.keyframes:
            return touched
        pids = pids[pts.is_alive(pids)]
        pids = pids[~np.isin(pids, target.map_point_ids)]
        if len(pids) == 0:
            return touched
        feats = keyframe_features(target, self.sensor)
        proj = project_points(
            np.linalg.inv(target.T_map_cam),
            pts.xyz[pids],
            self.K,
            self.bf,
            (self.camera.width, self.camera.height),
            self.scales,
            pts.max_dist[pids],
            pts.normal[pids],
        )
        pi, kj, _ = search_by_projection(
            proj,
            pts.desc[pids],
            feats,
            self.config.mapping.fuse_radius_px,
            self.scales,
            self.config.tracking.max_descriptor_distance,
            1.0,
            chi2_gate=5.991,
        )
        for p_row, j in zip(pi, kj):
            pid = int(pids[proj.index[p_row]])
            if not pts.alive[pid] or target.keyframe_id in pts.obs[pid]:
                continue
            existing = int(target.map_point_ids[j])
            if existing and pts.alive[existing]:
                # Keep the point seen more often; the other one's observations move to it.
                if len(pts.obs[existing]) >= len(pts.obs[pid]):
                    vmap.replace_point(pid, existing)
                    touched.add(existing)
                else:
                    vmap.replace_point(existing, pid)
                    touched.add(pid)
                self.stats["fused"] += 1
            else:
                vmap.add_observation(pid, target.keyframe_id, int(j))
                touched.add(pid)
        return touched

    # --- new points of a monocular keyframe -----------------------------------------------------
    def triangulate_new_points(self, vmap: Map, kf_id: int) -> set[int]:
        """New map points of keyframe ``kf_id`` from its keypoints without a point, triangulated
        with the keypoints without a point of its best covisible keyframes (ORB-SLAM's
        CreateNewMapPoints; see :func:`.triangulation.triangulation_pairs`). Returns the new
        points' ids.

        The matching and triangulation run on copies outside the map lock; the points are added
        under it, each only if both keypoints are still free. Stops early when another keyframe
        waits (threaded), as ORB-SLAM: tracking needs the next keyframe's points more."""
        cfg = self.config
        created: set[int] = set()
        with self._step(vmap):
            if kf_id not in vmap.keyframes:
                return created
            neighbours = vmap.best_covisible(kf_id, cfg.triangulation.neighbors)
        for i, other in enumerate(neighbours):
            if i > 0 and self._thread is not None and not self._queue.empty():
                break
            with self._step(vmap):
                if kf_id not in vmap.keyframes or other not in vmap.keyframes:
                    continue
                views = [triangulation_view(vmap, k) for k in (kf_id, other)]
            found = triangulation_pairs(*views, self.config, self.K, self.scales)
            if found is None:
                continue
            i1, i2, xyz = found
            with self._step(vmap):
                kf1, kf2 = vmap.keyframes.get(kf_id), vmap.keyframes.get(other)
                if kf1 is None or kf2 is None:
                    continue
                free = (kf1.map_point_ids[i1] == 0) & (kf2.map_point_ids[i2] == 0)
                i1, i2, xyz = i1[free], i2[free], xyz[free]
                if len(i1) == 0:
                    continue
                centre = kf1.T_map_cam[:3, 3]
                ray = xyz - centre
                dist = np.linalg.norm(ray, axis=1)
                ids = vmap.points.add(
                    xyz,
                    kf1.descriptors[i1],
                    kf1.angle_deg[i1],
                    ray / dist[:, None],
                    dist * self.scales[kf1.octaves[i1].astype(int)],
                    vmap.kf_seq,
                )
                for pid, a, b in zip(ids.tolist(), i1.tolist(), i2.tolist()):
                    vmap.add_observation(pid, kf_id, a)
                    vmap.add_observation(pid, other, b)
            created.update(ids.tolist())
            self.stats["triangulated"] += len(ids)
        return created

    def _cull_points(self, vmap: Map) -> None:
        """Remove recent points that tracking rarely finds or no second keyframe sees."""
        cfg = self.config
        pts = vmap.points
        ids = pts.alive_ids()
        age = vmap.kf_seq - pts.created_kf_seq[ids]
        recent = ids[age <= 3]
        if len(recent) == 0:
            return
        ratio = pts.found[recent] / np.maximum(pts.visible[recent], 1)
        n_obs = np.array([len(pts.obs[int(p)]) for p in recent])
        age = vmap.kf_seq - pts.created_kf_seq[recent]
        min_obs = cfg.mapping.cull_min_observations
        bad = (ratio < cfg.mapping.cull_found_ratio) | ((age >= 2) & (n_obs < min_obs))
        for pid in recent[bad]:
            vmap.remove_point(int(pid))
        self.stats["points_culled"] += int(bad.sum())

    # --- local BA ---------------------------------------------------------------------------------
    def _ba_sizes(self) -> tuple[int, int]:
        """(keyframes optimized, at most fixed) of a local BA for this camera (a monocular map's
        window is wider: see VoConfig.sensors)."""
        return self.config.ba.window, self.config.ba.max_fixed

    def build_ba_problem(self, vmap: Map, kf_id: int) -> BaProblem | None:
        """Local BA around keyframe ``kf_id`` (map lock held): its covisible window free, the
        keyframes outside it that see the window's points fixed; None when nothing is left to
        optimize."""
        cfg = self.config
        found = self._ba_keyframes(vmap, kf_id)
        if found is None:
            return None
        all_ids, fixed, local = found
        found = self._ba_observations(vmap, all_ids, local)
        if found is None:
            return None
        local, obs_kf, obs_pt, obs_kp, uv, ur, octave = found
        scale_anchor = None
        if self.sensor.monocular and fixed.sum() < 2:
            scale_anchor = _scale_anchor(vmap, all_ids, fixed)
        return BaProblem(
            segment=vmap.segment,
            kf_ids=np.array(all_ids),
            T_map_cam=np.array([vmap.keyframes[k].T_map_cam for k in all_ids]),
            fixed=fixed,
            point_ids=local,
            points_map=vmap.points.xyz[local].copy(),
            obs_kf=obs_kf,
            obs_pt=obs_pt,
            obs_kp=obs_kp,
            obs_uv=uv,
            obs_u_right=ur,
            obs_octave=octave,
            fx=self.camera.fx,
            fy=self.camera.fy,
            cx=self.camera.cx,
            cy=self.camera.cy,
            baseline_m=self.sensor.baseline_m,
            scale_factor=cfg.features.scale_factor,
            n_levels=cfg.features.n_levels,
            iterations=cfg.ba.iterations,
            huber_mono=cfg.ba.huber_mono,
            huber_stereo=cfg.ba.huber_stereo,
            planar_up_cam=np.asarray(cfg.planar.up_cam, float) if cfg.planar.enabled else None,
            planar_sigmas=(np.radians(cfg.planar.sigma_tilt_deg), cfg.planar.sigma_height_m),
            chi2_mono=cfg.tracking.chi2_mono,
            chi2_stereo=cfg.tracking.chi2_stereo,
            scale_anchor=scale_anchor,
        )

    def _ba_keyframes(
        self, vmap: Map, kf_id: int
    ) -> tuple[list[int], np.ndarray, np.ndarray] | None:
        """(keyframe ids: the window, then the fixed ones; which are fixed; the window's points
        seen twice or more) of a local BA, or None."""
        n_window, max_fixed = self._ba_sizes()
        window = [kf_id] + vmap.best_covisible(kf_id, n_window - 1)
        pts = vmap.points
        local = np.unique(
            np.concatenate([vmap.keyframes[k].map_point_ids for k in window]).astype(np.int64)
        )
        local = local[(local > 0) & pts.is_alive(local)]
        # Points seen by a single keyframe constrain nothing but themselves: leave them out.
        n_obs = np.fromiter((len(pts.obs[int(p)]) for p in local), dtype=np.int64, count=len(local))
        local = local[n_obs >= 2]
        if len(local) == 0:
            return None
        candidates = set()
        for k in window:
            candidates.update(int(c) for c in vmap.keyframes[k].covisible_ids)
        candidates -= set(window)
        candidates = [c for c in candidates if c in vmap.keyframes]
        counts = [int(np.isin(vmap.keyframes[c].map_point_ids, local).sum()) for c in candidates]
        order = np.argsort(counts)[::-1][:max_fixed]
        fixed_ids = [candidates[i] for i in order if counts[i] > 0]
        all_ids = window + fixed_ids
        fixed = np.array([False] * len(window) + [True] * len(fixed_ids))
        if vmap.first_keyframe_id in window:
            fixed[window.index(vmap.first_keyframe_id)] = True
        if not fixed.any():
            if len(window) < 2:
                return None
            fixed[int(np.argmin(window))] = True  # gauge: hold the oldest keyframe
        return all_ids, fixed, local

    def _ba_observations(self, vmap: Map, all_ids: list[int], local: np.ndarray) -> tuple | None:
        """(points kept, then per observation of them: keyframe index, point index, keypoint
        index, uv, u_right (NaN without depth), octave) of a local BA, or None."""
        obs_kf, obs_pt, obs_kp = [], [], []
        for k_idx, k in enumerate(all_ids):
            mp = vmap.keyframes[k].map_point_ids.astype(np.int64)
            pos = np.searchsorted(local, mp)
            pos = np.minimum(pos, len(local) - 1)
            hit = np.flatnonzero((mp > 0) & (local[pos] == mp))
            obs_kf.append(np.full(len(hit), k_idx))
            obs_pt.append(pos[hit])
            obs_kp.append(hit)
        obs_kf = np.concatenate(obs_kf)
        obs_pt = np.concatenate(obs_pt)
        obs_kp = np.concatenate(obs_kp)
        uv = np.zeros((len(obs_kf), 2))
        ur = np.full(len(obs_kf), np.nan)
        octave = np.zeros(len(obs_kf), int)
        for k_idx, k in enumerate(all_ids):
            sel = obs_kf == k_idx
            kf = vmap.keyframes[k]
            idx = obs_kp[sel]
            uv[sel] = kf.uv_px[idx]
            ur[sel] = self.sensor.u_right(kf.uv_px[idx, 0], kf.depths_m[idx].astype(float))
            octave[sel] = kf.octaves[idx]
        # Keep points the problem constrains: >= 2 observations in it, at least one with depth. A
        # point seen once without depth (its creator outside the problem) leaves the linear system
        # singular, and mono-only points over a short baseline are barely determined: LM then
        # spends most of its time raising lambda (docs/tuning.md).
        # A monocular camera has only such points (triangulated with enough parallax).
        n_in = np.bincount(obs_pt, minlength=len(local))
        good_pt = n_in >= 2
        if not self.sensor.monocular:
            good_pt &= np.bincount(obs_pt, weights=np.isfinite(ur), minlength=len(local)) >= 1
        keep = good_pt[obs_pt]
        new_index = np.cumsum(good_pt) - 1
        obs_kf, obs_kp, uv, ur, octave = (
            obs_kf[keep],
            obs_kp[keep],
            uv[keep],
            ur[keep],
            octave[keep],
        )
        obs_pt = new_index[obs_pt[keep]]
        local = local[good_pt]
        if len(local) == 0:
            return None
        return local, obs_kf, obs_pt, obs_kp, uv, ur, octave

    def apply_ba_result(self, vmap: Map, result: BaResult) -> None:
        cfg = self.config
        self.stats["ba_runs"] += 1
        self.stats["ba_ms"].append(result.time_ms)
        if not result.ok or result.segment != vmap.segment:
            if result.message:
                log.warning(result.message)
            return
        pts = vmap.points
        moved = []
        for k, T in zip(result.kf_ids, result.T_map_cam):
            kf = vmap.keyframes.get(int(k))
            if kf is not None:
                if not np.allclose(kf.T_map_cam, T):
                    moved.append(int(k))
                kf.T_map_cam = T
        alive = pts.is_alive(result.point_ids)
        pts.xyz[result.point_ids[alive]] = result.points_map[alive]
        # Erase outlier observations only if the map still holds them (fusion may have moved them).
        for o in np.flatnonzero(result.outlier_obs):
            pid, k = int(result.obs_point_ids[o]), int(result.obs_kf_ids[o])
            if pts.alive[pid] and k in pts.obs[pid]:
                vmap.erase_observation(pid, k)
        # A keyframe tracking inserted after this BA's own can sit in its window before local
        # mapping announced it: its NEW (a snapshot taken later) carries the moved pose, and an
        # UPDATE first would reach the server as an unknown keyframe, its NEW then as a duplicate.
        for k in moved:
            sent = self._sent_pose.get(k)
            if sent is not None:
                trans_m, rot_deg = transform_error(vmap.keyframes[k].T_map_cam, sent)
                if (
                    trans_m >= cfg.mapping.update_min_trans_m
                    or rot_deg >= cfg.mapping.update_min_rot_deg
                ):
                    self._announce(EVENT_KEYFRAME_UPDATE, vmap, k)

    def _announce(self, kind: str, vmap: Map, kf_id: int) -> None:
        snapshot = vmap.snapshot(kf_id)
        self._sent_pose[kf_id] = snapshot.T_map_cam
        self._emit(VoEvent(kind, vmap.segment, kf_id, snapshot))

    # --- keyframe culling -------------------------------------------------------------------------
    def cull_keyframes(self, vmap: Map, kf_id: int) -> list[int]:
        """Remove covisible keyframes whose close points (monocular: all points) are >= 90 % seen
        by >= 3 other keyframes at the same or a finer scale (ORB-SLAM's KeyFrameCulling)."""
        removed = []
        with self._step(vmap):
            if kf_id not in vmap.keyframes:
                return removed
            candidates = vmap.best_covisible(kf_id, 2 * self._ba_sizes()[0])
        for c in candidates:
            with self._step(vmap):  # one candidate at a time: see process()
                if self._cull_keyframe(vmap, kf_id, c):
                    removed.append(c)
        return removed

    def _cull_keyframe(self, vmap: Map, kf_id: int, c: int) -> bool:
        """Remove keyframe ``c`` if it is redundant (map lock held)."""
        cfg = self.config
        if (
            c in (vmap.first_keyframe_id, kf_id)
            or c not in vmap.keyframes
            or c not in self._sent_pose
        ):
            return False
        kf = vmap.keyframes[c]
        if self.sensor.monocular:  # all its points (ORB-SLAM's monocular culling)
            idx = np.flatnonzero(kf.map_point_ids > 0)
        else:
            d = kf.depths_m
            idx = np.flatnonzero(
                (kf.map_point_ids > 0) & (d > 0) & (d <= self.sensor.close_depth_m)
            )
        if len(idx) == 0:
            return False
        row, other, oidx = vmap.observation_table(kf.map_point_ids[idx])
        # Observations by other keyframes at the same or a finer scale (octave <= own + 1).
        sel = other != c
        row, other, oidx = row[sel], other[sel], oidx[sel]
        if len(row) == 0:
            return False
        fine = (
            vmap.gather(other, oidx, "octaves").astype(int) <= kf.octaves[idx][row].astype(int) + 1
        )
        n_fine = np.bincount(row[fine], minlength=len(idx))
        redundant = int((n_fine >= cfg.keyframes.cull_observers).sum())
        if redundant <= cfg.keyframes.cull_redundancy * len(idx):
            return False
        vmap.remove_keyframe(c)
        self._sent_pose.pop(c, None)
        self.stats["kf_culled"] += 1
        self._emit(VoEvent(EVENT_KEYFRAME_REMOVE, vmap.segment, c, None))
        return True


def _scale_anchor(vmap: Map, all_ids: list[int], fixed: np.ndarray) -> tuple[int, int] | None:
    """A monocular map's scale is free with fewer than two fixed keyframes: hold the distance of
    the fixed keyframe to the farthest free one (see BaProblem.scale_anchor)."""
    centres = np.array([vmap.keyframes[k].T_map_cam[:3, 3] for k in all_ids])
    f = int(np.flatnonzero(fixed)[0])
    dist = np.where(fixed, -1.0, np.linalg.norm(centres - centres[f], axis=1))
    if dist.max() > 0:
        return (f, int(np.argmax(dist)))
    return None
