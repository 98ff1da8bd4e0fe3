"""Pictures of a run: top views of the robots' trajectories against ground truth, each robot
aligned on its own and the team with one alignment; each robot's keyframe errors over time (its
odometry, the team map's poses, the path its client published); and the stitched team cloud as a
PLY file. Pure over arrays: matplotlib (Agg) draws, nothing is shown."""

from __future__ import annotations

import os

import numpy as np

from .metrics import EvaluationError, ate


def top_view_axes(poses_cam: np.ndarray) -> tuple[int, int]:
    """The two axes of the frame a top view draws, for camera poses (N, 4, 4; optical frames,
    y down in the image): all but the one the cameras' "down" lies along (x-y in a z-up world;
    x-z in a frame whose y points down, as KITTI's or EuRoC's first camera's: a straight road
    spreads as little sideways as up and down, so the spread alone picked a side view)."""
    poses_cam = np.asarray(poses_cam, float).reshape(-1, 4, 4)
    if not len(poses_cam):
        return 0, 1
    down = np.abs(poses_cam[:, :3, 1].mean(axis=0))
    vertical = int(np.argmax(down))
    a, b = (k for k in range(3) if k != vertical)
    return a, b


def save_top_view(path: str, title: str, curves) -> None:
    """Top view of trajectories on the plane they spread over (:func:`top_view_axes`):
    ``curves`` are (poses (N, 4, 4), colour index, label, is estimate); ground truth dashed,
    estimates with keyframe dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    drawn = [poses for poses, _, _, _ in curves if len(poses)]
    a, b = top_view_axes(np.concatenate(drawn)) if drawn else (0, 1)
    for poses, k, label, estimate in curves:
        style = dict(marker="o", ms=2) if estimate else dict(linestyle="--", alpha=0.5)
        ax.plot(
            poses[:, a, 3], poses[:, b, 3], color=colours[k % len(colours)], label=label, **style
        )
    ax.set_xlabel(f"{'xyz'[a]} [m]")
    ax.set_ylabel(f"{'xyz'[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def aligned(res, poses: np.ndarray) -> np.ndarray:
    """Estimated poses (N, 4, 4) moved by an ATE result's alignment, its scale included."""
    poses = np.array(poses, dtype=float)
    poses[:, :3, 3] *= res.scale
    return np.einsum("ij,njk->nik", res.T_gt_est, poses)


def plot_trajectories(out_dir: str, keyframes: dict, gts: dict, mono=()) -> None:
    """``trajectories.png``: top view of every robot's keyframes (robot id -> (stamps, poses) in
    its map) aligned to its ground truth (robot id -> (stamps, T_world_cam)), and the ground
    truth; without ground truth, the keyframes in their own map frames. Robots in ``mono``
    (monocular maps) are aligned with a similarity, as their ATE is."""
    curves = []
    for k, rid in enumerate(sorted(gts)):
        stamps_gt, poses_gt = gts[rid]
        stamps, poses = keyframes.get(rid, (np.zeros(0), np.zeros((0, 4, 4))))
        if len(stamps_gt) == 0:
            if len(stamps):
                curves.append((poses, k, f"robot_{rid} keyframes (own map)", True))
            continue
        curves.append((poses_gt, k, f"robot_{rid} ground truth", False))
        if len(stamps) >= 3:
            try:
                res = ate(stamps, poses, stamps_gt, poses_gt, correct_scale=rid in mono)
            except EvaluationError:
                continue
            sim3 = ", Sim(3)" if rid in mono else ""
            curves.append(
                (
                    aligned(res, poses),
                    k,
                    f"robot_{rid} keyframes (ATE {100 * res.rmse_m:.1f} cm{sim3})",
                    True,
                )
            )
    save_top_view(
        os.path.join(out_dir, "trajectories.png"),
        "trajectories (each robot aligned to its ground truth)",
        curves,
    )


def plot_team(out_dir: str, est_world: dict, gt_world: dict, team, own_ate: dict) -> None:
    """``team_trajectories.png``: top view of every robot's keyframes in world (one alignment,
    ``team``'s, for the team: a similarity for a world of monocular maps) and ground truth; and
    ``team_errors.png`` (see :func:`plot_team_errors`; ``own_ate``: robot id -> its own ATE)."""
    plot_team_errors(out_dir, team, own_ate)
    curves = []
    for k, rid in enumerate(sorted(est_world)):
        curves.append((gt_world[rid][1], k, f"robot_{rid} ground truth", False))
        curves.append(
            (aligned(team, est_world[rid][1]), k, f"robot_{rid} keyframes in world", True)
        )
    save_top_view(
        os.path.join(out_dir, "team_trajectories.png"),
        f"team map: one alignment for all robots (team ATE {100 * team.rmse_m:.1f} cm)",
        curves,
    )


def plot_team_errors(out_dir: str, team, own_ate: dict) -> None:  # (drawn by plot_team)
    """``team_errors.png``: each keyframe's position error in the team map (the team's one
    alignment) over time, coloured by robot, beside each robot's own ATE (its map aligned
    alone, dashed): where a team's error comes from."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    shares = team.robot_rmse()
    for k, rid in enumerate(sorted(shares)):
        sel = team.robot_ids == rid
        colour = f"C{k}"
        ax.plot(
            team.robot_stamps_s[sel],
            100 * team.errors_m[sel],
            ".-",
            color=colour,
            lw=0.8,
            label=f"robot_{rid}: {100 * shares[rid]:.2f} cm in the team map",
        )
        if rid in own_ate:
            ax.axhline(
                100 * own_ate[rid],
                color=colour,
                ls="--",
                lw=0.8,
                label=f"robot_{rid}: own ATE {100 * own_ate[rid]:.2f} cm",
            )
    ax.set_xlabel("keyframe stamp [s]")
    ax.set_ylabel("position error [cm]")
    ax.set_title(f"team map: keyframe errors (team ATE {100 * team.rmse_m:.2f} cm)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "team_errors.png"), dpi=100)
    plt.close(fig)


def keyframe_errors(stamps, poses, stamps_gt, poses_gt, mono: bool = False):
    """(stamps, position errors [m], ATE result) of a trajectory aligned on its own as its ATE
    is; None when it cannot be aligned."""
    try:
        res = ate(stamps, poses, stamps_gt, poses_gt, correct_scale=mono)
    except EvaluationError:
        return None
    return res.stamps_s, res.errors_m, res


def plot_path_errors(out_dir: str, series: dict, gts: dict, mono=()) -> None:
    """``path_errors.png``: per robot, the position error of each keyframe over time for each of
    its trajectories (robot id -> [(label, stamps, poses)], e.g. its odometry, the team map's
    poses, its client's published path), each aligned to ground truth on its own."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    robots = [r for r in sorted(series) if r in gts and len(gts[r][0])]
    if not robots:
        return
    cols = 1 if len(robots) == 1 else 2
    rows = -(-len(robots) // cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(6.5 * cols, 2.4 * rows + 0.8), squeeze=False, sharex=True
    )
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, rid in zip(axes.flat, robots):
        for k, (label, stamps, poses) in enumerate(series[rid]):
            found = keyframe_errors(stamps, poses, *gts[rid], mono=rid in mono)
            if found is None:
                continue
            t, err, res = found
            ax.plot(
                t,
                100 * err,
                marker="o",
                ms=2,
                lw=max(0.8, 2.6 - 0.9 * k),  # later series thinner: a path on another shows
                alpha=0.85,
                color=colours[k % len(colours)],
                label=f"{label} (ATE {100 * res.rmse_m:.2f} cm)",
            )
        ax.set_title(f"robot_{rid}", fontsize=9)
        ax.set_ylabel("error [cm]")
        ax.legend(fontsize=7)
    for ax in axes.flat[len(robots) :]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle("keyframe position errors (each trajectory aligned to ground truth on its own)")
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "path_errors.png"), dpi=110)
    plt.close(fig)


def write_ply(path: str, points: np.ndarray, rgb: np.ndarray) -> None:
    """ASCII PLY (x, y, z, red, green, blue) of points (N, 3) [m] with colours (N, 3) uint8."""
    points = np.asarray(points, float).reshape(-1, 3)
    rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
    with open(path, "w", encoding="ascii") as fh:
        fh.write(
            f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\n"
            "property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
            "property uchar blue\nend_header\n"
        )
        np.savetxt(fh, np.column_stack([points, rgb]), fmt="%.4f %.4f %.4f %d %d %d")
