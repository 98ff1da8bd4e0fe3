"""Turn what a run published (keyframes, frame stats, merges, corrections, message sizes) and the
ground truth into the report: per-robot and team ATE (evo), merge errors and latencies, bandwidth,
timing, trajectory files and plots.

Pure functions over :class:`RunData`; the demo fills RunData live (see ``tools/demo.py``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ..datasets import write_tum_trajectory
from ..evaluation import EvaluationError, ate, merge_error, team_ate
from ..geometry import invert, path_length
from ..playback import RobotStream, build_schedule
from ..report import count_wrong_merges, new_report


@dataclass
class RobotRun:
    frames: int = 0
    lost_frames: int = 0
    track_ms: list = field(default_factory=list)
    keyframes: dict = field(default_factory=dict)  # id -> (stamp_s, T_map_cam), latest version
    first_keyframe: tuple | None = None  # (stamp_s, T_map_cam) as first published
    kf_bytes: list = field(default_factory=list)  # (sim stamp_s, bytes) per KeyFrame message
    T_world_map: np.ndarray | None = None  # latest correction, when merged


@dataclass
class RunData:
    robots: dict = field(default_factory=dict)  # robot id -> RobotRun
    merges: list = field(default_factory=list)  # dicts: type, robot_a, robot_b, stamp_s, T_mapA_mapB
    server_stats: dict = field(default_factory=dict)
    duration_s: float = 0.0  # sim time from first to last frame


def _gt_of(stream: RobotStream, keep_timing: bool):
    """Ground truth of a robot on the playback timeline: (stamps, T_world_cam)."""
    sched = [s for s in build_schedule([stream], keep_timing) if s.robot_id == stream.robot_id]
    poses = stream.sequence.frame_poses()
    ok = np.all(np.isfinite(poses), axis=(1, 2))
    stamps = np.array([s.play_s for s in sched])
    return stamps[ok], poses[ok]


def _kf_arrays(run: RobotRun):
    ids = sorted(run.keyframes)
    return (np.array([run.keyframes[k][0] for k in ids]),
            np.array([run.keyframes[k][1] for k in ids]).reshape(-1, 4, 4))


def evaluate_run(run: RunData, streams: list[RobotStream], keep_timing: bool = False,
                 overlap: dict | None = None, out_dir: str | None = None) -> dict:
    """The report dict (see coop_slam.report); writes trajectories and plots into ``out_dir``."""
    report = new_report([s.robot_id for s in streams])
    gts = {s.robot_id: _gt_of(s, keep_timing) for s in streams}
    est_world, gt_world = {}, {}
    # Ground-truth pose of each robot's map frame: the SE(3) alignment of its keyframe trajectory
    # to ground truth (as for its ATE), so a map's drift is averaged rather than frozen at one frame.
    T_world_map_gt = {}
    for entry, stream in zip(report["robots"], streams):
        rid = stream.robot_id
        r = run.robots.get(rid, RobotRun())
        stamps_gt, poses_gt = gts[rid]
        entry["frames"] = r.frames
        entry["path_length_m"] = path_length(poses_gt) if len(poses_gt) else None
        entry["keyframes"] = len(r.keyframes)
        entry["tracking_lost"] = r.lost_frames
        if r.track_ms:
            entry["track_ms_mean"] = float(np.mean(r.track_ms))
            entry["track_ms_p95"] = float(np.percentile(r.track_ms, 95))
        if r.keyframes:
            stamps, poses = _kf_arrays(r)
            try:
                res = ate(stamps, poses, stamps_gt, poses_gt)
                entry["ate_rmse_m"] = res.rmse_m
                T_world_map_gt[rid] = res.T_gt_est
            except EvaluationError:
                pass
            if out_dir:
                write_tum_trajectory(os.path.join(out_dir, "trajectories", f"robot_{rid}_keyframes.txt"),
                                     stamps, poses)
            if r.T_world_map is not None:
                est_world[rid] = (stamps, np.einsum("ij,njk->nik", r.T_world_map, poses))
                gt_world[rid] = (stamps_gt, poses_gt)
        if out_dir:
            write_tum_trajectory(os.path.join(out_dir, "trajectories", f"robot_{rid}_groundtruth.txt"),
                                 stamps_gt, poses_gt)
    # Merges: transform error against ground truth and latency from the first true overlap.
    for m in run.merges:
        a, b = m["robot_a"], m["robot_b"]
        entry = {"type": m["type"], "robots": [a, b], "stamp": m["stamp_s"], "trans_err_m": None,
                 "rot_err_deg": None, "latency_s": None}
        if a in T_world_map_gt and b in T_world_map_gt:
            entry["trans_err_m"], entry["rot_err_deg"] = merge_error(
                m["T_mapA_mapB"], T_world_map_gt[a], T_world_map_gt[b])
        local = _local_merge_error(m, run, gts)
        entry["local_trans_err_m"], entry["local_rot_err_deg"] = local if local else (None, None)
        first = _first_overlap(overlap, a, b)
        if first is not None:
            entry["latency_s"] = m["stamp_s"] - first
        report["merges"].append(entry)
    # A wrong merge is a wrong registration: judged at the matched keyframes, where odometry drift
    # (which only the team optimization can remove) does not enter.
    report["wrong_merges"] = count_wrong_merges(
        [{"trans_err_m": m["local_trans_err_m"], "rot_err_deg": m["local_rot_err_deg"]}
         for m in report["merges"]])
    report["groups"] = run.server_stats.get("groups") or [[s.robot_id] for s in streams]
    if len(est_world) >= 2:
        try:
            report["team_ate_rmse_m"] = team_ate(est_world, gt_world).rmse_m
        except EvaluationError:
            pass
    elif len(streams) == 1 and report["robots"][0]["ate_rmse_m"] is not None:
        report["team_ate_rmse_m"] = report["robots"][0]["ate_rmse_m"]
    report["server_ms_per_keyframe"] = run.server_stats.get("ms_per_keyframe_mean")
    report["bandwidth"] = _bandwidth(run)
    if out_dir:
        _plot(out_dir, run, streams, gts)
    return report


def _local_merge_error(m: dict, run: RunData, gts: dict) -> tuple[float, float] | None:
    """Error of T_mapA_mapB against the truth at the matched keyframes: the map transform that the
    true relative pose of the two keyframes would have given, with both keyframes' estimated poses."""
    poses = []
    for robot, kf in ((m["robot_a"], m.get("keyframe_a")), (m["robot_b"], m.get("keyframe_b"))):
        r = run.robots.get(robot)
        snapshot = (m.get("keyframes_at_merge") or {}).get(robot)
        if snapshot is None and r is not None:
            snapshot = r.keyframes.get(kf)
        if snapshot is None or robot not in gts:
            return None
        stamp, T_map_cam = snapshot
        stamps_gt, poses_gt = gts[robot]
        if len(stamps_gt) == 0:
            return None
        i = int(np.argmin(np.abs(stamps_gt - stamp)))
        if abs(stamps_gt[i] - stamp) > 0.02:
            return None
        poses.append((T_map_cam, poses_gt[i]))
    (T_mapA_camA, T_world_camA), (T_mapB_camB, T_world_camB) = poses
    # merge_error(T_est, T_world_mapA, T_world_mapB) with the maps placed so that the keyframes'
    # estimated poses coincide with their true ones.
    return merge_error(m["T_mapA_mapB"], T_world_camA @ invert(T_mapA_camA),
                       T_world_camB @ invert(T_mapB_camB))


def _first_overlap(overlap: dict | None, a: int, b: int) -> float | None:
    if not overlap:
        return None
    times = [e["stamp_s"] for e in overlap.get("first_overlap", []) if sorted(e["robots"]) == sorted([a, b])]
    return min(times) if times else None


def _bandwidth(run: RunData) -> dict:
    per_robot, peaks, total = [], [], 0
    for r in run.robots.values():
        if not r.kf_bytes:
            continue
        t = np.array([s for s, _ in r.kf_bytes])
        b = np.array([n for _, n in r.kf_bytes], float)
        total += b.sum()
        per_robot.append(b.sum() / max(run.duration_s, 1e-9) / 1e3)
        bins = np.floor(t - t.min()).astype(int)
        peaks.append(np.bincount(bins, weights=b).max() / 1e3)  # busiest second of sim time
    if not per_robot:
        return {"per_robot_kBps": None, "peak_kBps": None, "total_MB": None}
    return {"per_robot_kBps": float(np.mean(per_robot)), "peak_kBps": float(max(peaks)),
            "total_MB": float(total / 1e6)}


def _plot(out_dir: str, run: RunData, streams, gts) -> None:
    """Top view of every robot's keyframes (aligned to ground truth) and ground truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, stream in enumerate(streams):
        rid, c = stream.robot_id, colours[k % len(colours)]
        stamps_gt, poses_gt = gts[rid]
        ax.plot(poses_gt[:, 0, 3], poses_gt[:, 1, 3], "--", color=c, alpha=0.5,
                label=f"robot_{rid} ground truth")
        r = run.robots.get(rid)
        if r and len(r.keyframes) >= 3:
            stamps, poses = _kf_arrays(r)
            try:
                res = ate(stamps, poses, stamps_gt, poses_gt)
            except EvaluationError:
                continue
            aligned = np.einsum("ij,njk->nik", res.T_gt_est, poses)
            ax.plot(aligned[:, 0, 3], aligned[:, 1, 3], "-o", ms=2, color=c,
                    label=f"robot_{rid} keyframes (ATE {100 * res.rmse_m:.1f} cm)")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)
    ax.set_title("trajectories (each robot aligned to its ground truth)")
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "trajectories.png"), dpi=110)
    plt.close(fig)
