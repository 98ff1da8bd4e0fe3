"""The run report (``report.json`` + ``report.md``): one schema, every key always present.

The keys are a contract (see the README): later stages fill more of them, none is ever renamed, and
a value that was not measured is ``null`` rather than absent.
"""

from __future__ import annotations

import json
import math
import os
from typing import Any

ROBOT_KEYS = (
    "id",
    "frames",
    "frames_dropped",  # frames a busy client skipped for a newer one (live playback)
    "mapping_backlog_max",  # most keyframes local mapping had not finished at a frame
    "frames_mapping_behind",  # frames tracked while local mapping held more than one keyframe
    "keyframes",
    "path_length_m",
    "ate_rmse_m",
    # the server's optimized poses of the robot's keyframes, aligned alone like ate_rmse_m
    # (Sim(3) for a monocular robot)
    "server_ate_rmse_m",
    # its keyframes in the team map under the team's one alignment (what of the team ATE is its
    # share: against its own ate_rmse_m, what placing its map in the team cost or gained)
    "team_map_ate_rmse_m",
    # ... over how many keyframes (those the server holds whole, when a robot sends signatures:
    # its others enter the team ATE placed as the server placed their nearest whole keyframe,
    # so that team and pooled ATE are over the same keyframes)
    "team_keyframes_optimized",
    # the client's own last published trajectory (/robot_k/path: its keyframes with the team
    # map's corrections, pose-graph sharing), aligned alone like ate_rmse_m
    "path_ate_rmse_m",
    # ... and its keyframes, placed in world by the robot's latest map transform, against the
    # server's optimized ones (median distance; 0 when the client shows the team map's poses)
    "path_team_gap_m",
    "rpe_rmse_m",
    "tracking_lost",
    "track_ms_mean",
    "track_ms_p95",
    # Radio: robot -> server (keyframe messages) and server -> robot (corrections, acks) [kB/s]
    "uplink_kBps",
    # ... by what its messages carried: {whole|delta|signature|removal: {messages, kBps}}
    "uplink_by_kind",
    "downlink_kBps",
    # ... and on the wire with --hosts: the robot's radio interface, sent / received (every topic,
    # TCP/IP and ROS overhead included) over the data's duration [kB/s]
    "radio_up_kBps",
    "radio_down_kBps",
    # Monocular robots (a map without metric scale; ate_rmse_m, an SE(3) alignment, is null):
    # the Sim(3)-aligned ATE of its own keyframes, and once the server placed it in a metric world
    # group, the server's scale of its map against the true one (relative, signed).
    "sensor",
    "ate_sim3_rmse_m",
    "scale_error",
    # Delivery: new keyframes this run's clients sent whole (all their sessions), distinct
    # keyframes in the server's map, and the difference (sent and never stored).
    "keyframes_sent",
    # ... and the new keyframes that did not go whole (the radio budget, low-bandwidth mode): sent
    # as place signatures only (the server may still ask for them), or not at all
    "keyframes_held_back",
    "keyframes_stored",
    "keyframes_lost",
    # Low-bandwidth mode: keyframes the server asked for whole (the others: signatures only).
    "keyframes_pulled",
    # The robot's clock minus the server's as the server estimated it [s] (low by the smallest
    # transit time; null: no estimate, e.g. an older client)
    "clock_offset_s",
)
MERGE_KEYS = (
    "type",
    "robots",
    "stamp",
    "trans_err_m",
    "rot_err_deg",
    "latency_s",
    "published_s",
    "local_trans_err_m",
    "local_rot_err_deg",
    # A merge by a similarity (a monocular side): its scale against the true ratio of the two
    # maps' units over their whole paths, and around the matched keyframes (relative, signed)
    "scale_err",
    "local_scale_err",
)
TOP_KEYS = (
    "robots",
    "merges",
    "groups",
    "team_ate_rmse_m",
    "single_ate_pooled_m",
    "bandwidth",
    "server_ms_per_keyframe",
    "wrong_merges",
    "loop_closures",
    "links",
    "overlap_agreement",
    "grid_iou",
    "grid_free_iou",
    "grid_free_coverage",
    "dense_surface_rmse_m",
    "topics",
)
BANDWIDTH_KEYS = (
    "per_robot_kBps",  # uplink: keyframe messages
    "peak_kBps",
    "total_MB",
    "keyframe_bytes_mean",
    "downlink_per_robot_kBps",  # server -> robot: corrections and acknowledgements
)
WRONG_MERGE_TRANS_M = 0.10  # a merge is wrong when its transform is off by more than this ...
WRONG_MERGE_ROT_DEG = 5.0  # ... or this


def _clean(value: Any) -> Any:
    """JSON-safe: numpy scalars to Python, NaN/inf to None."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def new_report(robot_ids: list[int]) -> dict:
    return {
        "robots": [dict({k: None for k in ROBOT_KEYS}, id=int(r)) for r in robot_ids],
        "merges": [],
        "groups": [],
        "team_ate_rmse_m": None,
        # The robots' own ATEs (each map aligned on its own) pooled over all their keyframes: the
        # team ATE a perfect placement of the clients' maps would reach without removing drift.
        # Below it, the team map removed drift. (With equal keyframe counts, the mean of the
        # per-robot RMS values sits below it whenever the robots' errors differ.)
        "single_ate_pooled_m": None,
        "bandwidth": {k: None for k in BANDWIDTH_KEYS},
        "server_ms_per_keyframe": None,
        "wrong_merges": None,
        "loop_closures": None,
        # Per robot pair of one group: constraints between the two accepted after they merged
        # (count), with their registrations' median error at the keyframes against ground truth.
        "links": [],
        # Per robot pair whose maps overlap, without ground truth: how far each one's points lie
        # from the other's surfaces (inter_m) against how far a robot's points lie from its own
        # surfaces where it revisits (intra_m); see coop_slam.evaluation.agreement.
        "overlap_agreement": [],
        # The dense team map against the synthetic world (None elsewhere): occupancy grid IoU of
        # occupied / free cells and the share of free space mapped (coop_slam.evaluation
        # .grid_score), RMS distance of the dense cloud's points to the true surfaces [m].
        "grid_iou": None,
        "grid_free_iou": None,
        "grid_free_coverage": None,
        "dense_surface_rmse_m": None,
        "duplicates_received": None,  # keyframe messages the server got again (clients resending)
        "faults": None,  # faults injected (scripts/demo --faults)
        "topics": {},
    }


def count_wrong_merges(merges: list[dict]) -> int | None:
    """Merges whose transform error exceeds the thresholds (None when no error could be
    computed)."""
    if not merges:
        return 0
    errs = [(m.get("trans_err_m"), m.get("rot_err_deg")) for m in merges]
    if all(t is None for t, _ in errs):
        return None
    return sum(
        1
        for t, r in errs
        if t is not None
        and (t > WRONG_MERGE_TRANS_M or (r is not None and r > WRONG_MERGE_ROT_DEG))
    )


def write_report(out_dir: str, report: dict, extra_md: str = "") -> tuple[str, str]:
    """Write report.json and report.md into ``out_dir``; returns both paths."""
    os.makedirs(out_dir, exist_ok=True)
    report = _clean(report)
    for key in TOP_KEYS:
        report.setdefault(key, None)
    json_path = os.path.join(out_dir, "report.json")
    with open(json_path, "w", encoding="utf-8") as fh:
        json.dump(report, fh, indent=2)
        fh.write("\n")
    md_path = os.path.join(out_dir, "report.md")
    with open(md_path, "w", encoding="utf-8") as fh:
        fh.write(render_markdown(report) + extra_md)
    return json_path, md_path


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    if isinstance(v, dict) and all(isinstance(x, dict) and "kBps" in x for x in v.values()):
        return ", ".join(f"{k} {x['messages']} ({x['kBps']:.1f} kB/s)" for k, x in v.items())
    return str(v)


def render_markdown(report: dict) -> str:
    lines = ["# coop_slam run report", ""]
    lines += ["## Robots", "", "| " + " | ".join(ROBOT_KEYS) + " |", "|" + "---|" * len(ROBOT_KEYS)]
    for r in report["robots"]:
        lines.append("| " + " | ".join(_fmt(r.get(k)) for k in ROBOT_KEYS) + " |")
    lines += ["", "## Merges", ""]
    if report["merges"]:
        lines += [
            "Errors against ground truth: `trans_err_m`/`rot_err_deg` of the map transform (maps "
            "placed by their own ATE alignment), `local_*` of the registration (the matched "
            "keyframes' relative pose); `latency_s` from the first co-observation of one scene "
            "(rendezvous) or first revisit (place recognition) in the ground truth, whose view "
            "model counts a surface as shared only when seen from similar directions (within "
            "about 22 deg): a negative latency is a verified merge on a view it does not count. "
            "`published_s`: when the server published the merge, in data time (the newest camera "
            "frame by then; `stamp` is the keyframe's that triggered it, which a client's uplink "
            "sends a while after the frame, `uplink.hold_new_s`). "
            "`scale_err` / `local_scale_err` of a merge by a similarity (a monocular side): its "
            "scale against the true ratio of the maps' units over their whole paths / around the "
            "matched keyframes.",
            "",
            "| " + " | ".join(MERGE_KEYS) + " |",
            "|" + "---|" * len(MERGE_KEYS),
        ]
        for m in report["merges"]:
            lines.append("| " + " | ".join(_fmt(m.get(k)) for k in MERGE_KEYS) + " |")
    else:
        lines.append("no merges")
    bw = report.get("bandwidth") or {}
    lines += [
        "",
        "## Team",
        "",
        f"- groups: {report.get('groups')}",
        f"- team ATE RMSE: {_fmt(report.get('team_ate_rmse_m'), 4)} m (single-robot maps placed "
        f"perfectly: {_fmt(report.get('single_ate_pooled_m'), 4)} m)",
        f"- wrong merges: {_fmt(report.get('wrong_merges'))}",
        f"- server time per keyframe: {_fmt(report.get('server_ms_per_keyframe'), 1)} ms",
        f"- bandwidth: per robot {_fmt(bw.get('per_robot_kBps'), 1)} kB/s, peak "
        f"{_fmt(bw.get('peak_kBps'), 1)} kB/s, total {_fmt(bw.get('total_MB'), 2)} MB, "
        f"mean keyframe message {_fmt(bw.get('keyframe_bytes_mean'), 0)} B; downlink per robot "
        f"{_fmt(bw.get('downlink_per_robot_kBps'), 1)} kB/s",
        f"- loop closures: {_fmt(report.get('loop_closures'))}",
        f"- dense map: grid IoU occupied {_fmt(report.get('grid_iou'), 3)}, free "
        f"{_fmt(report.get('grid_free_iou'), 3)} (free space mapped "
        f"{_fmt(report.get('grid_free_coverage'), 3)}), surfaces RMS "
        f"{_fmt(report.get('dense_surface_rmse_m'), 4)} m",
        "",
    ]
    if report.get("links"):
        lines += [
            "## Links between merged robots",
            "",
            "Constraints accepted between two robots after they merged; errors are the median "
            "registration error at the keyframes against ground truth (in metres: a group of "
            "monocular maps' links by its unit's true length, its first map's Sim(3) scale).",
            "",
            "| robots | count | trans_err_m | rot_err_deg |",
            "|---|---|---|---|",
        ]
        for k in report["links"]:
            lines.append(
                f"| {k['robots']} | {k['count']} | {_fmt(k.get('trans_err_m'))} | "
                f"{_fmt(k.get('rot_err_deg'), 2)} |"
            )
        lines.append("")
    if report.get("overlap_agreement"):
        lines += [
            "## Overlap agreement (no ground truth needed)",
            "",
            "How far one robot's map points lie from the other's surfaces where both mapped "
            "(`inter_m`), against how far a robot's points lie from its own surfaces where it "
            "revisits (`intra_m`): a stitch as good as the robots' own maps has inter <= intra.",
            "",
            "| robots | inter_m | intra_m | ratio |",
            "|---|---|---|---|",
        ]
        for k in report["overlap_agreement"]:
            inter, intra = k.get("inter_m"), k.get("intra_m")
            ratio = inter / intra if inter is not None and intra else None
            lines.append(
                f"| {k['robots']} | {_fmt(inter, 4)} | {_fmt(intra, 4)} | {_fmt(ratio, 2)} |"
            )
        lines.append("")
    topics = report.get("topics") or {}
    if topics:
        lines += [
            "## Bandwidth per topic",
            "",
            "| topic | messages | mean kB/s | peak kB/s | total MB |",
            "|---|---|---|---|---|",
        ]
        for name, t in topics.items():
            lines.append(
                f"| {name} | {t['messages']} | {_fmt(t['mean_kBps'], 2)} | "
                f"{_fmt(t['peak_kBps'], 1)} | {_fmt(t['total_MB'], 3)} |"
            )
        lines.append("")
    return "\n".join(lines)
