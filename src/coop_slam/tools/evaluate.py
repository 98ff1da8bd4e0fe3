"""Turn what a run published (keyframes, frame stats, merges, corrections, optimized team paths,
message sizes) and the ground truth into the report: per-robot and team ATE/RPE (evo), merge errors
and latencies, bandwidth per topic and robot, timing, trajectory files and plots.

:class:`RunRecorder` builds :class:`RunData` from the system's messages, live (the demo's monitor)
or from the bag the demo records (``scripts/evaluate``); :func:`evaluate_run` is pure over RunData.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ..datasets import write_tum_trajectory
from ..evaluation import EvaluationError, ate, merge_error, rpe_rmse, team_ate
from ..geometry import invert, path_length, transform_error
from ..playback import COLOR_TOPIC, GROUND_TRUTH_TOPIC, build_schedule
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
    # server's optimized keyframe poses in world (latest /team_map/robot_k/path, when merged):
    # id -> (stamp_s, T_world_cam)
    team_keyframes: dict = field(default_factory=dict)


@dataclass
class RunData:
    robots: dict = field(default_factory=dict)  # robot id -> RobotRun
    merges: list = field(
        default_factory=list
    )  # dicts: type, robot_a, robot_b, stamp_s, T_mapA_mapB
    server_stats: dict = field(default_factory=dict)
    duration_s: float = 0.0  # sim time from first to last frame
    topic_bytes: dict = field(default_factory=dict)  # topic -> [(sim t_s, bytes)] per message
    team_cloud: object = None  # latest /team_map/cloud message


_ROBOT_TOPICS = {  # relative to /robot_k; the message type of each
    "keyframes": "coop_slam/KeyFrame",
    "frame_stats": "coop_slam/FrameStats",
    "correction": "coop_slam/MapCorrection",
    "pose": "geometry_msgs/PoseStamped",
    "path": "nav_msgs/Path",
    "local_map": "sensor_msgs/PointCloud2",
}
_TEAM_TOPICS = {
    "/merge_events": "coop_slam/MergeEvent",
    "/server/stats": "std_msgs/String",
    "/team_map/cloud": "sensor_msgs/PointCloud2",
    "/team_map/markers": "visualization_msgs/MarkerArray",
    "/robot_sightings": "coop_slam/RobotSighting",
    "/player/done": "std_msgs/Bool",
}


def _msg_class(type_name: str):
    import importlib

    pkg, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class RunRecorder:
    """Builds :class:`RunData` from what the system publishes: :meth:`feed` takes one message with
    the sim time it was seen at and its serialized size; the same code serves live and bag input."""

    def __init__(self, robot_ids: list[int]):
        import threading

        self.run = RunData(robots={int(r): RobotRun() for r in robot_ids})
        self.lock = threading.Lock()
        self.done = False  # the player said it has played everything

    def topics(self) -> dict[str, str]:
        """Topic -> message type of everything recorded (the demo's rosbag takes the same list)."""
        out = {f"/robot_{r}/{t}": ty for r in self.run.robots for t, ty in _ROBOT_TOPICS.items()}
        out.update({f"/team_map/robot_{r}/path": "nav_msgs/Path" for r in self.run.robots})
        out.update(_TEAM_TOPICS)
        return out

    def feed(self, topic: str, msg, t_s: float, nbytes: int) -> None:
        with self.lock:
            self.run.topic_bytes.setdefault(topic, []).append((float(t_s), int(nbytes)))
            parts = topic.strip("/").split("/")
            if topic == "/team_map/cloud":
                self.run.team_cloud = msg
            elif topic == "/merge_events":
                self._on_merge(msg)
            elif topic == "/server/stats":
                import json

                self.run.server_stats = json.loads(msg.data)
            elif topic == "/player/done":
                self.done = self.done or bool(msg.data)
            elif len(parts) == 3 and parts[0] == "team_map" and parts[2] == "path":
                self._on_team_path(msg, int(parts[1].split("_")[1]))
            elif len(parts) == 2 and parts[0].startswith("robot_"):
                robot_id = int(parts[0].split("_")[1])
                handler = getattr(self, f"_on_{parts[1]}", None)
                if robot_id in self.run.robots and handler is not None:
                    handler(msg, self.run.robots[robot_id], t_s, nbytes)

    def _on_frame_stats(self, msg, r: RobotRun, t_s, nbytes) -> None:
        r.frames += 1
        if msg.track_ms > 0:
            r.track_ms.append(float(msg.track_ms))
        if not msg.tracking_ok and r.first_keyframe is not None:
            r.lost_frames += 1

    def _on_keyframes(self, msg, r: RobotRun, t_s, nbytes) -> None:
        from ..keyframe import ACTION_REMOVE
        from ..ros.convert import MessageError, pose_from_msg

        r.kf_bytes.append((float(t_s), int(nbytes)))
        if msg.action == ACTION_REMOVE:
            r.keyframes.pop(msg.keyframe_id, None)
            return
        try:
            T = pose_from_msg(msg.pose)
        except MessageError:
            return
        stamp = msg.header.stamp.to_sec()
        r.keyframes[msg.keyframe_id] = (stamp, T)
        if r.first_keyframe is None:
            r.first_keyframe = (stamp, T)

    def _on_correction(self, msg, r: RobotRun, t_s, nbytes) -> None:
        from ..ros.convert import transform_from_msg

        r.T_world_map = transform_from_msg(msg.T_world_map) if msg.merged else None

    def _on_team_path(self, msg, robot_id: int) -> None:
        from ..ros.convert import MessageError, pose_from_msg

        r = self.run.robots.get(robot_id)
        if r is None:
            return
        if msg.header.frame_id != "world":
            r.team_keyframes = {}
            return
        poses = {}
        for ps in msg.poses:
            try:
                poses[ps.header.seq] = (ps.header.stamp.to_sec(), pose_from_msg(ps.pose))
            except MessageError:
                continue
        r.team_keyframes = poses

    def _on_merge(self, msg) -> None:
        from ..ros.convert import transform_from_msg

        # Stamps of the matched keyframes now: a keyframe the client culls later leaves the record.
        stamps = {}
        for robot, kf in ((msg.robot_a, msg.keyframe_a), (msg.robot_b, msg.keyframe_b)):
            known = self.run.robots[robot].keyframes.get(kf) if robot in self.run.robots else None
            if known is not None:
                stamps[robot] = known[0]
        self.run.merges.append(
            {
                "type": msg.type,
                "robot_a": msg.robot_a,
                "robot_b": msg.robot_b,
                "keyframe_a": msg.keyframe_a,
                "keyframe_b": msg.keyframe_b,
                "keyframe_stamps": stamps,
                "stamp_s": msg.header.stamp.to_sec(),
                "T_mapA_mapB": transform_from_msg(msg.T_mapA_mapB),
                "T_camA_camB": transform_from_msg(msg.T_camA_camB),
            }
        )


def run_data_from_bag(bag_path: str, robot_ids: list[int]) -> RunData:
    """Replay a recorded run through :class:`RunRecorder` (bag time is the sim time)."""
    import rosbag

    if not os.path.isfile(bag_path):
        raise EvaluationError(f"bag not found: {bag_path}")
    rec = RunRecorder(robot_ids)
    topics = rec.topics()
    try:
        bag = rosbag.Bag(bag_path)
    except (rosbag.ROSBagException, OSError) as exc:
        raise EvaluationError(f"cannot read bag {bag_path}: {exc}") from exc
    with bag:
        for topic, raw, t in bag.read_messages(topics=list(topics), raw=True):
            msg = _msg_class(topics[topic])()
            msg.deserialize(raw[1])
            rec.feed(topic, msg, t.to_sec(), len(raw[1]))
    return rec.run


@dataclass
class RunInput:
    """What a run plays and is judged against, whether from a scenario/dataset or a sensor bag."""

    robot_ids: list[int]
    frames: int  # colour images of all robots
    start_s: float  # first and last frame on the playback timeline [s]
    end_s: float
    gts: dict  # robot id -> (stamps, T_world_cam); empty arrays for robots without ground truth
    overlap: dict | None = None  # synthetic overlap events (merge latency), when known


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
    )


def read_bag_input(bag_path: str) -> RunInput:
    """The run input of a sensor bag (``scripts/demo --bag``): robots from
    ``/robot_<k>/camera/color/image_raw``, ground truth from ``/robot_<k>/ground_truth/pose`` (as
    the player publishes it)."""
    import rosbag

    from ..ros.convert import MessageError, pose_from_msg

    if not os.path.isfile(bag_path):
        raise EvaluationError(f"bag not found: {bag_path}")
    try:
        bag = rosbag.Bag(bag_path)
    except (rosbag.ROSBagException, OSError) as exc:
        raise EvaluationError(f"cannot read bag {bag_path}: {exc}") from exc
    with bag:
        topics = bag.get_type_and_topic_info().topics
        colors = {t: int(m.group(1)) for t in topics if (m := COLOR_TOPIC.match(t))}
        if not colors:
            raise EvaluationError(
                f"bag {bag_path} has no robot camera topics (/robot_<k>/camera/color/image_raw); "
                f"it has: {', '.join(sorted(topics)) or 'nothing'}"
            )
        robot_ids = sorted(colors.values())
        gt_topics = {t: int(m.group(1)) for t in topics if (m := GROUND_TRUTH_TOPIC.match(t))}
        samples = {rid: ([], []) for rid in robot_ids}
        if gt_topics:
            for topic, msg, _ in bag.read_messages(topics=list(gt_topics)):
                rid = gt_topics[topic]
                if rid not in samples:
                    continue
                try:
                    T = pose_from_msg(msg.pose, f"{topic} pose")
                except MessageError:
                    continue  # a NaN ground-truth sample is no sample
                samples[rid][0].append(msg.header.stamp.to_sec())
                samples[rid][1].append(T)
        gts = {}
        for rid, (stamps, poses) in samples.items():
            order = np.argsort(stamps)
            gts[rid] = (
                np.asarray(stamps, float)[order],
                np.asarray(poses, float).reshape(-1, 4, 4)[order],
            )
        return RunInput(
            robot_ids,
            sum(topics[t].message_count for t in colors),
            bag.get_start_time(),
            bag.get_end_time(),
            gts,
        )


def _kf_arrays(run: RobotRun):
    ids = sorted(run.keyframes)
    return (
        np.array([run.keyframes[k][0] for k in ids]),
        np.array([run.keyframes[k][1] for k in ids]).reshape(-1, 4, 4),
    )


def evaluate_run(
    run: RunData,
    gts: dict,
    overlap: dict | None = None,
    out_dir: str | None = None,
) -> dict:
    """The report dict (see coop_slam.report) of a run against ground truth ``gts`` (robot id ->
    (stamps, T_world_cam) on the playback timeline, as in :class:`RunInput`; empty arrays
    where a robot has none, whose accuracy fields then stay null); writes trajectories and plots
    into ``out_dir``."""
    robot_ids = sorted(gts)
    report = new_report(robot_ids)
    est_world, gt_world = {}, {}
    # Ground-truth pose of each robot's map frame: the SE(3) alignment of its keyframe trajectory
    # to ground truth (as for its ATE), so a map's drift is averaged rather than frozen at one
    # frame.
    T_world_map_gt = {}
    own_ate = {}  # robot -> (its own ATE, keyframes it was computed on)
    for entry, rid in zip(report["robots"], robot_ids):
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
                own_ate[rid] = (res.rmse_m, res.count)
            except EvaluationError:
                pass
            if out_dir:
                write_tum_trajectory(
                    os.path.join(out_dir, "trajectories", f"robot_{rid}_keyframes.txt"),
                    stamps,
                    poses,
                )
            try:
                entry["rpe_rmse_m"] = rpe_rmse(stamps, poses, stamps_gt, poses_gt)
            except EvaluationError:
                pass
            if r.team_keyframes:  # the server's optimized poses, in world
                ids = sorted(r.team_keyframes)
                est_world[rid] = (
                    np.array([r.team_keyframes[k][0] for k in ids]),
                    np.array([r.team_keyframes[k][1] for k in ids]),
                )
            elif r.T_world_map is not None:  # client poses moved by the latest correction
                est_world[rid] = (stamps, np.einsum("ij,njk->nik", r.T_world_map, poses))
            if rid in est_world and len(stamps_gt):
                gt_world[rid] = (stamps_gt, poses_gt)
                if out_dir:
                    write_tum_trajectory(
                        os.path.join(out_dir, "trajectories", f"robot_{rid}_world.txt"),
                        *est_world[rid],
                    )
        if out_dir and len(stamps_gt):
            write_tum_trajectory(
                os.path.join(out_dir, "trajectories", f"robot_{rid}_groundtruth.txt"),
                stamps_gt,
                poses_gt,
            )
    # Merges: transform error against ground truth and latency from the first moment ground truth
    # allowed a merge of that kind.
    for m in run.merges:
        a, b = m["robot_a"], m["robot_b"]
        entry = {
            "type": m["type"],
            "robots": [a, b],
            "stamp": m["stamp_s"],
            "trans_err_m": None,
            "rot_err_deg": None,
            "latency_s": None,
        }
        if a in T_world_map_gt and b in T_world_map_gt:
            entry["trans_err_m"], entry["rot_err_deg"] = merge_error(
                m["T_mapA_mapB"], T_world_map_gt[a], T_world_map_gt[b]
            )
        local = _local_merge_error(m, run, gts)
        entry["local_trans_err_m"], entry["local_rot_err_deg"] = local if local else (None, None)
        first = _first_evidence(overlap, m["type"], a, b)
        if first is not None:
            entry["latency_s"] = m["stamp_s"] - first
        report["merges"].append(entry)
    # A wrong merge is a wrong registration: judged at the matched keyframes, where odometry drift
    # (which only the team optimization can remove) does not enter.
    report["wrong_merges"] = count_wrong_merges(
        [
            {"trans_err_m": m["local_trans_err_m"], "rot_err_deg": m["local_rot_err_deg"]}
            for m in report["merges"]
        ]
    )
    report["groups"] = run.server_stats.get("groups") or [[rid] for rid in robot_ids]
    if len(gt_world) >= 2 or (len(robot_ids) == 1 and gt_world):
        est_world = {rid: est_world[rid] for rid in gt_world}  # only what can be judged
        try:
            team = team_ate(est_world, gt_world)
            report["team_ate_rmse_m"] = team.rmse_m
        except EvaluationError:
            team = None
        if out_dir and team is not None:
            _plot_team(out_dir, est_world, gt_world, team)
    if report["team_ate_rmse_m"] is None and len(robot_ids) == 1:
        report["team_ate_rmse_m"] = report["robots"][0]["ate_rmse_m"]
    if report["team_ate_rmse_m"] is not None:
        # Pooled over the robots the team ATE covers, so that the two compare like with like.
        pooled = [own_ate[r] for r in (gt_world or own_ate) if r in own_ate]
        n = sum(c for _, c in pooled)
        if n:
            report["single_ate_pooled_m"] = float(np.sqrt(sum(e**2 * c for e, c in pooled) / n))
    report["server_ms_per_keyframe"] = run.server_stats.get("ms_per_keyframe_mean")
    report["loop_closures"] = run.server_stats.get("loops")
    report["bandwidth"] = _bandwidth(run)
    report["topics"] = _topic_bandwidth(run)
    if out_dir:
        _plot(out_dir, run, gts)
    return report


def _local_merge_error(m: dict, run: RunData, gts: dict) -> tuple[float, float] | None:
    """Error of the merge's registration against the truth: the verified relative pose of the
    matched keyframes' cameras against their true relative pose. Odometry drift does not enter,
    nor do later local-BA moves of the keyframes (which the map transform was chained through)."""
    T_world_cams = []
    for robot, kf in ((m["robot_a"], m.get("keyframe_a")), (m["robot_b"], m.get("keyframe_b"))):
        stamp = (m.get("keyframe_stamps") or {}).get(robot)
        if stamp is None and robot in run.robots and kf in run.robots[robot].keyframes:
            stamp = run.robots[robot].keyframes[kf][0]
        if stamp is None or robot not in gts or len(gts[robot][0]) == 0:
            return None
        stamps_gt, poses_gt = gts[robot]
        i = int(np.argmin(np.abs(stamps_gt - stamp)))
        if abs(stamps_gt[i] - stamp) > 0.02:
            return None
        T_world_cams.append(poses_gt[i])
    T_world_camA, T_world_camB = T_world_cams
    return transform_error(m["T_camA_camB"], invert(T_world_camA) @ T_world_camB)


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
        return {
            "per_robot_kBps": None,
            "peak_kBps": None,
            "total_MB": None,
            "keyframe_bytes_mean": None,
        }
    sizes = [n for r in run.robots.values() for _, n in r.kf_bytes]
    return {
        "per_robot_kBps": float(np.mean(per_robot)),
        "peak_kBps": float(max(peaks)),
        "total_MB": float(total / 1e6),
        "keyframe_bytes_mean": float(np.mean(sizes)),
    }


def _topic_bandwidth(run: RunData) -> dict:
    """topic -> messages, mean and peak (busiest second of sim time) kB/s, total MB."""
    out = {}
    for topic, entries in sorted(run.topic_bytes.items()):
        t = np.array([s for s, _ in entries])
        b = np.array([n for _, n in entries], float)
        peak = np.bincount(np.floor(t - t.min()).astype(int), weights=b).max() / 1e3
        out[topic] = {
            "messages": len(b),
            "mean_kBps": float(b.sum() / max(run.duration_s, 1e-9) / 1e3),
            "peak_kBps": float(peak),
            "total_MB": float(b.sum() / 1e6),
        }
    return out


def _save_top_view(path: str, title: str, curves) -> None:
    """x-y top view of trajectories: ``curves`` are (poses (N, 4, 4), colour index, label, is
    estimate); ground truth dashed, estimates with keyframe dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for poses, k, label, estimate in curves:
        style = dict(marker="o", ms=2) if estimate else dict(linestyle="--", alpha=0.5)
        ax.plot(
            poses[:, 0, 3], poses[:, 1, 3], color=colours[k % len(colours)], label=label, **style
        )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot(out_dir: str, run: RunData, gts) -> None:
    """Top view of every robot's keyframes (aligned to ground truth) and ground truth; without
    ground truth, the keyframes in their own map frames."""
    curves = []
    for k, rid in enumerate(sorted(gts)):
        stamps_gt, poses_gt = gts[rid]
        r = run.robots.get(rid)
        if len(stamps_gt) == 0:
            if r and r.keyframes:
                curves.append((_kf_arrays(r)[1], k, f"robot_{rid} keyframes (own map)", True))
            continue
        curves.append((poses_gt, k, f"robot_{rid} ground truth", False))
        if r and len(r.keyframes) >= 3:
            stamps, poses = _kf_arrays(r)
            try:
                res = ate(stamps, poses, stamps_gt, poses_gt)
            except EvaluationError:
                continue
            aligned = np.einsum("ij,njk->nik", res.T_gt_est, poses)
            curves.append(
                (aligned, k, f"robot_{rid} keyframes (ATE {100 * res.rmse_m:.1f} cm)", True)
            )
    _save_top_view(
        os.path.join(out_dir, "trajectories.png"),
        "trajectories (each robot aligned to its ground truth)",
        curves,
    )


def _plot_team(out_dir: str, est_world: dict, gt_world: dict, team) -> None:
    """Top view of every robot's keyframes in world (one alignment for the team) and ground
    truth."""
    curves = []
    for k, rid in enumerate(sorted(est_world)):
        curves.append((gt_world[rid][1], k, f"robot_{rid} ground truth", False))
        aligned = np.einsum("ij,njk->nik", team.T_gt_est, est_world[rid][1])
        curves.append((aligned, k, f"robot_{rid} keyframes in world", True))
    _save_top_view(
        os.path.join(out_dir, "team_trajectories.png"),
        f"team map: one alignment for all robots (team ATE {100 * team.rmse_m:.1f} cm)",
        curves,
    )


def _write_ply(path: str, cloud_msg) -> None:
    """ASCII PLY (x, y, z, red, green, blue) of a PointCloud2 with an rgb field."""
    from ..ros.convert import cloud_from_msg

    xyz = cloud_from_msg(cloud_msg)
    offsets = {f.name: f.offset for f in cloud_msg.fields}
    rgb = np.zeros((len(xyz), 3), np.uint8)
    if "rgb" in offsets and len(xyz):
        raw = np.frombuffer(cloud_msg.data, np.uint8).reshape(len(xyz), cloud_msg.point_step)
        packed = raw[:, offsets["rgb"] : offsets["rgb"] + 4].copy().view(np.uint32)[:, 0]
        rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], 1).astype(
            np.uint8
        )
    with open(path, "w", encoding="ascii") as fh:
        fh.write(
            f"ply\nformat ascii 1.0\nelement vertex {len(xyz)}\nproperty float x\n"
            "property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
            "property uchar blue\nend_header\n"
        )
        np.savetxt(fh, np.column_stack([xyz, rgb]), fmt="%.4f %.4f %.4f %d %d %d")


def evaluate_results(out_dir: str, run: RunData, gts: dict, overlap: dict | None = None):
    """Report, trajectories, plots and the team map PLY of one run into ``out_dir`` (arguments as
    for :func:`evaluate_run`); returns (report, report.json path, report.md path, PLY path or
    None)."""
    from ..report import write_report

    report = evaluate_run(run, gts, overlap, out_dir)
    ply = None
    if run.team_cloud is not None:
        ply = os.path.join(out_dir, "team_map.ply")
        _write_ply(ply, run.team_cloud)
    json_path, md_path = write_report(out_dir, report)
    return report, json_path, md_path, ply


def main(argv=None) -> int:
    """``scripts/evaluate RESULTS``: re-evaluate a demo run from its recorded bag."""
    import argparse
    import json
    import sys

    from ..errors import CoopSlamError
    from ..playback import load_run_source

    p = argparse.ArgumentParser(prog="scripts/evaluate", description=main.__doc__.split(":")[1])
    p.add_argument("results", help="results folder of a demo run (holds run.json and run.bag)")
    p.add_argument("--bag", help="bag to evaluate (default: RESULTS/run.bag)")
    args = p.parse_args(argv)
    try:
        info_path = os.path.join(args.results, "run.json")
        if not os.path.isfile(info_path):
            raise EvaluationError(
                f"{info_path} not found: is {args.results} a demo results folder?"
            )
        with open(info_path, encoding="utf-8") as fh:
            info = json.load(fh)
        bag = args.bag or os.path.join(args.results, "run.bag")
        what = info.get("bag") or info.get("scenario") or info.get("dataset")
        print(f"[evaluate] loading the ground truth ({what})", flush=True)
        if info.get("bag"):  # the run played a sensor bag: ground truth (if any) is in it
            inputs = read_bag_input(info["bag"])
        else:
            inputs = run_input_of(load_run_source(info), bool(info.get("keep_timing")))
        print(f"[evaluate] reading {bag}", flush=True)
        run = run_data_from_bag(bag, inputs.robot_ids)
        run.duration_s = inputs.end_s - inputs.start_s
        _, json_path, md_path, ply = evaluate_results(args.results, run, inputs.gts, inputs.overlap)
    except (CoopSlamError, OSError, ValueError) as exc:
        print(f"[evaluate] ERROR: {exc}", file=sys.stderr)
        return 2
    print(f"[evaluate] report: {json_path}\n[evaluate]         {md_path}", flush=True)
    if ply:
        print(f"[evaluate] team map: {ply}", flush=True)
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
