"""Run the visual odometry over a dataset sequence and score it (shared by tests, bench and demo).

``run_sequence`` feeds every frame to :class:`VisualOdometry` (as fast as possible, or paced at
``rate_hz`` like a live camera), waits for local mapping to finish and returns per-frame poses and
timings plus the final keyframes. ``ate_rmse`` is the absolute trajectory error after an SE(3)
Umeyama alignment (no scale), computed with evo.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..datasets.base import Sequence
from ..timestamps import associate
from ..vo.config import VoConfig
from ..vo.map import MapKeyframe
from ..vo.pipeline import VisualOdometry
from ..vo.types import EVENT_KEYFRAME_NEW, EVENT_KEYFRAME_REMOVE, STATE_LOST
from .metrics import ate


@dataclass
class VoRun:
    """Outcome of one sequence run."""

    name: str
    stamps_s: np.ndarray  # (F,)
    poses_se3: np.ndarray  # (F, 4, 4) T_map_cam per frame; NaN where tracking was not ok
    ok: np.ndarray  # (F,) bool
    states: list[str]
    segments: np.ndarray  # (F,) map segment of each frame
    track_ms: np.ndarray  # (F,) wall time of track()
    mapping_backlog: np.ndarray  # (F,) keyframes local mapping had not finished after track()
    cpu_ms: np.ndarray  # (F,) CPU time of the tracking thread in track()
    keyframes: list[MapKeyframe]  # final keyframes of the last segment (after local BA and culling)
    keyframes_created: int
    keyframes_removed: int
    wall_s: float
    mapping_stats: dict = field(default_factory=dict)

    @property
    def n_lost(self) -> int:
        return sum(s == STATE_LOST for s in self.states)

    @property
    def n_segments(self) -> int:
        return len(np.unique(self.segments))

    def timing(self) -> dict:
        t = self.track_ms
        return {
            "mean_ms": float(np.mean(t)) if len(t) else float("nan"),
            "p95_ms": float(np.percentile(t, 95)) if len(t) else float("nan"),
            "max_ms": float(np.max(t)) if len(t) else float("nan"),
            "cpu_mean_ms": float(np.mean(self.cpu_ms)) if len(t) else float("nan"),
            "cpu_p95_ms": float(np.percentile(self.cpu_ms, 95)) if len(t) else float("nan"),
        }

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_s (K,), T_map_cam (K, 4, 4)) of the final keyframes."""
        stamps = np.array([kf.stamp_s for kf in self.keyframes], dtype=float)
        poses = np.array([kf.T_map_cam for kf in self.keyframes], dtype=float).reshape(-1, 4, 4)
        return stamps, poses


def run_sequence(
    seq: Sequence,
    config: VoConfig | None = None,
    progress: Callable[[int, int, object], None] | None = None,
    rate_hz: float | None = None,
) -> VoRun:
    """Track every frame of ``seq``; ``progress(i, n, result)`` is called after each frame."""
    config = config or VoConfig()
    vo = VisualOdometry(config, seq.camera)
    n = len(seq)
    stamps = seq.stamps_s
    poses = np.full((n, 4, 4), np.nan)
    ok = np.zeros(n, bool)
    states, segments, track_ms, cpu_ms = [], np.zeros(n, int), np.zeros(n), np.zeros(n)
    backlog = np.zeros(n, int)
    created = removed = 0
    t_start = time.perf_counter()
    try:
        for i, frame in enumerate(seq.frames):
            if seq.camera.sensor == "mono":  # the colour (left) image of any data
                image, second = seq.load_color(frame), None
            else:
                image, second = seq.load_frame(frame)
            if rate_hz:
                # Pace like a live camera: frame i is available at t_start + i / rate.
                wait = t_start + i / rate_hz - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            res = vo.track(frame.stamp_s, image, second)
            states.append(res.state)
            segments[i] = res.map_segment
            track_ms[i] = res.track_ms
            cpu_ms[i] = res.cpu_ms
            backlog[i] = vo.mapping_backlog
            ok[i] = res.ok
            if res.ok:
                poses[i] = res.T_map_cam
            for ev in vo.drain_events():
                created += ev.kind == EVENT_KEYFRAME_NEW
                removed += ev.kind == EVENT_KEYFRAME_REMOVE
            if progress is not None:
                progress(i, n, res)
        vo.flush()
        for ev in vo.drain_events():
            created += ev.kind == EVENT_KEYFRAME_NEW
            removed += ev.kind == EVENT_KEYFRAME_REMOVE
        keyframes = vo.keyframes()
        stats = dict(vo.mapping_stats)
    finally:
        vo.close()
    return VoRun(
        name=seq.name,
        stamps_s=stamps,
        poses_se3=poses,
        ok=ok,
        states=states,
        segments=segments,
        track_ms=track_ms,
        mapping_backlog=backlog,
        cpu_ms=cpu_ms,
        keyframes=keyframes,
        keyframes_created=int(created),
        keyframes_removed=int(removed),
        wall_s=time.perf_counter() - t_start,
        mapping_stats=stats,
    )


def ate_rmse(stamps_s, poses_est, poses_gt, correct_scale: bool = False) -> float:
    """ATE RMSE [m] of estimated against ground-truth poses (same length and order), after an SE(3)
    Umeyama alignment without scale (Sim(3) with ``correct_scale``: a monocular map). Pairs where
    either pose is NaN are left out."""
    stamps_s = np.asarray(stamps_s, dtype=float)
    poses_est = np.asarray(poses_est, dtype=float).reshape(-1, 4, 4)
    poses_gt = np.asarray(poses_gt, dtype=float).reshape(-1, 4, 4)
    if not len(stamps_s) == len(poses_est) == len(poses_gt):
        raise ValueError(
            f"ate_rmse needs equally many stamps, estimates and ground truth poses, got "
            f"{len(stamps_s)}, {len(poses_est)}, {len(poses_gt)}"
        )
    valid = np.isfinite(poses_est).all(axis=(1, 2)) & np.isfinite(poses_gt).all(axis=(1, 2))
    if valid.sum() < 3:
        return float("nan")
    stamps = stamps_s[valid]
    est, gt = poses_est[valid], poses_gt[valid]
    return ate(stamps, est, stamps, gt, max_dt_s=1e-9, correct_scale=correct_scale).rmse_m


def ground_truth_at(seq: Sequence, stamps_s) -> np.ndarray:
    """Ground-truth T_world_cam of ``seq`` at the given frame stamps (NaN where there is none)."""
    stamps_s = np.asarray(stamps_s, float)
    out = np.full((len(stamps_s), 4, 4), np.nan)
    i_query, i_frame = associate(stamps_s, seq.stamps_s, 1e-6)
    out[i_query] = seq.frame_poses()[i_frame]
    return out


def keyframe_ate(run: VoRun, seq: Sequence) -> float:
    """Keyframe trajectory ATE RMSE [m] of a run against the sequence's ground truth (aligned
    with Sim(3) for a monocular camera, whose map has no metric scale)."""
    stamps, poses = run.keyframe_trajectory()
    mono = seq.camera.sensor == "mono"
    return ate_rmse(stamps, poses, ground_truth_at(seq, stamps), correct_scale=mono)


def frame_ate(run: VoRun, seq: Sequence) -> float:
    """Per-frame trajectory ATE RMSE [m] (frames tracked ok in the last segment)."""
    last = run.segments == run.segments.max() if len(run.segments) else np.zeros(0, bool)
    poses = np.where((run.ok & last)[:, None, None], run.poses_se3, np.nan)
    return ate_rmse(run.stamps_s, poses, seq.frame_poses())
