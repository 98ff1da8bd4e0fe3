"""Teammates are not obstacles: a robot's camera sees the other robots of its team, and their
bodies, kept in the dense map, would stand in the occupancy grid where they once were -- walls in
the middle of a corridor, for good. The server knows every robot's path (its keyframes' poses)
and body (its description's box around base_link), so each keyframe's points inside another
robot's body at that keyframe's time are left out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class BodyTrack:
    """A robot's body along its path: keyframe stamps (N,) sorted, its base_link poses (N, 4, 4)
    in the view frame, and its box (x, y, z) around base_link, on the floor [m]."""

    robot_id: int
    group: int
    stamps_s: np.ndarray
    T_view_base: np.ndarray
    size_m: tuple[float, float, float]

    def pose_at(self, t_s: float, max_gap_s: float) -> np.ndarray | None:
        """base_link at ``t_s``: between the two keyframes around it (position interpolated, the
        nearer one's orientation); after its last keyframe, there (a robot that stopped makes no
        keyframes, and stays where it stopped); None before its first by more than
        ``max_gap_s``."""
        if t_s < self.stamps_s[0] - max_gap_s:
            return None
        k = int(np.searchsorted(self.stamps_s, t_s))
        before, after = max(k - 1, 0), min(k, len(self.stamps_s) - 1)
        gap_before, gap_after = t_s - self.stamps_s[before], self.stamps_s[after] - t_s
        T = self.T_view_base[before if abs(gap_before) <= abs(gap_after) else after].copy()
        span = self.stamps_s[after] - self.stamps_s[before]
        if before != after and span > 0 and 0 <= gap_before <= span:
            w = gap_before / span
            T[:3, 3] = (1 - w) * self.T_view_base[before][:3, 3] + w * self.T_view_base[after][
                :3, 3
            ]
        return T


def outside_bodies(
    points_view: np.ndarray, bodies_T_view_base: list[tuple[np.ndarray, tuple]], margin_m: float
) -> np.ndarray:
    """Mask (N,) of the points outside every body (T_view_base, size) grown by ``margin_m``."""
    keep = np.ones(len(points_view), bool)
    for T, (sx, sy, sz) in bodies_T_view_base:
        local = (points_view - T[:3, 3]) @ T[:3, :3]
        inside = (np.abs(local[:, 0]) <= sx / 2 + margin_m) & (
            np.abs(local[:, 1]) <= sy / 2 + margin_m
        )
        inside &= (local[:, 2] >= -margin_m) & (local[:, 2] <= sz + margin_m)
        keep &= ~inside
    return keep
