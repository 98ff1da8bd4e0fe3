"""The report of a run, pure over what was recorded (:class:`RunData`) and the ground truth
(:class:`RunInput`): per-robot and team ATE/RPE (evo), merge errors and latencies, bandwidth per
topic and robot, timing; trajectory files, plots and the team map PLY in the results folder.

What a run published is recorded by :mod:`coop_slam.ros.run_recorder` (into :mod:`.run_data`);
its radio use is summed up by :mod:`.bandwidth`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ..datasets import write_tum_trajectory
from ..geometry import path_length
from ..playback import build_schedule
from ..registration.camera import RegistrationError
from ..registration.umeyama import umeyama
from ..team.map_scale import scale_translation
from .agreement import KeyframeCloud, team_agreement
from .bandwidth import bandwidth, downlink_kBps, topic_bandwidth, uplink_by_kind, uplink_kBps
from .map_results import DenseTruth, map_results, world_of
from .merge_accuracy import (
    link_errors,
    local_merge_error,
    map_units,
    merge_scale_errors,
    metres_per_unit,
)
from .metrics import EvaluationError, ate, merge_error, rpe_rmse, team_ate
from .overlap_view import plot_overlap
from .plots import plot_path_errors, plot_team, plot_trajectories
from .report import count_wrong_merges, new_report, write_report
from .run_data import RobotRun, RunData, RunInput


def run_input_of(source, keep_timing: bool = False) -> RunInput:
    """The run input of a played scenario or dataset (see :func:`coop_slam.playback.load_streams`):
    ground truth on the playback timeline, frames without ground truth left out."""
    schedule = build_schedule(source.streams, keep_timing)
    gts = {}
    for stream in source.streams:
        # A robot's frames keep their order on the timeline.
        stamps = np.array([s.play_s for s in schedule if s.robot_id == stream.robot_id])
        poses = stream.sequence.frame_poses()
        ok = np.all(np.isfinite(poses), axis=(1, 2))
        gts[stream.robot_id] = (stamps[ok], poses[ok])
    return RunInput(
        [s.robot_id for s in source.streams],
        len(schedule),
        schedule[0].play_s if schedule else 0.0,
        schedule[-1].play_s if schedule else 0.0,
        gts,
        (source.meta or {}).get("overlap"),
        [s.sequence.camera.sensor for s in source.streams],
        world_of(source.meta or {}),
    )


def _sim3_scale(points_src: np.ndarray, points_dst: np.ndarray) -> float | None:
    """Scale of the least-squares similarity of two matched point sets (None when degenerate)."""
    if len(points_src) < 3:
        return None
    try:
        return float(umeyama(points_src, points_dst, with_scale=True)[1])
    except RegistrationError:
        return None


def _robot_accuracy(entry: dict, r: RobotRun, rid: int, gts: dict, world_metric: bool):
    """A robot's own ATE (Sim(3) for a monocular map), into ``entry``; returns the ATE result used
    for its map's ground-truth placement (None for a monocular map: its map transform has a
    scale) and the result for pooling."""
    stamps, poses = r.first_segment_arrays()
    stamps_gt, poses_gt = gts[rid]
    try:
        res = ate(stamps, poses, stamps_gt, poses_gt, correct_scale=entry["sensor"] == "mono")
    except EvaluationError:
        return None, None
    if entry["sensor"] != "mono":
        entry["ate_rmse_m"] = res.rmse_m
        return res, res
    entry["ate_sim3_rmse_m"] = res.rmse_m
    if world_metric and r.team_keyframes:
        # The server's scale of the map: its keyframes in world (metric) against the client's.
        ids = sorted(set(r.team_keyframes) & set(r.keyframes))
        s_server = _sim3_scale(
            np.array([r.keyframes[k][1][:3, 3] for k in ids]).reshape(-1, 3),
            np.array([r.team_keyframes[k][1][:3, 3] for k in ids]).reshape(-1, 3),
        )
        if s_server is not None:
            entry["scale_error"] = s_server / res.scale - 1.0
    return None, res


def _client_path_accuracy(
    entry: dict, r: RobotRun, T_base_cam: np.ndarray, gt: tuple, mono: bool
) -> tuple[np.ndarray, np.ndarray]:
    """``path_ate_rmse_m`` (the client's last published path, aligned alone: its first map
    segment, as ``ate_rmse_m``) and ``path_team_gap_m`` (its keyframes of the current segment
    placed in world by the robot's latest ``T_world_map``, which is that segment's, against the
    server's optimized ones: median distance). Returns the first segment's path (stamps, camera
    poses)."""
    known = r.keyframe_segments and all(k > 0 for k, _, _ in r.path)
    current = r.keyframe_segments[max(r.keyframe_segments)] if known else None

    def poses(keep) -> tuple[np.ndarray, np.ndarray]:
        sel = [(t, T @ T_base_cam) for k, t, T in r.path if not known or keep(k)]
        return np.array([t for t, _ in sel]), np.array([T for _, T in sel]).reshape(-1, 4, 4)

    stamps, poses_cam = poses(r.in_first_segment)
    if len(gt[0]) and len(stamps):  # (a restarted client's path holds later segments only)
        try:
            entry["path_ate_rmse_m"] = ate(stamps, poses_cam, *gt, correct_scale=mono).rmse_m
        except EvaluationError:
            pass
    first = (stamps, poses_cam)
    if r.T_world_map is None:
        return first
    # Keyframes by id (a robot's clock may be off the server's), by stamp in older recordings.
    team = {k if known else round(t, 6): T for k, (t, T) in r.team_keyframes.items()}
    keep = lambda k: r.keyframe_segments.get(k) == current  # noqa: E731
    keys = [k if known else round(t, 6) for k, t, _ in r.path if not known or keep(k)]
    _, poses_cam = poses(keep)
    gaps = [
        np.linalg.norm((r.T_world_map @ scale_translation(T, r.map_scale))[:3, 3] - team[k][:3, 3])
        for k, T in zip(keys, poses_cam)
        if k in team
    ]
    if gaps:
        entry["path_team_gap_m"] = float(np.median(gaps))
    return first


@dataclass
class _RobotResults:
    """What the per-robot part of a report hands on to the merges, the team ATE and the plots."""

    # Ground-truth pose of each robot's map frame: the SE(3) alignment of its keyframe trajectory
    # to ground truth (as for its ATE), so a map's drift is averaged rather than frozen at one
    # frame.
    T_world_map_gt: dict = field(default_factory=dict)
    true_scale: dict = field(default_factory=dict)  # monocular robot -> metres per unit of its map
    own_ate: dict = field(default_factory=dict)  # robot -> (its own ATE, keyframes it was on)
    published: dict = field(default_factory=dict)  # robot -> its client's path (first segment)
    est_world: dict = field(default_factory=dict)  # robot -> its keyframes in world: stamps, poses
    gt_world: dict = field(default_factory=dict)  # ... and their ground truth, where it has some
    # Low-bandwidth mode: the server holds whole (and optimizes) only the keyframes it asked for.
    signatures_only: bool = False


def evaluate_run(
    run: RunData,
    gts: dict,
    overlap: dict | None = None,
    out_dir: str | None = None,
    sensors: dict | None = None,
    T_base_cam: np.ndarray | None = None,
) -> dict:
    """The report dict (see :mod:`.report`) of a run against ground truth ``gts`` (robot id ->
    (stamps, T_world_cam) on the playback timeline, as in :class:`RunInput`; empty arrays
    where a robot has none, whose accuracy fields then stay null); writes trajectories and plots
    into ``out_dir``. ``sensors`` (robot id -> rgbd / stereo / mono) defaults to what each
    robot's keyframes said; each robot's camera mount (its description's, else ``T_base_cam``)
    places its published path (base_link poses) at the camera (``path_ate_rmse_m``; none
    without a mount)."""
    robot_ids = sorted(gts)
    report = new_report(robot_ids)
    _adopt_loaded_keyframes(run)
    sensors = {
        rid: (sensors or {}).get(rid) or run.robots.get(rid, RobotRun()).sensor or "rgbd"
        for rid in robot_ids
    }
    world_groups = run.server_stats.get("groups") or [[rid] for rid in robot_ids]
    world = next((set(g) for g in world_groups if min(robot_ids, default=0) in g), set())
    world_metric = any(sensors[r] != "mono" for r in world)
    results = _RobotResults(signatures_only=bool(run.server_stats.get("pull")))
    for entry, rid in zip(report["robots"], robot_ids):
        _evaluate_robot(
            entry,
            run,
            rid,
            gts,
            sensors[rid],
            world_metric and rid in world,
            results,
            out_dir,
            T_base_cam,
        )
    merge_units, unit_timeline = map_units(run, sensors)
    report["merges"].extend(_merge_entries(run, gts, overlap, merge_units, results))
    # A wrong merge is a wrong registration: judged at the matched keyframes, where odometry drift
    # (which only the team optimization can remove) does not enter.
    report["wrong_merges"] = count_wrong_merges(
        [
            {"trans_err_m": m["local_trans_err_m"], "rot_err_deg": m["local_rot_err_deg"]}
            for m in report["merges"]
        ]
    )
    report["groups"] = run.server_stats.get("groups") or [[rid] for rid in robot_ids]
    est_world = _team_accuracy(report, results, robot_ids, world_metric, out_dir)
    _server_figures(report, run, robot_ids)
    report["links"] = link_errors(run, gts, report["groups"], unit_timeline, results.true_scale)
    report["overlap_agreement"] = _overlap_agreement(run, out_dir)
    report["bandwidth"] = bandwidth(run)
    report["topics"] = topic_bandwidth(run)
    if out_dir:
        _plot_robot_paths(out_dir, run, gts, robot_ids, sensors, results.published, est_world)
    return report


def _adopt_loaded_keyframes(run: RunData) -> None:
    """A robot of a map loaded from an earlier session sends nothing in this run: its keyframes
    are the server's optimized ones, taken back into its own map frame."""
    for r in run.robots.values():
        if not r.keyframes and r.team_keyframes:
            T_map_world = np.eye(4) if r.T_world_map is None else np.linalg.inv(r.T_world_map)
            r.keyframes = {k: (t, T_map_world @ T) for k, (t, T) in r.team_keyframes.items()}
            r.keyframe_stamps = {k: t for k, (t, _) in r.team_keyframes.items()}


def _evaluate_robot(
    entry: dict,
    run: RunData,
    rid: int,
    gts: dict,
    sensor: str,
    world_metric: bool,
    results: _RobotResults,
    out_dir: str | None,
    T_base_cam: np.ndarray | None,
) -> None:
    """A robot's entry of the report: its counts, timing and radio, and with keyframes its
    accuracy (``world_metric``: it is in the metric world group); its trajectories into
    ``out_dir``."""
    r = run.robots.get(rid, RobotRun())
    stamps_gt, poses_gt = gts[rid]
    entry["frames"] = r.frames
    entry["frames_dropped"] = r.frames_dropped
    entry["mapping_backlog_max"] = r.mapping_backlog_max
    entry["uplink_kBps"], entry["uplink_by_kind"] = uplink_kBps(run, r), uplink_by_kind(run, r)
    entry["downlink_kBps"] = downlink_kBps(run, rid)
    if rid in run.radio_bytes and run.duration_s > 0:  # on the wire: every topic, TCP and ROS
        sent, received = run.radio_bytes[rid]
        entry["radio_up_kBps"] = sent / run.duration_s / 1000.0
        entry["radio_down_kBps"] = received / run.duration_s / 1000.0
    entry["frames_mapping_behind"] = r.frames_mapping_behind
    entry["path_length_m"] = path_length(poses_gt) if len(poses_gt) else None
    entry["keyframes"] = len(r.keyframes)
    entry["tracking_lost"] = r.lost_frames
    entry["sensor"] = sensor
    if r.track_ms:
        entry["track_ms_mean"] = float(np.mean(r.track_ms))
        entry["track_ms_p95"] = float(np.percentile(r.track_ms, 95))
    if r.keyframes:
        _keyframe_accuracy(entry, r, rid, gts, sensor, world_metric, results, out_dir, T_base_cam)
    if out_dir and len(stamps_gt):
        write_tum_trajectory(
            os.path.join(out_dir, "trajectories", f"robot_{rid}_groundtruth.txt"),
            stamps_gt,
            poses_gt,
        )


def _keyframe_accuracy(
    entry: dict,
    r: RobotRun,
    rid: int,
    gts: dict,
    sensor: str,
    world_metric: bool,
    results: _RobotResults,
    out_dir: str | None,
    T_base_cam: np.ndarray | None,
) -> None:
    """A robot's own ATE and RPE, its published path's and its keyframes' as the team placed
    them, into ``entry`` and ``results``."""
    stamps_gt, poses_gt = gts[rid]
    stamps, poses = r.first_segment_arrays()
    placed, res = _robot_accuracy(entry, r, rid, gts, world_metric)
    if placed is not None:
        results.T_world_map_gt[rid] = placed.T_gt_est
    if res is not None:
        results.own_ate[rid] = (res.rmse_m, res.count)
        if sensor == "mono":
            results.true_scale[rid] = res.scale
    if out_dir:
        write_tum_trajectory(
            os.path.join(out_dir, "trajectories", f"robot_{rid}_keyframes.txt"),
            stamps,
            poses,
        )
    try:
        if sensor != "mono":  # in the map's own units otherwise
            entry["rpe_rmse_m"] = rpe_rmse(stamps, poses, stamps_gt, poses_gt)
    except EvaluationError:
        pass
    mount = r.T_base_cam if r.T_base_cam is not None else T_base_cam  # its own, where it said
    if r.path and mount is not None:
        results.published[rid] = _client_path_accuracy(entry, r, mount, gts[rid], sensor == "mono")
    _world_estimate(entry, r, rid, (stamps, poses), gts[rid], sensor, results, out_dir)


def _world_estimate(
    entry: dict,
    r: RobotRun,
    rid: int,
    keyframes: tuple,
    gt: tuple,
    sensor: str,
    results: _RobotResults,
    out_dir: str | None,
) -> None:
    """Where the team placed a robot's keyframes (stamps, poses) in world, into
    ``results.est_world``: the server's optimized poses (their ATE: ``server_ate_rmse_m``), else
    the client's moved by its latest correction, none before a merge."""
    stamps, poses = keyframes
    stamps_gt, poses_gt = gt
    est_world = results.est_world
    if r.team_keyframes:  # the server's optimized poses, in world
        ids = sorted(r.team_keyframes)
        est_world[rid] = (
            np.array([r.team_keyframes[k][0] for k in ids]),
            np.array([r.team_keyframes[k][1] for k in ids]),
        )
        # The same alignment as the robot's own ATE: how much better the team map
        # places this robot's keyframes than its own odometry (pose-graph sharing brings
        # the client's own trajectory to it).
        try:
            entry["server_ate_rmse_m"] = ate(
                *est_world[rid], stamps_gt, poses_gt, correct_scale=sensor == "mono"
            ).rmse_m
        except EvaluationError:
            pass
        entry["team_keyframes_optimized"] = len(ids)
        if results.signatures_only:
            # The team ATE is compared with the robots' own, over all their keyframes: those the
            # server holds only as signatures are placed as it places their neighbours.
            est_world[rid] = _with_signature_only_placed(
                est_world[rid], r, set(ids), sensor == "mono"
            )
    elif r.T_world_map is not None:  # client poses moved by the latest correction
        est_world[rid] = (stamps, np.einsum("ij,njk->nik", r.T_world_map, poses))
    if rid in est_world and len(stamps_gt):
        results.gt_world[rid] = (stamps_gt, poses_gt)
        if out_dir:
            write_tum_trajectory(
                os.path.join(out_dir, "trajectories", f"robot_{rid}_world.txt"),
                *est_world[rid],
            )


def _with_signature_only_placed(server: tuple, r: RobotRun, optimized: set, mono: bool) -> tuple:
    """``server`` (stamps, poses in world of the keyframes the server optimized) and the robot's
    other keyframes of the same map segments, each placed as the team map places its nearest
    optimized keyframe of its segment (by time; a monocular map's offsets scaled by the team's
    scale of that segment), in time order. A segment the team map does not hold (one lost
    before and not merged back) has no place in world."""
    first = min(r.keyframe_segments.values(), default=0)
    segment = lambda k: r.keyframe_segments.get(k, first)  # noqa: E731
    held = sorted(k for k in optimized if k in r.keyframes)
    stamps, poses = list(server[0]), list(server[1])
    current = max(r.keyframe_segments.values(), default=0)
    for seg in sorted({segment(k) for k in held}):
        held_seg = [k for k in held if segment(k) == seg]
        rest = sorted(k for k in r.keyframes if k not in optimized and segment(k) == seg)
        scale = 1.0
        if mono:  # the team's lengths per length of the segment's map
            scale = r.map_scale if seg == current else None
            if scale is None:
                scale = _sim3_scale(
                    np.array([r.keyframes[k][1][:3, 3] for k in held_seg]).reshape(-1, 3),
                    np.array([r.team_keyframes[k][1][:3, 3] for k in held_seg]).reshape(-1, 3),
                )
        if not rest or scale is None:
            continue
        held_s = np.array([r.keyframes[k][0] for k in held_seg])
        for k in rest:
            stamp, T_map_cam = r.keyframes[k]
            near = held_seg[int(np.argmin(np.abs(held_s - stamp)))]
            T_near_cam = scale_translation(np.linalg.inv(r.keyframes[near][1]) @ T_map_cam, scale)
            stamps.append(stamp)
            poses.append(r.team_keyframes[near][1] @ T_near_cam)
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps)[order], np.asarray(poses).reshape(-1, 4, 4)[order]


def _merge_entries(
    run: RunData, gts: dict, overlap: dict | None, units: list, results: _RobotResults
) -> list[dict]:
    """The report's merges: transform error against ground truth and latency from the first
    moment ground truth allowed a merge of that kind (``units``: per merge, as
    :func:`.merge_accuracy.map_units` gives them)."""
    return [_merge_entry(m, unit, run, gts, overlap, results) for m, unit in zip(run.merges, units)]


def _merge_entry(
    m: dict, units: tuple, run: RunData, gts: dict, overlap: dict | None, results: _RobotResults
) -> dict:
    """One merge's entry (``units``: its item of :func:`.merge_accuracy.map_units`)."""
    a, b = m["robot_a"], m["robot_b"]
    entry = {
        "type": m["type"],
        "robots": [a, b],
        "stamp": m["stamp_s"],
        "trans_err_m": None,
        "rot_err_deg": None,
        "latency_s": None,
        "published_s": m.get("published_s"),
        "scale_err": None,
        "local_scale_err": None,
    }
    # A map transform is judged for robots' first map segments (their maps as placed
    # against ground truth); a later segment's merge at its keyframes (local) only.
    first_segments = all(
        run.robots.get(m[f"robot_{s}"], RobotRun()).in_first_segment(m[f"keyframe_{s}"])
        for s in "ab"
    )
    T_world_map_gt, true_scale = results.T_world_map_gt, results.true_scale
    if a in T_world_map_gt and b in T_world_map_gt and first_segments:
        entry["trans_err_m"], entry["rot_err_deg"] = merge_error(
            m["T_mapA_mapB"], T_world_map_gt[a], T_world_map_gt[b]
        )
    unit, unit_a, unit_b = units
    if m.get("scale") is not None and (unit_a != 1.0 or unit_b != 1.0):
        entry["scale_err"], entry["local_scale_err"] = merge_scale_errors(
            m, unit_a, unit_b, run, gts, true_scale
        )
    length = metres_per_unit(unit, true_scale)  # between monocular maps: the first side's units
    metric = dict(m, T_camA_camB=scale_translation(m["T_camA_camB"], length)) if length else None
    local = local_merge_error(metric, run, gts) if metric is not None else None
    entry["local_trans_err_m"], entry["local_rot_err_deg"] = local if local else (None, None)
    evidence = _first_evidence(overlap, m["type"], a, b)
    if evidence is not None:
        entry["latency_s"] = m["stamp_s"] - evidence
    return entry


def _team_accuracy(
    report: dict,
    results: _RobotResults,
    robot_ids: list,
    world_metric: bool,
    out_dir: str | None,
) -> dict:
    """``team_ate_rmse_m`` (one alignment for all; a lone robot's own ATE), each robot's share and
    ``single_ate_pooled_m``; the team's pictures into ``out_dir``. Returns the robots' keyframes
    in world as judged: those with ground truth when there was a team ATE."""
    est_world, gt_world, own_ate = results.est_world, results.gt_world, results.own_ate
    if len(gt_world) >= 2 or (len(robot_ids) == 1 and gt_world):
        est_world = {rid: est_world[rid] for rid in gt_world}  # only what can be judged
        try:  # one SE(3) alignment for all; a similarity for monocular maps only (no metres)
            team = team_ate(est_world, gt_world, correct_scale=not world_metric)
            report["team_ate_rmse_m"] = team.rmse_m
        except EvaluationError:
            team = None
        shares = team.robot_rmse() if team is not None else {}
        for entry in report["robots"]:
            entry["team_map_ate_rmse_m"] = shares.get(entry["id"])
        if out_dir and team is not None:
            plot_team(out_dir, est_world, gt_world, team, {r: e for r, (e, _) in own_ate.items()})
    if report["team_ate_rmse_m"] is None and len(robot_ids) == 1:
        report["team_ate_rmse_m"] = report["robots"][0]["ate_rmse_m"]
    if report["team_ate_rmse_m"] is not None:
        # Pooled over the robots the team ATE covers, so that the two compare like with like.
        pooled = [own_ate[r] for r in (gt_world or own_ate) if r in own_ate]
        n = sum(c for _, c in pooled)
        if n:
            report["single_ate_pooled_m"] = float(np.sqrt(sum(e**2 * c for e, c in pooled) / n))
    return est_world


def _server_figures(report: dict, run: RunData, robot_ids: list) -> None:
    """What the server reported: its time per keyframe, the keyframes it stored (and pulled) of
    those each robot sent, the duplicates it received and its loop closures."""
    report["server_ms_per_keyframe"] = run.server_stats.get("ms_per_keyframe_mean")
    stored = run.server_stats.get("keyframes_stored") or {}
    clocks = run.server_stats.get("clock_offset_s") or {}
    pull = run.server_stats.get("pull")
    report["pull"] = pull
    for entry, rid in zip(report["robots"], robot_ids):
        r = run.robots.get(rid, RobotRun())
        sent = int(sum(r.keyframes_sent_sessions))
        entry["keyframes_sent"] = sent
        entry["keyframes_held_back"] = int(sum(r.held_back_sessions))
        entry["keyframes_stored"] = stored.get(str(rid))
        entry["clock_offset_s"] = clocks.get(str(rid))
        # Sent by this run's clients and never stored (a loaded map's robots sent none now).
        entry["keyframes_lost"] = (
            max(0, sent - int(stored[str(rid)])) if str(rid) in stored and sent else None
        )
        if pull:  # low-bandwidth mode: stored as signatures, these whole
            entry["keyframes_pulled"] = int((pull.get("held") or {}).get(str(rid), 0))
    report["duplicates_received"] = run.server_stats.get("duplicates")
    report["loop_closures"] = run.server_stats.get("loops")


def _plot_robot_paths(
    out_dir: str,
    run: RunData,
    gts: dict,
    robot_ids: list,
    sensors: dict,
    published: dict,
    est_world: dict,
) -> None:
    """Each robot's keyframe trajectory against ground truth, and with published paths the
    pose-graph sharing's picture: what each client shows (odometry, team map, published path)."""
    mono = {rid for rid in robot_ids if sensors[rid] == "mono"}
    plot_trajectories(
        out_dir,
        {rid: r.first_segment_arrays() for rid, r in run.robots.items() if r.keyframes},
        gts,
        mono=mono,
    )
    if published:  # the pose-graph sharing's picture: what each client shows
        series = {}
        for rid, path in published.items():
            r = run.robots[rid]
            series[rid] = [("odometry (as sent)", *r.first_segment_arrays())]
            if r.team_keyframes:
                series[rid].append(("team map (server)", *est_world[rid]))
            series[rid].append(("published path (client)", *path))
        plot_path_errors(out_dir, series, gts, mono=mono)


def _overlap_agreement(run: RunData, out_dir: str | None) -> list[dict]:
    """Ground-truth-free agreement of the robots' maps where they overlap (see
    :mod:`.agreement`), over the robots in ``world`` (their keyframes' depth points at the
    server's optimized poses); draws ``overlap.png`` into ``out_dir``."""
    clouds = {}
    for rid, r in sorted(run.robots.items()):
        kfs = [
            KeyframeCloud(stamp, T_world_cam, r.keyframe_points[k])
            for k, (stamp, T_world_cam) in sorted(r.team_keyframes.items())
            if len(r.keyframe_points.get(k, ()))
        ]
        if kfs:
            clouds[rid] = kfs
    if len(clouds) < 2:
        return []
    result = team_agreement(clouds)
    pairs = [
        {"robots": p["robots"], "inter_m": p["inter_m"], "intra_m": p["intra_m"]}
        for p in result.pairs
    ]
    if out_dir:
        plot_overlap(
            os.path.join(out_dir, "overlap.png"),
            clouds,
            up_axis="z",  # world (REP-103)
            pairs=result.pairs,
            title="team map where robots overlap (world, top view and a slice)",
        )
    return pairs


def _first_evidence(overlap: dict | None, kind: str, a: int, b: int) -> float | None:
    """When ground truth first allowed a merge of this kind between robots a and b: the first
    co-observation of one scene for a rendezvous, the first revisit (either robot seeing what the
    other saw earlier) for place recognition, the other kind when that never happened. Marker
    sightings alone do not count: without a shared scene no merge is possible (nor wanted)."""
    if not overlap:
        return None
    from ..synthetic.overlap import OverlapEvents

    events = OverlapEvents.from_dict(overlap)
    revisits = [t for t in (events.revisit_time(a, b), events.revisit_time(b, a)) if t is not None]
    revisit = min(revisits) if revisits else None
    together = events.rendezvous_time(a, b)
    first, second = (together, revisit) if kind == "rendezvous" else (revisit, together)
    return first if first is not None else second


def evaluate_results(
    out_dir: str,
    run: RunData,
    gts: dict,
    overlap: dict | None = None,
    sensors: dict | None = None,
    extra: dict | None = None,
    T_base_cam: np.ndarray | None = None,
    dense_truth: DenseTruth | None = None,
):
    """Report, trajectories, plots and the team map PLYs and grid of one run into ``out_dir``
    (arguments as for :func:`evaluate_run`; ``extra``: fields of the run the recording does not
    hold, e.g. the faults injected; ``dense_truth``: the synthetic world, see :mod:`.map_results`);
    returns (report, report.json path, report.md path, PLY path or None)."""
    report = evaluate_run(run, gts, overlap, out_dir, sensors, T_base_cam)
    dense, ply = map_results(out_dir, run, dense_truth)
    report.update(extra or {}, **dense)
    json_path, md_path = write_report(out_dir, report)
    return report, json_path, md_path, ply
