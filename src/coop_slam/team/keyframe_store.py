"""The server's keyframe store: every map's current keyframes, their BoW vectors in the team
keyframe database, and the lookups the stitching stages share (by map, by time, a map's track).

A stored keyframe (:class:`StoredKeyframe`) is the client's record with the map it belongs to on
the server (its robot's map segment, see :mod:`coop_slam.ids`); keys are ``(map_id,
keyframe_id)``. A keyframe's BoW vector is computed once, when it arrives as new: local-BA updates
move its pose and points, never its descriptors.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..bow import Vocabulary
from ..bow.database import DatabaseConfig, KeyframeDatabase
from ..bow.vocabulary import BowVector
from ..ids import KeyframeKey, MapId
from ..registration.keyframe_view import KeyframeView
from ..wire.record import KeyframeRecord


@dataclass
class StoredKeyframe(KeyframeRecord):
    """A keyframe as the server holds it: the client's record (``robot_id`` its robot's) and the
    map it belongs to on the server."""

    map_id: MapId = MapId(0)

    @property
    def key(self) -> KeyframeKey:
        return (self.map_id, self.keyframe_id)


def stored_keyframe(rec: KeyframeRecord, map_id: MapId) -> StoredKeyframe:
    """``rec`` as the keyframe of map ``map_id`` (its arrays shared, not copied)."""
    fields = {f.name: getattr(rec, f.name) for f in dataclasses.fields(KeyframeRecord)}
    return StoredKeyframe(**fields, map_id=map_id)


@dataclass
class _Stored:
    record: StoredKeyframe
    view: KeyframeView | None = None  # built on first use by a registration


class KeyframeStore:
    """Keyframes of all robots, in arrival order, with the team's BoW database."""

    def __init__(self, vocabulary: Vocabulary, database: DatabaseConfig):
        self.vocabulary = vocabulary
        self.database = KeyframeDatabase(database)
        self._stored: dict[KeyframeKey, _Stored] = {}

    # --- changes ----------------------------------------------------------------------------------
    def add(self, rec: StoredKeyframe) -> tuple[BowVector, list[KeyframeKey]]:
        """Store a new keyframe and index it; returns its BoW vector and covisible keys."""
        bow, _ = self.vocabulary.transform(rec.descriptors)
        covisible = [(rec.map_id, int(k)) for k in rec.covisible_ids]
        self._stored[rec.key] = _Stored(rec)
        self.database.add(rec.map_id, rec.keyframe_id, bow, covisible)
        return bow, covisible

    def update(self, rec: StoredKeyframe) -> None:
        """A stored keyframe's new pose and points (its place in the arrival order stays)."""
        self._stored[rec.key] = _Stored(rec)

    def remove(self, key: KeyframeKey) -> bool:
        """Forget a keyframe; whether it was stored."""
        if key not in self._stored:
            return False
        del self._stored[key]
        self.database.remove(*key)
        return True

    # --- lookups ----------------------------------------------------------------------------------
    def __contains__(self, key: KeyframeKey) -> bool:
        return key in self._stored

    def __len__(self) -> int:
        return len(self._stored)

    def keys(self) -> list[KeyframeKey]:
        """Every stored key, in arrival order."""
        return list(self._stored)

    def records(self) -> list[StoredKeyframe]:
        """Every stored keyframe, in arrival order."""
        return [s.record for s in self._stored.values()]

    def record(self, key: KeyframeKey) -> StoredKeyframe:
        return self._stored[key].record

    def stamp(self, key: KeyframeKey) -> float:
        return self._stored[key].record.stamp_s

    def view(self, key: KeyframeKey) -> KeyframeView:
        """The keyframe as registration sees it (keypoints, descriptors, intrinsics, 3D points:
        from depth, or a monocular keyframe's from its map points, in its map's units)."""
        stored = self._stored[key]
        if stored.view is None:
            r = stored.record
            if is_mono(r):
                stored.view = KeyframeView.from_map_points(
                    r.uv_px, r.descriptors, r.camera.K, r.map_points_per_keypoint(), r.T_map_cam
                )
            else:
                stored.view = KeyframeView(r.uv_px, r.descriptors, r.depths_m, r.camera.K)
        return stored.view

    def is_mono(self, key: KeyframeKey) -> bool:
        return is_mono(self._stored[key].record)

    def bow(self, key: KeyframeKey) -> BowVector:
        return self.database.bow(*key)

    def maps(self) -> list[MapId]:
        """Maps with at least one stored keyframe."""
        return sorted({m for m, _ in self._stored})

    def keyframe_ids(self, map_id: MapId) -> list[int]:
        return sorted(k for (m, k) in self._stored if m == map_id)

    def latest_stamp(self, map_id: MapId) -> float | None:
        return max(
            (s.record.stamp_s for k, s in self._stored.items() if k[0] == map_id), default=None
        )

    def map_records(self, map_id: MapId) -> list[StoredKeyframe]:
        """A map's keyframes, in arrival order."""
        return [s.record for k, s in self._stored.items() if k[0] == map_id]

    def near_in_time(
        self, map_id: MapId, stamp_s: float, window_s: float, latest_fallback: bool = False
    ) -> list[KeyframeKey]:
        """Keys of a map's keyframes within window_s of stamp_s, nearest first. A robot that
        stands still makes no new keyframes: with ``latest_fallback`` its latest keyframe before
        the window stands for what it sees. Only for requests that bring their own cue (a marker
        sighting, an operator): for the automatic test, being seen at the same time is part of the
        evidence (identical textures in two places pass any geometric check)."""
        keys = [
            (k, abs(s.record.stamp_s - stamp_s))
            for k, s in self._stored.items()
            if k[0] == map_id and abs(s.record.stamp_s - stamp_s) <= window_s
        ]
        if not keys and latest_fallback:
            before = [
                (k, s.record.stamp_s)
                for k, s in self._stored.items()
                if k[0] == map_id and s.record.stamp_s < stamp_s
            ]
            return [max(before, key=lambda ks: ks[1])[0]] if before else []
        return [k for k, _ in sorted(keys, key=lambda kd: kd[1])]


def is_mono(rec: KeyframeRecord) -> bool:
    """Whether a keyframe comes from a monocular camera: its map has no metric scale of its own."""
    return rec.camera.sensor == "mono"


def track(records: list[KeyframeRecord]) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s (K,), camera positions (K, 3) in their map) of keyframes, in time order."""
    # Sorted by stamp only: equal stamps must not compare the arrays.
    ordered = sorted(((r.stamp_s, r.T_map_cam[:3, 3]) for r in records), key=lambda sp: sp[0])
    if not ordered:
        return np.zeros(0), np.zeros((0, 3))
    return np.array([t for t, _ in ordered]), np.array([p for _, p in ordered])
