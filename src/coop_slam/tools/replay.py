"""``scripts/replay RESULTS``: feed a recorded run's keyframes and marker sightings through the
server core again, without ROS nodes, and print what the server decides.

The server core is deterministic: the same recorded input gives the same merges, links and
optimized poses. That makes a recorded run a regression check for any change to the server (a
refactor must replay identically) and a quick way to try server parameters on real runs
(``--server-config``). Operator requests (``--rendezvous``) are not in the bag and are not replayed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from ..errors import CoopSlamError
from .paths import CONFIG_DIR


def _server_config(path: str, info: dict, overrides: dict):
    """The server configuration the demo ran with: the YAML, as server.launch adjusts it."""
    from ..config import load_yaml_config, merge_overrides
    from ..team.config import ServerConfig

    launch = {}
    if info.get("ground_robots"):
        launch["global_ba"] = {"planar_motion": True}
    if info.get("split"):
        launch["rendezvous"] = {"min_separation_m": 0.0}
    if info.get("low_bandwidth"):  # the robots sent place signatures
        launch["pull"] = {"enabled": True}
    launch["robots"] = list(info["robot_ids"])
    return load_yaml_config(ServerConfig, path, "server", merge_overrides(launch, overrides))


def replay(bag_path: str, info: dict, config_path: str, overrides: dict | None = None) -> dict:
    """Replay the bag through a fresh server worker (the node's, without ROS); returns the
    server, the summary (see :func:`summary`) and the stamp of every keyframe received."""
    import rosbag

    from ..bow import Vocabulary
    from ..default_vocabulary import ensure_default_vocabulary
    from ..geometry import T_base_cam_of
    from ..markers import MarkerConfig
    from ..robot_description import describe
    from ..ros.convert import MessageError, description_from_msg, marker_seen_from_msg
    from ..ros.recorded import KEYFRAME_TOPIC, is_removal, keyframe_message
    from ..team.durable import DurableServer
    from ..team.jobs import RendezvousJob
    from ..team.server import TeamServer
    from ..team.worker import ServerWorker

    cfg = _server_config(config_path, info, overrides or {})
    vocab = Vocabulary.load(info.get("vocabulary") or ensure_default_vocabulary())
    # The node's worker, its global BA at once after a merge (the node runs it when no message
    # waits, which a bag does not record): the same input gives the same decisions.
    worker = ServerWorker(
        cfg,
        lambda resume, load: DurableServer(cfg, lambda c: TeamServer(c, vocab), None),
    )
    # Robots' descriptions in the bag replace these: a run recorded before robots described
    # themselves has only the run's mounts.
    own = info.get("T_base_cams") or {}
    for r in cfg.robots:
        base_cam = own.get(str(r)) or info.get("T_base_cam") or []
        if base_cam:
            worker.sightings.describe(describe(r, "rgbd", T_base_cam_of(base_cam), MarkerConfig()))
    server = worker.server
    topics = [KEYFRAME_TOPIC.format(r) for r in cfg.robots] + ["/robot_sightings"]
    topics += [f"/robot_{r}/description" for r in cfg.robots]
    rejected = 0
    stamps = {}  # (robot, keyframe) -> stamp_s of every keyframe received, culled ones included
    try:
        with rosbag.Bag(bag_path) as bag:
            for topic, msg, t in bag.read_messages(topics=topics):
                if topic == "/robot_sightings":
                    try:
                        seen = marker_seen_from_msg(msg)
                    except MessageError:
                        rejected += 1
                        continue
                    stamp_s = msg.header.stamp.to_sec()
                    worker.handle(
                        RendezvousJob(msg.observer_id, msg.observed_id, stamp_s, seen, True)
                    )
                    continue
                if topic.endswith("/description"):
                    try:
                        worker.sightings.describe(description_from_msg(msg))
                    except MessageError:
                        rejected += 1
                    continue
                msg = keyframe_message(msg)
                if not is_removal(msg):  # a removal carries no stamp
                    key = (msg.robot_id, msg.keyframe_id)
                    stamps.setdefault(key, msg.header.stamp.to_sec())
                job = worker.intake(msg, msg.robot_id, t.to_sec())  # (recorded on arrival)
                if job is not None:
                    worker.handle(job)
    finally:
        worker.close()
    return server, summary(server, worker.rejected + rejected), stamps


def summary(server, rejected: int = 0) -> dict:
    """What the server decided: merges, constraints, groups and every keyframe's final position
    in its group frame (rounded to 0.1 mm)."""
    out = {
        "merges": [
            {
                "type": m.type,
                "robots": [m.map_a, m.map_b],
                "keyframes": [m.keyframe_a, m.keyframe_b],
                "inliers": m.inliers,
                "stamp_s": round(m.stamp_s, 3),
                "scale": round(m.scale, 5),
            }
            for m in server.merges
        ],
        "constraints": [
            {"type": c.type, "a": list(c.key_a), "b": list(c.key_b), "inliers": c.inliers}
            for c in server.constraints
        ],
        "refused_constraints": server.rejected_constraints,
        "verifications": server.verifications,
        "groups": [list(g) for g in server.robot_groups()],
        "rejected": rejected,
        "keyframes": len(server.store),
        "positions_mm": {},
    }
    for robot in server.store.maps():
        poses = server.optimized_keyframes(robot)
        out["positions_mm"][str(robot)] = {
            str(k): [round(float(v) * 1e3, 1) for v in T[:3, 3]] for k, T in poses.items()
        }
    return out


def agreement(server) -> list:
    """[robots, inter, intra] [mm] of every robot pair in ``world`` (see
    :mod:`coop_slam.evaluation.agreement`), from the stored keyframes' depth points at their
    optimized poses: no ground truth needed."""
    from ..evaluation.agreement import KeyframeCloud, team_agreement

    clouds = {}
    for robot in server.store.maps():
        if not server.in_world(robot):
            continue
        kfs = []
        for k in server.store.keyframe_ids(robot):
            view = server.store.view((robot, k))
            points = view.points_cam[view.has_point]
            if len(points):
                kfs.append(
                    KeyframeCloud(
                        server.store.stamp((robot, k)), server.T_group_cam(robot, k), points
                    )
                )
        clouds[robot] = kfs
    if len(clouds) < 2:
        return []
    mm = lambda v: None if v is None else round(1e3 * v, 1)  # noqa: E731
    return [[p["robots"], mm(p["inter_m"]), mm(p["intra_m"])] for p in team_agreement(clouds).pairs]


def judge(server, stamps: dict, gts: dict) -> dict:
    """The replayed decisions against ground truth ``gts`` (robot -> (stamps, T_world_cam) on the
    playback timeline): each merge's and inter-robot constraint's registration error at its
    keyframes, the team ATE of the world group's optimized keyframes and the pooled ATE of the
    robots' own keyframe poses (as in the demo's report, there from the published poses). A
    registration between monocular maps is in its a-side map's stored units: judged in metres by
    that map's Sim(3) scale against ground truth."""
    from ..evaluation.metrics import EvaluationError, ate, relative_pose_error, team_ate
    from ..team.map_scale import scale_translation

    metres_per_unit: dict = {}  # map id -> true metres per stored unit (a monocular group's)

    def error(key_a, key_b, T_camA_camB):
        unit = 1.0 if server.is_metric(key_a[0]) else metres_per_unit.get(key_a[0])
        if unit is None:
            return None
        T_camA_camB = scale_translation(T_camA_camB, unit)
        # Map ids to robots (a later map segment is its robot's); stamps are by robot.
        key_a = (server.robot_of(key_a[0]), key_a[1])
        key_b = (server.robot_of(key_b[0]), key_b[1])
        if key_a not in stamps or key_b not in stamps or key_a[0] not in gts or key_b[0] not in gts:
            return None
        err = relative_pose_error(
            T_camA_camB, stamps[key_a], stamps[key_b], gts[key_a[0]], gts[key_b[0]]
        )
        return None if err is None else [round(err[0] * 100, 2), round(err[1], 2)]

    out = {"merge_errors_cm_deg": [], "link_errors_cm_deg": [], "loop_errors_cm_deg": []}
    own, est = [], {}
    metric = False  # a world of monocular maps only has no metric scale (aligned with Sim(3))
    for mid in server.store.maps():  # map ids: a robot's map segments apart
        robot = server.robot_of(mid)
        keys = sorted(server.store.keyframe_ids(mid))
        t = np.array([server.store.stamp((mid, k)) for k in keys])
        if robot not in gts or len(gts[robot][0]) == 0 or len(keys) < 3:
            continue
        try:
            # A monocular map is judged up to its scale (its own units, or the server's).
            mono = server.scales.is_mono(mid)
            poses = [server.store.record((mid, k)).T_map_cam for k in keys]
            res = ate(t, poses, *gts[robot], correct_scale=mono)
            own.append((res.rmse_m, res.count))
            if mono and not server.is_metric(mid):
                metres_per_unit[mid] = res.scale
        except EvaluationError:
            pass
        if server.in_world(mid):
            metric = metric or server.is_metric(mid)
            poses = np.array([server.T_group_cam(mid, k) for k in keys])
            if robot in est:  # another segment of the robot in the world group
                t = np.concatenate([est[robot][0], t])
                poses = np.concatenate([est[robot][1], poses])
                order = np.argsort(t, kind="stable")
                t, poses = t[order], poses[order]
            est[robot] = (t, poses)
    for m in server.merges:
        key_a, key_b = (m.map_a, m.keyframe_a), (m.map_b, m.keyframe_b)
        out["merge_errors_cm_deg"].append(error(key_a, key_b, m.T_camA_camB))
    for c in server.constraints:
        kind = "loop" if c.key_a[0] == c.key_b[0] else "link"
        out[f"{kind}_errors_cm_deg"].append(error(c.key_a, c.key_b, c.T_camA_camB))
    out["overlap_agreement_mm"] = agreement(server)
    n = sum(c for _, c in own)
    out["single_ate_pooled_cm"] = (
        round(100 * float(np.sqrt(sum(e**2 * c for e, c in own) / n)), 2) if n else None
    )
    try:
        team = team_ate(est, gts, correct_scale=not metric) if est else None
        out["team_ate_cm"] = round(100 * team.rmse_m, 2) if team else None
    except EvaluationError:
        out["team_ate_cm"] = None
    return out


def compare(a: dict, b: dict, tol_mm: float = 0.5) -> list[str]:
    """Differences between two replay summaries (positions within ``tol_mm`` count as equal)."""
    diffs = []
    for key in ("merges", "constraints", "refused_constraints", "groups", "keyframes"):
        if a.get(key) != b.get(key):
            diffs.append(f"{key}: {a.get(key)} != {b.get(key)}")
    worst = 0.0
    for robot, poses in a.get("positions_mm", {}).items():
        other = b.get("positions_mm", {}).get(robot, {})
        for k, p in poses.items():
            if k not in other:
                diffs.append(f"robot {robot} keyframe {k} missing")
                continue
            worst = max(worst, float(np.max(np.abs(np.subtract(p, other[k])))))
    if worst > tol_mm:
        diffs.append(f"keyframe positions differ by up to {worst:.2f} mm")
    return diffs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/replay", description=__doc__.split("\n\n")[0])
    p.add_argument("results", help="results folder of a demo run (run.json and run.bag)")
    p.add_argument("--server-config", help="server YAML (default: config/server.yaml)")
    p.add_argument("--out", help="write the summary as JSON here")
    p.add_argument("--compare", help="a summary JSON written before: print the differences")
    p.add_argument(
        "--no-truth", action="store_true", help="do not judge against the run's ground truth"
    )
    args = p.parse_args(argv)
    truth = None
    config = args.server_config or os.path.join(CONFIG_DIR, "server.yaml")
    try:
        with open(os.path.join(args.results, "run.json"), encoding="utf-8") as fh:
            info = json.load(fh)
        bag = os.path.join(args.results, "run.bag")
        if not os.path.isfile(bag):
            raise CoopSlamError(f"{bag} not found: the run was not recorded")
        server, result, stamps = replay(bag, info, config)
        if not args.no_truth and (info.get("scenario") or info.get("dataset")):
            from ..evaluation.run_report import run_input_of
            from ..playback import load_run_source

            gts = run_input_of(load_run_source(info), bool(info.get("keep_timing"))).gts
            truth = judge(server, stamps, gts)
    except (CoopSlamError, OSError, ValueError) as exc:
        print(f"[replay] ERROR: {exc}", file=sys.stderr)
        return 2
    for m in result["merges"]:
        print(
            f"[replay] merge {m['type']}: robots {m['robots']} keyframes {m['keyframes']} "
            f"({m['inliers']} inliers, scale {m.get('scale', 1.0):.4f}) at {m['stamp_s']:.2f} s"
        )
    print(
        f"[replay] {len(result['constraints'])} constraints "
        f"({sum(c['type'] == 'loop' for c in result['constraints'])} loops), "
        f"{result['refused_constraints']} refused, {result['verifications']} verifications, "
        f"groups {result['groups']}, {result['keyframes']} keyframes, {result['rejected']} rejected"
    )
    if truth is not None:
        print(
            f"[replay] truth: team ATE {truth['team_ate_cm']} cm, single-robot pooled "
            f"{truth['single_ate_pooled_cm']} cm"
        )
        print(f"[replay] merge errors [cm, deg] at the keyframes: {truth['merge_errors_cm_deg']}")
        print(
            f"[replay] overlap agreement [robots, inter, intra mm]: {truth['overlap_agreement_mm']}"
        )
        for kind in ("link", "loop"):
            errs = np.array([e for e in truth[f"{kind}_errors_cm_deg"] if e is not None])
            if len(errs):
                print(
                    f"[replay] {len(errs)} {kind}s' errors at the keyframes: median "
                    f"{np.median(errs[:, 0]):.2f} cm / {np.median(errs[:, 1]):.2f} deg, max "
                    f"{errs[:, 0].max():.2f} cm / {errs[:, 1].max():.2f} deg"
                )
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump(result, fh, indent=1)
    if args.compare:
        with open(args.compare, encoding="utf-8") as fh:
            diffs = compare(json.load(fh), result)
        print("[replay] same as " + args.compare if not diffs else "[replay] DIFFERS:")
        for d in diffs:
            print("   " + d)
        return 1 if diffs else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
