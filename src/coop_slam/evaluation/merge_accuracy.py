"""How accurate a run's merges and links between merged robots are against ground truth, each
judged in its group's length unit: metres, or (a group of monocular maps) the first map's own
units, whose true length that map's Sim(3) alignment gives."""

from __future__ import annotations

import numpy as np

from ..team.map_scale import scale_translation
from ..team.results import TYPE_LINK
from .metrics import EvaluationError, ate, relative_pose_error
from .run_data import RobotRun, RunData


def map_units(run: RunData, sensors: dict) -> tuple[list[tuple], list[tuple]]:
    """Per merge (in order), the true length (metres) of one unit of its ``T_camA_camB`` and of
    each side's map just before it, as ``1.0`` (metres) or ``("unit", robot)`` (that monocular
    robot's own units, whose length its Sim(3) ATE gives): a group with a robot with depth is
    metric (the server rescales a monocular side into metres), a group of monocular maps keeps
    the units of the first side's group; and the timeline of every robot's units: ``(stamp_s,
    {robot: unit})`` from the start and after each merge (a link between merged robots is in
    the units of its time). Rescales by marker sightings are not followed."""

    def own(robot):
        return 1.0 if sensors.get(robot) != "mono" else ("unit", robot)

    units = {r: own(r) for r in run.robots}
    group = {r: {r} for r in run.robots}
    out, timeline = [], [(-np.inf, dict(units))]
    for m in run.merges:
        a, b = m["robot_a"], m["robot_b"]
        ga, gb = group.get(a, {a}), group.get(b, {b})
        unit_a, unit_b = units.get(a, own(a)), units.get(b, own(b))
        after = 1.0 if 1.0 in (unit_a, unit_b) else unit_a
        out.append((after, unit_a, unit_b))
        merged = ga | gb
        for x in merged:
            group[x] = merged
            units[x] = after
        timeline.append((m["stamp_s"], dict(units)))
    return out, timeline


def metres_per_unit(unit, true_scale: dict) -> float | None:
    """The true length of one ``unit`` (as :func:`map_units` gives them) [m]; None when that
    monocular map's true scale is unknown."""
    return 1.0 if unit == 1.0 else true_scale.get(unit[1])


def merge_scale_errors(m: dict, unit_a, unit_b, run: RunData, gts: dict, true_scale: dict):
    """A similarity merge's scale (b's lengths into a's) against the true ratio of the two maps'
    units (see :func:`map_units`): their whole paths' (scale drift inside a map enters) and
    around the matched keyframes; each None when unknown."""

    def length(unit, side: str, local: bool) -> float | None:
        if unit == 1.0 or not local:
            return metres_per_unit(unit, true_scale)
        robot = m[f"robot_{side}"]
        if unit[1] != robot or robot not in gts:
            return None  # the units are another robot's: no local truth at this keyframe
        r = run.robots.get(robot, RobotRun())
        return local_scale(r, gts[robot], m[f"keyframe_{side}"], MERGE_SCALE_HALF_WINDOW)

    out = []
    for local in (False, True):
        la, lb = length(unit_a, "a", local), length(unit_b, "b", local)
        out.append(m["scale"] * la / lb - 1.0 if la and lb else None)
    return tuple(out)


# Keyframes each side of a merge's matched keyframe whose alignment gives the map's true local scale
MERGE_SCALE_HALF_WINDOW = 7


def local_scale(r: RobotRun, gt: tuple, keyframe_id: int, half_window: int) -> float | None:
    """True metres per unit of a monocular map around one of its keyframes: the Sim(3) alignment
    of its ``2 half_window + 1`` keyframes nearest in time to ground truth. A merge's similarity
    comes from the map points around its matched keyframes, so scale drift elsewhere in the map
    does not enter its error."""
    stamp = r.keyframe_stamps.get(keyframe_id)
    if stamp is None or not r.keyframes:
        return None
    stamps, poses = r.first_segment_arrays()
    i = int(np.searchsorted(stamps, stamp))
    lo, hi = max(0, i - half_window), min(len(stamps), i + half_window + 1)
    try:
        return ate(stamps[lo:hi], poses[lo:hi], *gt, correct_scale=True).scale
    except EvaluationError:
        return None


def local_merge_error(m: dict, run: RunData, gts: dict) -> tuple[float, float] | None:
    """Error of the merge's registration against the truth: the verified relative pose of the
    matched keyframes' cameras against their true relative pose. Odometry drift does not enter,
    nor do later local-BA moves of the keyframes (which the map transform was chained through)."""
    stamps = []
    for side in "ab":
        robot, kf = m[f"robot_{side}"], m.get(f"keyframe_{side}")
        stamp = (m.get("keyframe_stamps") or {}).get(side)
        if stamp is None and robot in run.robots:
            stamp = run.robots[robot].keyframe_stamps.get(kf)
        if stamp is None or robot not in gts:
            return None
        stamps.append(stamp)
    a, b = m["robot_a"], m["robot_b"]
    return relative_pose_error(m["T_camA_camB"], stamps[0], stamps[1], gts[a], gts[b])


def link_errors(
    run: RunData, gts: dict, groups: list, unit_timeline: list, true_scale: dict
) -> list[dict]:
    """Per robot pair of one group: the links between them (see :class:`RunData`) and their
    median registration error at the keyframes (None without ground truth). A link's
    ``T_camA_camB`` is in its group's length unit when it was made (``unit_timeline``, see
    :func:`map_units`: 1.0 for metres or ``("unit", robot)``), a monocular map's true metres
    per unit being ``true_scale``'s (None without it)."""
    out = []
    for group in groups:
        for i, a in enumerate(sorted(group)):
            for b in sorted(group)[i + 1 :]:
                errs = []
                count = 0
                for k in run.links:
                    if k["type"] != TYPE_LINK or sorted(k["robots"]) != [a, b]:
                        continue
                    count += 1
                    (ra, rb), (sa, sb) = k["robots"], k["keyframe_stamps"]
                    if sa is None or sb is None or ra not in gts or rb not in gts:
                        continue
                    unit = _units_at(unit_timeline, k.get("stamp_s", np.inf)).get(a, 1.0)
                    length = metres_per_unit(unit, true_scale)
                    if length is None:
                        continue
                    T_camA_camB = scale_translation(k["T_camA_camB"], length)
                    err = relative_pose_error(T_camA_camB, sa, sb, gts[ra], gts[rb])
                    if err is not None:
                        errs.append(err)
                errs = np.array(errs).reshape(-1, 2)
                out.append(
                    {
                        "robots": [a, b],
                        "count": count,
                        "trans_err_m": float(np.median(errs[:, 0])) if len(errs) else None,
                        "rot_err_deg": float(np.median(errs[:, 1])) if len(errs) else None,
                    }
                )
    return out


def _units_at(unit_timeline: list, stamp_s: float) -> dict:
    """The robots' units at ``stamp_s`` (after the merges decided by then)."""
    units = unit_timeline[0][1]
    for merged_s, after in unit_timeline[1:]:
        if merged_s > stamp_s:
            break
        units = after
    return units
