"""The look-alike check: whether a verified match between two robots' keyframes taken at about the
same time is physically possible. Pure functions over keyframe records.

Identical textures in two places (posters, repeated furniture) pass any two-view check. When the
two keyframes were taken at about the same time, the match also fixes where each robot stood in
the other's map, and that can be impossible: the two cameras closer than two robots can stand, or
a keyframe seeing surfaces straight through where the other robot would be.
"""

from __future__ import annotations

import logging

import numpy as np

from ..geometry import invert, transform_points
from ..registration.camera import project
from ..registration.relative_pose import RelativePoseResult
from ..wire.record import KeyframeRecord
from .config import RendezvousConfig
from .keyframe_store import KeyframeStore, track
from .map_scale import MapScales, rescale_record, scale_translation

log = logging.getLogger(__name__)

# A robot's position between two keyframes is interpolated only across gaps up to this long [s]:
# a robot's path bends little in a second, so the straight line between them errs by
# centimetres, well under rendezvous.min_separation_m.
TRACK_GAP_S = 1.0

# What of a robot surely surrounds its camera (housing, mount, body) [m], and how deep its body
# reaches behind that [m]: a keyframe whose keypoints around where another robot's camera would
# be (at least SEE_THROUGH_MIN_KEYPOINTS of them, nearly all) lie farther than that looks
# straight through the other robot.
BODY_RADIUS_M = 0.1
BODY_DEPTH_M = 0.3
SEE_THROUGH_MIN_KEYPOINTS = 5
SEE_THROUGH_FRACTION = 0.8


def sees_through(rec: KeyframeRecord, c_cam: np.ndarray) -> bool:
    """Whether keyframe ``rec`` sees surfaces behind the point ``c_cam`` (its camera frame)
    all around it, where another robot's camera would be."""
    cam = rec.camera
    if c_cam[2] < 2 * BODY_RADIUS_M:
        return False
    u, v = project(c_cam[None], cam.K)[0]
    if not (0 <= u < cam.width and 0 <= v < cam.height):
        return False
    radius_px = cam.fx * BODY_RADIUS_M / c_cam[2]
    uv = rec.keypoints[:, :2]
    near = (np.hypot(uv[:, 0] - u, uv[:, 1] - v) <= radius_px) & (rec.depths_m > 0)
    if near.sum() < SEE_THROUGH_MIN_KEYPOINTS:
        return False
    beyond = rec.depths_m[near] > c_cam[2] + BODY_DEPTH_M
    return bool(beyond.mean() >= SEE_THROUGH_FRACTION)


def interpolate_track(stamps_s: np.ndarray, positions: np.ndarray, stamp_s: float):
    """Position at ``stamp_s`` on a time-ordered track: its keyframe at that stamp, else the
    straight line between the keyframes just before and after, when each is within TRACK_GAP_S;
    None when they do not pin it down (a gap, before the first or after the last keyframe)."""
    after = int(np.searchsorted(stamps_s, stamp_s))  # first keyframe at or after stamp_s
    if after < len(stamps_s) and stamps_s[after] == stamp_s:
        return positions[after]
    if after == 0 or after == len(stamps_s):
        return None
    t0, t1 = stamps_s[after - 1], stamps_s[after]
    if t1 - stamp_s > TRACK_GAP_S or stamp_s - t0 > TRACK_GAP_S:
        return None
    w = (stamp_s - t0) / (t1 - t0)
    return (1.0 - w) * positions[after - 1] + w * positions[after]


def impossible_reason(
    rec_a: KeyframeRecord,
    rec_b: KeyframeRecord,
    T_a_b: np.ndarray,
    segment_a: list[KeyframeRecord],
    segment_b: list[KeyframeRecord],
    window_s: float,
    min_separation_m: float,
) -> str | None:
    """Why ``T_a_b`` (keyframe b's camera in keyframe a's) cannot hold, or None.

    ``segment_a`` / ``segment_b`` are the keyframes of each robot's map segment (the segment of
    rec_a / rec_b). The match fixes where each robot's map lies in the other's. Then, at the time
    of every keyframe of either robot within ``window_s`` of the pair (as far as the other robot's
    keyframes tell where it was then): the two cameras must be ``min_separation_m`` apart, and a
    keyframe cannot see surfaces straight through the other robot's body."""
    T_mapA_mapB = rec_a.T_map_cam @ T_a_b @ invert(rec_b.T_map_cam)
    lo = min(rec_a.stamp_s, rec_b.stamp_s) - window_s
    hi = max(rec_a.stamp_s, rec_b.stamp_s) + window_s
    for viewer, own, other, others, T_mapV_mapO in (
        (rec_a, segment_a, rec_b, segment_b, T_mapA_mapB),
        (rec_b, segment_b, rec_a, segment_a, invert(T_mapA_mapB)),
    ):
        other_track = track(others)
        for rec in own:
            if not lo <= rec.stamp_s <= hi:
                continue
            p_other = interpolate_track(*other_track, rec.stamp_s)
            if p_other is None:
                continue
            c = transform_points(invert(rec.T_map_cam) @ T_mapV_mapO, p_other[None])[0]
            if np.linalg.norm(c) < min_separation_m:
                return (
                    f"robot {other.robot_id}'s camera {np.linalg.norm(c):.2f} m from robot "
                    f"{viewer.robot_id}'s keyframe {rec.keyframe_id} at its time"
                )
            if sees_through(rec, c):
                return (
                    f"robot {viewer.robot_id}'s keyframe {rec.keyframe_id} sees past where robot "
                    f"{other.robot_id} would stand, {c[2]:.2f} m ahead"
                )
    return None


def is_look_alike(
    store: KeyframeStore,
    config: RendezvousConfig,
    kind: str,
    key_a,
    key_b,
    T_a_b: np.ndarray,
    s_a_b: float = 1.0,
    into_b: bool = False,
) -> bool:
    """Whether a verified pair of two robots' keyframes taken at about the same time
    (rendezvous.window_s) is physically impossible (see :func:`impossible_reason`): then the two
    places only look alike. Farther apart in time, each robot's drift would blur the test; at
    ``min_separation_m`` 0 it is off. ``kind`` names the path that verified it in the log.

    A similarity (``s_a_b`` != 1, a monocular map) is judged in one length unit: a's (b's maps
    rescaled by ``s_a_b``), or with ``into_b`` b's, when only b's map is metric."""
    rec_a, rec_b = store.record(key_a), store.record(key_b)
    dt = abs(rec_a.stamp_s - rec_b.stamp_s)
    if config.min_separation_m <= 0 or key_a[0] == key_b[0] or dt > config.window_s:
        return False
    segment_a = store.map_records(rec_a.map_id)
    segment_b = store.map_records(rec_b.map_id)
    if s_a_b != 1.0:
        if into_b:
            factor = 1.0 / s_a_b
            rec_a, T_a_b = rescale_record(rec_a, factor), scale_translation(T_a_b, factor)
            segment_a = [rescale_record(r, factor) for r in segment_a]
        else:
            rec_b = rescale_record(rec_b, s_a_b)
            segment_b = [rescale_record(r, s_a_b) for r in segment_b]
    why = impossible_reason(
        rec_a,
        rec_b,
        T_a_b,
        segment_a,
        segment_b,
        config.window_s,
        config.min_separation_m,
    )
    if why is None:
        return False
    log.info("%s %s - %s: a look-alike place: %s", kind, key_a, key_b, why)
    return True


def match_is_look_alike(
    store: KeyframeStore,
    config: RendezvousConfig,
    scales: MapScales | None,
    kind: str,
    key_a,
    key_b,
    res: RelativePoseResult,
) -> bool:
    """:func:`is_look_alike` of a verified match; a similarity is judged in the units of the side
    a merge would keep (the metric one; ``scales`` None: every map is metric)."""
    into_b = (
        scales is not None
        and res.scale != 1.0
        and scales.merge_side(key_a[0], key_b[0], res.scale)[0] == "a"
    )
    return is_look_alike(store, config, kind, key_a, key_b, res.T_a_b, res.scale, into_b)
