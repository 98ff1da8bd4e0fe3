"""A synthetic team for the pose graph's tests and benchmark: ground truth, drifting client
poses, and loop / merge constraints measured from the truth with noise."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import exp_so3, invert
from .pose_graph import PoseGraphConfig, TeamPoseGraph


@dataclass
class SyntheticTeam:
    """Ground truth, drifting client poses and constraints for pose-graph tests and benchmarks."""

    T_world_cam_gt: dict[int, np.ndarray]  # robot -> (N, 4, 4), keyframe ids 1..N
    T_map_cam: dict[int, np.ndarray]  # robot -> (N, 4, 4), client poses (map = first camera)
    loops: list[tuple[int, int, int, np.ndarray]] = field(default_factory=list)  # r, i, j, T
    merges: list[tuple[int, int, int, int, np.ndarray]] = field(default_factory=list)  # ra,i,rb,j,T


def synthetic_team(
    keyframes_per_robot: int = 60,
    robots: int = 3,
    seed: int = 0,
    odom_rot_noise_rad: float = 0.002,
    odom_trans_noise_m: float = 0.005,
    yaw_drift_rad: float = 0.003,
    meas_rot_noise_rad: float = 0.002,
    meas_trans_noise_m: float = 0.005,
    max_merges_per_pair: int = 6,
    loop_every: int = 4,
) -> SyntheticTeam:
    """Robots circling overlapping 4 m rings (one lap per 60 keyframes, camera looking ahead,
    gently bobbing in z); clients integrate noisy, yaw-drifting odometry from their first pose;
    loop / merge constraints come from the truth with small noise where keyframes are close in
    position (< 0.8 m) and heading (< 30 deg)."""
    rng = np.random.default_rng(seed)
    radius, per_lap = 4.0, 60
    gt, client = {}, {}
    for r in range(1, robots + 1):
        theta = 2 * np.pi * (np.arange(keyframes_per_robot) / per_lap + (r - 1) / robots)
        centre = np.array([0.8 * (r - 1), 0.4 * (r - 1), 0.0])
        pos = centre + np.column_stack(
            [radius * np.cos(theta), radius * np.sin(theta), 0.3 * np.sin(3 * theta)]
        )
        fwd = np.column_stack([-np.sin(theta), np.cos(theta), np.zeros_like(theta)])
        down = np.tile([0.0, 0.0, -1.0], (len(theta), 1))
        right = np.cross(down, fwd)
        T = np.tile(np.eye(4), (len(theta), 1, 1))
        T[:, :3, :3] = np.stack([right, down, fwd], axis=2)
        T[:, :3, 3] = pos
        gt[r] = T
        C = np.tile(np.eye(4), (len(theta), 1, 1))
        for k in range(1, len(theta)):
            D = invert(T[k - 1]) @ T[k]
            noise = np.eye(4)
            # Drift about the camera's y axis (down): yaw in the world.
            noise[:3, :3] = exp_so3(rng.normal(0, odom_rot_noise_rad, 3) + [0, yaw_drift_rad, 0])
            noise[:3, 3] = rng.normal(0, odom_trans_noise_m, 3)
            C[k] = C[k - 1] @ D @ noise
        client[r] = C

    def measure(Ta, Tb):
        noise = np.eye(4)
        noise[:3, :3] = exp_so3(rng.normal(0, meas_rot_noise_rad, 3))
        noise[:3, 3] = rng.normal(0, meas_trans_noise_m, 3)
        return invert(Ta) @ Tb @ noise

    def close_pairs(Ta, Tb):
        d = np.linalg.norm(Ta[:, None, :3, 3] - Tb[None, :, :3, 3], axis=2)
        cos = np.einsum("ik,jk->ij", Ta[:, :3, 2], Tb[:, :3, 2])
        return np.argwhere((d < 0.8) & (cos > np.cos(np.radians(30))))

    team = SyntheticTeam(gt, client)
    for r, T_r in gt.items():
        pairs = close_pairs(T_r, T_r)
        pairs = pairs[pairs[:, 1] - pairs[:, 0] > 20]
        for i, j in pairs[::loop_every]:
            team.loops.append((r, int(i) + 1, int(j) + 1, measure(T_r[i], T_r[j])))
    for ra, T_a in gt.items():
        for rb, T_b in gt.items():
            if rb <= ra:
                continue
            pairs = close_pairs(T_a, T_b)
            if len(pairs) == 0:
                continue
            pick = np.linspace(0, len(pairs) - 1, min(max_merges_per_pair, len(pairs))).astype(int)
            for i, j in pairs[pick]:
                team.merges.append((ra, int(i) + 1, rb, int(j) + 1, measure(T_a[i], T_b[j])))
    return team


def build_graph(team: SyntheticTeam, config: PoseGraphConfig | None = None) -> TeamPoseGraph:
    """A pose graph holding all keyframes, loops and merges of a synthetic team (not optimised)."""
    graph = TeamPoseGraph(config)
    for r, poses in team.T_map_cam.items():
        for k, T in enumerate(poses):
            graph.add_keyframe(r, k + 1, T)
    for r, i, j, T in team.loops:
        graph.add_loop(r, i, j, T)
    for ra, i, rb, j, T in team.merges:
        graph.add_merge(ra, i, rb, j, T)
    return graph


def bench_full_optimization(
    n_keyframes: int = 1000, robots: int = 4, seed: int = 0, repeats: int = 3
) -> float:
    """Median wall time [ms] of :meth:`TeamPoseGraph.optimize_full` right after the merges of a
    synthetic team of ``robots`` robots with ``n_keyframes`` keyframes in total."""
    team = synthetic_team(n_keyframes // robots, robots, seed)
    times = []
    for _ in range(repeats):
        graph = build_graph(team)
        times.append(graph.optimize_full().time_ms)
    return float(np.median(times))
