"""The team map's poses of a robot's own keyframes, as the robot shows them (pose-graph sharing
back to the robot).

After merges and loop closures the server holds better poses for a robot's keyframes than the
robot's odometry; it sends those that moved (see :mod:`coop_slam.team.pose_feedback`).
:class:`SharedPoses` keeps, per keyframe, the correction its last received pose makes to the
odometry's pose (``C_k = T_map_cam_team @ inv(T_odom_cam_k)``, a left multiplication in the robot's
odometry frame) and lays it over what the robot publishes: its keyframe path, its local cloud
(each point with the correction of its reference keyframe) and its live pose (the correction of
the newest corrected keyframe, REP-105's ``map -> odom``).

The odometry itself is not bent: it tracks and refines in its own continuous frame, and what it
sends the server stays an independent measurement. Moving the odometry's map onto the corrected
poses instead (as ORB-SLAM's loop correction does) bent its local bundle adjustment window with
corrections that differ per keyframe and made the team map worse (session 15's note: team ATE
0.35 -> 0.87 cm on the team world); the overlay leaves the team map as it is by construction.

A keyframe's correction follows later local refinements of its odometry pose (it is kept as an
offset, not as a fixed pose). Keyframes the server has not sent a pose for are within its
thresholds of their odometry pose (identity), except those newer than the newest corrected one
(the server has not seen them yet): they move with it, as the live pose does -- unless they begin
a new map segment, another odometry frame the server has not placed yet (identity until it
does). Keyframes the server does not hold (``server_holds``: a radio budget sent them as place
signatures only, or low-bandwidth mode) get no pose from it: they take the correction of the
corrected keyframe nearest to them in their map segment, so the published path follows the team
map through them rather than jumping back to the odometry between its corrected neighbours.

Pure core: numpy in, numpy out.
"""

from __future__ import annotations

import bisect
from typing import Callable

import numpy as np

from ..geometry import invert

_I = np.eye(4)
_I.setflags(write=False)
# A keyframe id beyond all: its correction is where the robot is now (the newest corrected one's).
NEWEST = np.iinfo(np.int64).max


class SharedPoses:
    """Corrections of one robot's keyframes (keyed by the ids its messages carry)."""

    def __init__(self, server_holds: Callable[[int], bool] | None = None) -> None:
        self._C: dict[int, np.ndarray] = {}
        self._newest: int | None = None
        # The first keyframe id of every map segment, in order (the last: the current one's)
        self._segment_starts: list[int] = [0]
        self.server_holds = server_holds  # None: the server holds every keyframe
        self._ids: list[int] | None = None  # corrected ids, sorted (None: to sort again)

    def receive(
        self, T_map_cam_team: dict[int, np.ndarray], T_odom_cam: dict[int, np.ndarray]
    ) -> int:
        """Take the team map's poses of some keyframes (robot_k/map), against the odometry's
        poses of the same keyframes now; ids the robot does not hold are ignored. Returns how
        many were taken."""
        taken = [k for k in T_map_cam_team if k in T_odom_cam]
        for k in taken:
            C = np.asarray(T_map_cam_team[k], float) @ invert(T_odom_cam[k])
            C.setflags(write=False)
            self._C[k] = C
            self._ids = None
        if taken:
            self._newest = max(*taken, self._newest or 0)  # (ids are >= 1)
        return len(taken)

    def start_segment(self, first_kf_id: int) -> None:
        """The odometry starts a new map segment with this keyframe id."""
        if int(first_kf_id) > self._segment_starts[-1]:  # (keyframe ids only grow)
            self._segment_starts.append(int(first_kf_id))

    def forget(self, kf_id: int) -> None:
        """A keyframe the odometry culled."""
        if self._C.pop(kf_id, None) is not None:
            self._ids = None
        if kf_id == self._newest:  # the newest corrected is the newest of those left
            self._newest = max(self._C, default=None)

    @property
    def corrected(self) -> bool:
        """Whether any keyframe has a correction."""
        return bool(self._C)

    @property
    def T_map_odom(self) -> np.ndarray:
        """The newest corrected keyframe's correction: where the robot is now (identity before
        the first, and in a new map segment before its first)."""
        return self.correction(NEWEST).copy()

    def correction(self, kf_id: int) -> np.ndarray:
        """``C_k`` of a keyframe (see the module)."""
        if kf_id in self._C:
            return self._C[kf_id]
        newest = self._newest
        start = self._segment_starts[-1]
        if newest is not None and kf_id > newest and not newest < start <= kf_id:
            return self._C[newest]
        if self._C and self.server_holds is not None and not self.server_holds(kf_id):
            near = self._nearest_corrected(kf_id)
            if near is not None:
                return self._C[near]
        return _I

    def _nearest_corrected(self, kf_id: int) -> int | None:
        """The corrected keyframe nearest to ``kf_id`` by id in its own map segment (another
        segment's corrections place another odometry frame)."""
        if self._ids is None:
            self._ids = sorted(self._C)
        ids, starts = self._ids, self._segment_starts
        s = bisect.bisect_right(starts, kf_id) - 1
        lo = bisect.bisect_left(ids, starts[s]) if s >= 0 else 0
        hi = bisect.bisect_left(ids, starts[s + 1]) if s + 1 < len(starts) else len(ids)
        if lo >= hi:
            return None
        i = bisect.bisect_left(ids, kf_id, lo, hi)
        near = [ids[j] for j in (i - 1, i) if lo <= j < hi]
        return min(near, key=lambda k: (abs(k - kf_id), k))

    def keyframe_poses(self, T_odom_cam: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """The keyframes' poses in robot_k/map: each odometry pose with its correction."""
        return {k: self.correction(k) @ T for k, T in T_odom_cam.items()}

    def points(self, xyz_odom: np.ndarray, ref_kf_ids: np.ndarray) -> np.ndarray:
        """Points (N, 3) of the odometry's map moved with their reference keyframes' corrections
        (``ref_kf_ids`` (N,), message ids)."""
        xyz_odom = np.asarray(xyz_odom, float).reshape(-1, 3)
        ids, inverse = np.unique(np.asarray(ref_kf_ids, np.int64).reshape(-1), return_inverse=True)
        C = np.stack([self.correction(int(k)) for k in ids]) if len(ids) else np.zeros((0, 4, 4))
        C = C[inverse]
        return np.einsum("nij,nj->ni", C[:, :3, :3], xyz_odom) + C[:, :3, 3]
