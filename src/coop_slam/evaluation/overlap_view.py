"""A picture of where robots' maps overlap: a top view of the team cloud and a thin horizontal slice
through it, points coloured by robot, titled with the agreement figures of
:mod:`.agreement`. In the slice a wall is a line; a misaligned stitch draws it twice, once per
robot, which is what a person checks the figures against. Matplotlib (Agg): nothing is shown."""

from __future__ import annotations

import numpy as np

from ..team.fusion import robot_colours
from .agreement import AgreementConfig, AgreementError, as_keyframe_clouds, overlap_agreement

_AXES = "xyz"
_MAX_TITLE_PAIRS = 6  # more pairs than this are summarised, the worst first


def parse_up_axis(up_axis: str) -> tuple[int, float]:
    """``"z"``, ``"+z"``, ``"-y"``, ... -> (axis index, sign)."""
    text = str(up_axis).strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    name = text.lstrip("+-")
    if name not in _AXES or len(name) != 1:
        raise AgreementError(
            f"up_axis {up_axis!r}: expected one of x, y, z with an optional sign, e.g. '-y' for a "
            "camera-optical map frame (y down) or 'z' for a ROS world frame"
        )
    return _AXES.index(name), sign


def guess_up_axis(positions_group: np.ndarray) -> tuple[int, float]:
    """Up axis of a frame from camera positions (N, 3): the axis along which the cameras spread
    least (robots and hand-held cameras mostly stay at one height). Its sign cannot be seen from
    positions: -y is assumed for y (camera-optical map frames, y down), + otherwise."""
    positions_group = np.asarray(positions_group, float).reshape(-1, 3)
    axis = int(np.argmin(np.ptp(positions_group, axis=0))) if len(positions_group) else 2
    return axis, (-1.0 if axis == 1 else 1.0)


def _view_axes(axis: int, sign: float) -> tuple[int, int]:
    """The two horizontal axes (h1, h2), ordered so h1 x h2 = up: a view from above, not a
    mirror image."""
    h1, h2 = (axis + 1) % 3, (axis + 2) % 3  # e_{i+1} x e_{i+2} = e_i
    return (h1, h2) if sign > 0 else (h2, h1)


def _pair_lines(pairs: list[dict]) -> list[str]:
    def ratio(p):
        if p["inter_m"] is None:
            return -1.0
        return p["inter_m"] / p["intra_m"] if p["intra_m"] else np.inf

    def mm(value):
        return "-" if value is None else f"{1e3 * value:.1f} mm"

    shown = sorted(pairs, key=lambda p: (-ratio(p), p["robots"]))
    lines = [
        f"robots {p['robots'][0]}-{p['robots'][1]}: inter {mm(p['inter_m'])} "
        f"({p.get('inter_points', 0)} pts), intra {mm(p['intra_m'])} "
        f"({p.get('intra_points', 0)} pts)"
        for p in shown[:_MAX_TITLE_PAIRS]
    ]
    if len(shown) > _MAX_TITLE_PAIRS:
        lines.append(f"... {len(shown) - _MAX_TITLE_PAIRS} more pairs")
    return lines


def plot_overlap(
    path_png: str,
    clouds_by_robot: dict,
    up_axis: str | None = None,
    slice_m: float = 0.10,
    slice_height_m: float | None = None,
    pairs: list[dict] | None = None,
    config: AgreementConfig | None = None,
    title: str = "map overlap",
    max_points_per_robot: int = 50_000,
    seed: int = 0,
) -> str:
    """Draw ``path_png``: left, a top view of every robot's points (keyframe positions as a path);
    right, the points within ``slice_m`` of ``slice_height_m`` (default: the median camera
    height), each robot in its team-map colour (as in rviz).

    ``clouds_by_robot`` is the input of :func:`.agreement.overlap_agreement` (one group frame).
    ``up_axis`` names the frame's up direction (``"z"``, ``"-y"``, ...); by default it is guessed
    from the camera positions (:func:`guess_up_axis`). ``pairs`` are the agreement figures for the
    title; None computes them with ``config``. Points are sampled (fixed ``seed``) down to
    ``max_points_per_robot`` per robot and drawn in a shuffled order so no robot hides another.
    Returns ``path_png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    if not isinstance(clouds_by_robot, dict) or not clouds_by_robot:
        raise AgreementError("plot_overlap: expected a non-empty dict robot id -> keyframe clouds")
    if not (np.isfinite(slice_m) and slice_m > 0):
        raise AgreementError(f"plot_overlap: slice_m must be > 0 [m], got {slice_m}")
    keyframes = {rid: as_keyframe_clouds(rid, kfs) for rid, kfs in sorted(clouds_by_robot.items())}
    if pairs is None:
        pairs = overlap_agreement(clouds_by_robot, config)
    rng = np.random.default_rng(seed)
    points, paths = {}, {}
    for rid, kfs in keyframes.items():
        kfs = sorted(kfs, key=lambda kf: kf.stamp_s)
        chunks = [
            kf.points_cam[np.all(np.isfinite(kf.points_cam), axis=1)] @ kf.T_group_cam[:3, :3].T
            + kf.T_group_cam[:3, 3]
            for kf in kfs
        ]
        points[rid] = np.concatenate(chunks) if chunks else np.zeros((0, 3))
        paths[rid] = np.array([kf.T_group_cam[:3, 3] for kf in kfs]).reshape(-1, 3)
    all_positions = np.concatenate(list(paths.values()))
    axis, sign = parse_up_axis(up_axis) if up_axis is not None else guess_up_axis(all_positions)
    h1, h2 = _view_axes(axis, sign)
    if slice_height_m is None:
        slice_height_m = (
            float(np.median(sign * all_positions[:, axis])) if len(all_positions) else 0
        )
    axis_label = ("-" if sign < 0 else "") + _AXES[axis]

    fig, (ax_top, ax_slice) = plt.subplots(1, 2, figsize=(14, 7.5), sharex=True, sharey=True)
    handles, top, in_slice = [], [], []
    for rid, pts in points.items():
        rgb = robot_colours([rid])[0] / 255.0
        sample = pts
        if len(pts) > max_points_per_robot:
            sample = pts[np.sort(rng.choice(len(pts), max_points_per_robot, replace=False))]
        top.append((sample, rgb))
        # The slice is thin: all its points are drawn, so a doubled wall is never thinned away.
        in_slice.append((pts[np.abs(sign * pts[:, axis] - slice_height_m) <= slice_m / 2], rgb))
        path = paths[rid]
        ax_top.plot(path[:, h1], path[:, h2], color=rgb, lw=1.2, zorder=3)
        handles.append(
            Line2D(
                [], [], color=rgb, marker="o", ls="-", ms=5, label=f"robot {rid} ({len(path)} kf)"
            )
        )
    for ax, groups, size, alpha in ((ax_top, top, 0.4, 0.25), (ax_slice, in_slice, 1.0, 0.8)):
        pts = np.concatenate([g[0] for g in groups])
        rgb = np.concatenate([np.tile(g[1], (len(g[0]), 1)) for g in groups])
        order = rng.permutation(len(pts))  # interleaved: no robot is drawn on top of another
        ax.scatter(pts[order, h1], pts[order, h2], s=size, c=rgb[order], alpha=alpha, lw=0)
    ax_top.set_title("top view: all points, keyframe paths")
    ax_slice.set_title(
        f"slice {100 * slice_m:.0f} cm thick at {axis_label} = {slice_height_m:.2f} m "
        "(doubled lines = maps disagree)"
    )
    for ax in (ax_top, ax_slice):
        ax.set_xlabel(f"{_AXES[h1]} [m]")
        ax.set_aspect("equal", adjustable="box")  # shared axes: same scale
        ax.grid(True, lw=0.4, alpha=0.5)
    ax_top.set_ylabel(f"{_AXES[h2]} [m]")
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=9)
    lines = _pair_lines(pairs) or ["no robot pair"]
    fig.suptitle(
        f"{title}  (up = {axis_label}; trimmed-RMS point-to-plane gap)\n" + "\n".join(lines),
        fontsize=10,
    )
    # Room for the legend below the panels and for the title's lines above them.
    top = 0.99 - 0.022 * (len(lines) + 1)
    fig.tight_layout(rect=(0, 0.05, 1, top))
    fig.savefig(path_png, dpi=110)
    plt.close(fig)
    return path_png
