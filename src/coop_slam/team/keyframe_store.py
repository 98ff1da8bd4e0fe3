"""The server's keyframe store: every robot's current keyframes, their BoW vectors in the team
keyframe database, and the lookups the stitching stages share (by robot, by time, a robot's track).

Keys are ``(robot_id, keyframe_id)``. A keyframe's BoW vector is computed once, when it arrives as
new: local-BA updates move its pose and points, never its descriptors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bow import Vocabulary
from ..bow.database import DatabaseConfig, KeyframeDatabase
from ..bow.vocabulary import BowVector
from ..registration.keyframe_view import KeyframeView
from ..wire.record import KeyframeRecord

Key = tuple[int, int]  # (robot_id, keyframe_id)


@dataclass
class _Stored:
    record: KeyframeRecord
    view: KeyframeView | None = None  # built on first use by a registration


class KeyframeStore:
    """Keyframes of all robots, in arrival order, with the team's BoW database."""

    def __init__(self, vocabulary: Vocabulary, database: DatabaseConfig):
        self.vocabulary = vocabulary
        self.database = KeyframeDatabase(database)
        self._stored: dict[Key, _Stored] = {}

    # --- changes ----------------------------------------------------------------------------------
    def add(self, rec: KeyframeRecord) -> tuple[BowVector, list[Key]]:
        """Store a new keyframe and index it; returns its BoW vector and covisible keys."""
        key = (rec.robot_id, rec.keyframe_id)
        bow, _ = self.vocabulary.transform(rec.descriptors)
        covisible = [(rec.robot_id, int(k)) for k in rec.covisible_ids]
        self._stored[key] = _Stored(rec)
        self.database.add(rec.robot_id, rec.keyframe_id, bow, covisible)
        return bow, covisible

    def update(self, rec: KeyframeRecord) -> None:
        """A stored keyframe's new pose and points (its place in the arrival order stays)."""
        self._stored[(rec.robot_id, rec.keyframe_id)] = _Stored(rec)

    def remove(self, key: Key) -> bool:
        """Forget a keyframe; whether it was stored."""
        if key not in self._stored:
            return False
        del self._stored[key]
        self.database.remove(*key)
        return True

    # --- lookups ----------------------------------------------------------------------------------
    def __contains__(self, key: Key) -> bool:
        return key in self._stored

    def __len__(self) -> int:
        return len(self._stored)

    def keys(self) -> list[Key]:
        """Every stored key, in arrival order."""
        return list(self._stored)

    def records(self) -> list[KeyframeRecord]:
        """Every stored keyframe, in arrival order."""
        return [s.record for s in self._stored.values()]

    def record(self, key: Key) -> KeyframeRecord:
        return self._stored[key].record

    def stamp(self, key: Key) -> float:
        return self._stored[key].record.stamp_s

    def view(self, key: Key) -> KeyframeView:
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

    def is_mono(self, key: Key) -> bool:
        return is_mono(self._stored[key].record)

    def bow(self, key: Key) -> BowVector:
        return self.database.bow(*key)

    def robots(self) -> list[int]:
        """Robots with at least one stored keyframe."""
        return sorted({r for r, _ in self._stored})

    def keyframe_ids(self, robot_id: int) -> list[int]:
        return sorted(k for (r, k) in self._stored if r == robot_id)

    def latest_stamp(self, robot_id: int) -> float | None:
        return max(
            (s.record.stamp_s for k, s in self._stored.items() if k[0] == robot_id), default=None
        )

    def segment_records(self, robot_id: int, map_segment: int) -> list[KeyframeRecord]:
        """A robot's keyframes of one map segment, in arrival order."""
        return [
            s.record
            for k, s in self._stored.items()
            if k[0] == robot_id and s.record.map_segment == map_segment
        ]

    def near_in_time(
        self, robot_id: int, stamp_s: float, window_s: float, latest_fallback: bool = False
    ) -> list[Key]:
        """Keys of robot_id's keyframes within window_s of stamp_s, nearest first. A robot that
        stands still makes no new keyframes: with ``latest_fallback`` its latest keyframe before
        the window stands for what it sees. Only for requests that bring their own cue (a marker
        sighting, an operator): for the automatic test, being seen at the same time is part of the
        evidence (identical textures in two places pass any geometric check)."""
        keys = [
            (k, abs(s.record.stamp_s - stamp_s))
            for k, s in self._stored.items()
            if k[0] == robot_id and abs(s.record.stamp_s - stamp_s) <= window_s
        ]
        if not keys and latest_fallback:
            before = [
                (k, s.record.stamp_s)
                for k, s in self._stored.items()
                if k[0] == robot_id and s.record.stamp_s < stamp_s
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
