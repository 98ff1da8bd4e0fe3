"""What changed in a keyframe since the server got it, and putting it back together: the
observation patches and point moves a client's updates carry, the descriptors a new keyframe takes
from keyframes the server holds, and a delta update completed from the keyframe as stored.
The client's uplink computes them; the server's decoder applies them: one code for both sides."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..descriptors import DESCRIPTOR_BYTES
from .encodings import MOVE_MAX_M, MOVE_STEP_M, move_steps, moves_from_steps
from .record import MAX_REF_KEYFRAMES, STATIC_ARRAYS, KeyframeError, KeyframeRecord


def observation_patch(
    held_ids: np.ndarray,
    held_points: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
    min_move_m: float,
) -> np.ndarray:
    """Indices of the keypoints whose observation differs from what the server holds
    (``held_ids``, ``held_points``: per keypoint, NaN rows where there is no map point): another
    map point or none, or the same point moved more than ``min_move_m``. ``ids``/``points`` are
    the keyframe's now, in the same per-keypoint form."""
    changed = np.asarray(held_ids) != np.asarray(ids)
    with np.errstate(invalid="ignore"):
        moved = np.linalg.norm(np.asarray(points) - held_points, axis=1) > min_move_m
    return np.flatnonzero(changed | moved).astype(np.uint32)


def patch_of(rec: KeyframeRecord, patched: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a patch of ``rec``'s observations carries for the keypoints ``patched``: their map
    point ids and, in that order, the (M, 3) positions of the non-zero ones."""
    patched = np.asarray(patched, np.int64)
    ids = np.asarray(rec.map_point_ids, np.uint32)[patched]
    return ids, rec.map_points_per_keypoint()[patched][ids != 0].astype(np.float32)


def apply_observation_patch(
    held_ids: np.ndarray,
    held_points: np.ndarray,
    patched: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The observations after a patch: (ids, per-keypoint points, NaN rows where none). The patch
    gives, for the keypoints ``patched``, their map point ids (0 = none now) and, in that order,
    the positions of the non-zero ones. Raises KeyframeError when it does not fit."""
    n = len(held_ids)
    patched = np.asarray(patched, np.int64)
    if len(ids) != len(patched):
        raise KeyframeError(
            f"an observation patch lists {len(patched)} keypoints but {len(ids)} map point ids"
        )
    if len(patched) and (patched.min() < 0 or patched.max() >= n):
        raise KeyframeError(
            f"an observation patch names keypoint {int(patched.max())} of a keyframe with {n}"
        )
    if len(np.unique(patched)) != len(patched):
        raise KeyframeError("an observation patch names a keypoint twice")
    seen = np.asarray(ids) != 0
    if len(points) != int(seen.sum()):
        raise KeyframeError(
            f"an observation patch gives {len(points)} map points for {int(seen.sum())} observed "
            "keypoints"
        )
    out_ids = np.array(held_ids, np.uint32, copy=True)
    out_points = np.array(held_points, float, copy=True)
    out_ids[patched] = ids
    out_points[patched] = np.nan
    out_points[patched[seen]] = points
    return out_ids, out_points


def split_moves(
    held_ids: np.ndarray,
    held_points: np.ndarray,
    patched: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
    min_move_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of the keypoints ``patched`` (see :func:`observation_patch`; ``ids``, ``points`` the
    keyframe's now, per keypoint), those whose map point only moved, by at most ``MOVE_MAX_M``
    per coordinate: ``(others, moved, moves)``, the rest of ``patched``, the moved keypoints and
    their (k, 3) float32 moves [m] since ``held_points``, rounded to ``MOVE_STEP_M`` (half a step
    off at most). ``min_move_m`` below a step: none (every position travels exact: the rounding
    would be above the moves left unsent)."""
    patched = np.asarray(patched, np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        move = np.asarray(points, float)[patched] - np.asarray(held_points, float)[patched]
        largest = np.abs(move).max(axis=1, initial=0.0)
        ok = (
            (np.asarray(held_ids)[patched] == np.asarray(ids)[patched])
            & (np.asarray(ids)[patched] != 0)
            & np.all(np.isfinite(move), axis=1)
            & (largest <= MOVE_MAX_M)
            & (min_move_m >= MOVE_STEP_M)
        )
    return (
        patched[~ok].astype(np.uint32),
        patched[ok].astype(np.uint32),
        moves_from_steps(move_steps(move[ok])).reshape(-1, 3),
    )


def apply_moves(
    held_ids: np.ndarray, held_points: np.ndarray, moved: np.ndarray, moves: np.ndarray
) -> np.ndarray:
    """The per-keypoint points after the keypoints ``moved``'s map points moved by ``moves``
    ((k, 3) [m], as the message carries them: see :func:`split_moves`), added in float32 as the
    message's points are (the client and the server add alike; the server's position differs
    from the client's by the rounding of a monocular map's scale at most). Raises KeyframeError
    when they do not fit."""
    n = len(held_ids)
    moved = np.asarray(moved, np.int64)
    moves = np.asarray(moves, np.float32).reshape(-1, 3)
    if len(moves) != len(moved):
        raise KeyframeError(f"{len(moves)} moves for {len(moved)} moved keypoints")
    if len(moved) and (moved.min() < 0 or moved.max() >= n):
        raise KeyframeError(f"moved names keypoint {int(moved.max())} of a keyframe with {n}")
    if len(np.unique(moved)) != len(moved):
        raise KeyframeError("moved names a keypoint twice")
    if np.any(np.asarray(held_ids)[moved] == 0):
        raise KeyframeError("moved names a keypoint that observes no map point")
    if not np.all(np.isfinite(moves)):
        raise KeyframeError("a move is NaN or inf")
    out = np.array(held_points, float, copy=True)
    out[moved] = np.asarray(out[moved], np.float32) + moves
    return out


def complete_update(
    sent: KeyframeRecord,
    base: KeyframeRecord,
    patched: np.ndarray | None = None,
    moves: tuple[np.ndarray, np.ndarray] | None = None,
) -> KeyframeRecord:
    """A delta update as the server holds it: what the keyframe saw from ``base`` (the keyframe
    as stored), and its observations from ``sent`` -- all of them (``patched`` None), or a patch
    of ``base``'s (see :func:`apply_observation_patch`) and ``moves`` of its map points (moved
    keypoints, their moves: see :func:`apply_moves`)."""
    static = {k: getattr(base, k) for k in STATIC_ARRAYS}
    if patched is None:
        return dataclasses.replace(sent, **static)
    if sent.keyframe_id != base.keyframe_id:  # (the server holds it under its map's id)
        raise KeyframeError(
            f"keyframe {sent.keyframe_id} of robot {sent.robot_id}: patched against keyframe "
            f"{base.keyframe_id}"
        )
    ids, per_keypoint = apply_observation_patch(
        base.map_point_ids,
        base.map_points_per_keypoint(),
        patched,
        sent.map_point_ids,
        np.asarray(sent.map_points).reshape(-1, 3),
    )
    if moves is not None:
        if len(np.intersect1d(np.asarray(moves[0], np.int64), np.asarray(patched, np.int64))):
            raise KeyframeError(
                f"keyframe {sent.keyframe_id} of robot {sent.robot_id}: a keypoint is both "
                "patched and moved"
            )
        per_keypoint = apply_moves(ids, per_keypoint, *moves)
    return dataclasses.replace(
        sent,
        **static,
        map_point_ids=ids,
        map_points=per_keypoint[ids != 0].astype(np.float32),
    )


def observation_index(source_ids: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Per map point id of ``ids``, the index of the first keypoint observing it in a keyframe
    whose per-keypoint map point ids are ``source_ids``; -1 where none does (and for id 0)."""
    source_ids, ids = np.asarray(source_ids, np.int64), np.asarray(ids, np.int64)
    if not len(source_ids):
        return np.full(len(ids), -1, np.int64)
    order = np.argsort(source_ids, kind="stable")  # equal ids keep their keypoint order
    ranked = source_ids[order]
    pos = np.minimum(np.searchsorted(ranked, ids), len(ranked) - 1)
    return np.where((ranked[pos] == ids) & (ids != 0), order[pos], -1)


def shared_descriptors(
    map_point_ids: np.ndarray,
    own: np.ndarray,
    refs: np.ndarray,
    ref_keyframes: np.ndarray,
    stored,
    where: str,
) -> np.ndarray:
    """A keyframe's (N, 32) descriptors from a message that leaves some out (a whole
    keyframe's ``descriptor_refs``): ``own`` are the descriptors of the keypoints whose ``refs``
    entry is 0; a keypoint with ``refs`` i >= 1 takes the descriptor of the keypoint observing its
    map point in keyframe ``ref_keyframes[i - 1]``, the record ``stored(keyframe_id)`` gives
    (None: not held).
    Raises KeyframeError naming what does not fit."""
    refs = np.asarray(refs, np.int64)
    ids = np.asarray(map_point_ids, np.int64)
    own = np.asarray(own, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
    if len(ref_keyframes) > MAX_REF_KEYFRAMES:
        raise KeyframeError(
            f"{where}: ref_keyframes lists {len(ref_keyframes)} keyframes, above the limit of "
            f"{MAX_REF_KEYFRAMES}"
        )
    if len(refs) != len(ids):
        raise KeyframeError(
            f"{where}: descriptor_refs has {len(refs)} entries, expected one per keypoint "
            f"({len(ids)})"
        )
    if len(own) != int(np.count_nonzero(refs == 0)):
        raise KeyframeError(
            f"{where}: descriptors hold {len(own)} descriptors for "
            f"{int(np.count_nonzero(refs == 0))} keypoints without a descriptor_refs entry"
        )
    if len(refs) and refs.max() > len(ref_keyframes):
        raise KeyframeError(
            f"{where}: descriptor_refs names reference {int(refs.max())} of "
            f"{len(ref_keyframes)} ref_keyframes"
        )
    if np.any((refs != 0) & (ids == 0)):
        raise KeyframeError(f"{where}: descriptor_refs names a keypoint that observes no map point")
    out = np.zeros((len(ids), DESCRIPTOR_BYTES), np.uint8)
    out[refs == 0] = own
    ref_keyframes = np.asarray(ref_keyframes, np.int64)
    for i in np.unique(refs[refs > 0]):
        mine, kf_id = np.flatnonzero(refs == i), int(ref_keyframes[i - 1])
        source = stored(kf_id)
        if source is None:
            raise KeyframeError(
                f"{where}: its descriptors refer to keyframe {kf_id}, which the server does not "
                "hold"
            )
        at = observation_index(source.map_point_ids, ids[mine])
        if np.any(at < 0):
            raise KeyframeError(
                f"{where}: descriptor_refs names map point {int(ids[mine][at < 0][0])} in "
                f"keyframe {kf_id}, which does not observe it"
            )
        out[mine] = source.descriptors[at]
    return out
