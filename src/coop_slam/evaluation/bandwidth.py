"""Radio use of a run, from the message sizes it recorded: per robot uplink (its keyframe
messages) and downlink (corrections and acknowledgements from the server), and per topic."""

from __future__ import annotations

import numpy as np

from .run_data import RobotRun, RunData

# Server -> robot k (the downlink of its radio), relative to /robot_k
DOWNLINK_TOPICS = ("correction", "keyframe_ack")


def downlink_kBps(run: RunData, robot_id: int) -> float | None:
    """Server -> robot: its corrections and acknowledgements, kB/s over the run (None when neither
    was recorded)."""
    entries = [
        n for t in DOWNLINK_TOPICS for _, n in run.topic_bytes.get(f"/robot_{robot_id}/{t}", ())
    ]
    return sum(entries) / max(run.duration_s, 1e-9) / 1e3 if entries else None


def uplink_kBps(run: RunData, r: RobotRun) -> float | None:
    """Robot -> server: its keyframe messages, kB/s over the run."""
    return sum(n for _, n in r.kf_bytes) / max(run.duration_s, 1e-9) / 1e3 if r.kf_bytes else None


def uplink_by_kind(run: RunData, r: RobotRun) -> dict | None:
    """Robot -> server by what its messages carried (whole keyframes, delta updates, place
    signatures, removals): messages and kB/s over the run each."""
    if not r.kf_kinds:
        return None
    duration = max(run.duration_s, 1e-9)
    return {
        kind: {"messages": int(n), "kBps": float(nbytes / duration / 1e3)}
        for kind, (n, nbytes) in sorted(r.kf_kinds.items())
    }


def bandwidth(run: RunData) -> dict:
    """The report's ``bandwidth``: uplink per robot (mean), the busiest second of a robot's uplink,
    the total and the mean size of a keyframe message; downlink per robot (mean)."""
    per_robot, peaks, total = [], [], 0
    downlink = [d for d in (downlink_kBps(run, rid) for rid in run.robots) if d is not None]
    for r in run.robots.values():
        if not r.kf_bytes:
            continue
        t = np.array([s for s, _ in r.kf_bytes])
        b = np.array([n for _, n in r.kf_bytes], float)
        total += b.sum()
        per_robot.append(uplink_kBps(run, r))
        bins = np.floor(t - t.min()).astype(int)
        peaks.append(np.bincount(bins, weights=b).max() / 1e3)  # busiest second of sim time
    if not per_robot:
        return {
            "per_robot_kBps": None,
            "peak_kBps": None,
            "total_MB": None,
            "keyframe_bytes_mean": None,
            "downlink_per_robot_kBps": float(np.mean(downlink)) if downlink else None,
        }
    sizes = [n for r in run.robots.values() for _, n in r.kf_bytes]
    return {
        "per_robot_kBps": float(np.mean(per_robot)),
        "peak_kBps": float(max(peaks)),
        "total_MB": float(total / 1e6),
        "keyframe_bytes_mean": float(np.mean(sizes)),
        "downlink_per_robot_kBps": float(np.mean(downlink)) if downlink else None,
    }


def topic_bandwidth(run: RunData) -> dict:
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
