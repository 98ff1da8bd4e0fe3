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

    def box_at(
        self, t_s: float, max_gap_s: float, margin_m: float, reach_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(T_view_base, box low, box high corner in base_link) of the body at ``t_s``: between
        the two keyframes around it (position interpolated, the nearer one's orientation); after
        its last keyframe, there, and up to ``reach_m`` ahead (a robot that stops makes no
        keyframes, and it stops up to a keyframe's distance past its last one); None before its
        first by more than ``max_gap_s``. The box is grown by ``margin_m``."""
        stamps = self.stamps_s
        if t_s < stamps[0] - max_gap_s:
            return None
        k = int(np.searchsorted(stamps, t_s))
        before, after = max(k - 1, 0), min(k, len(stamps) - 1)
        gap_before, gap_after = t_s - stamps[before], stamps[after] - t_s
        T = self.T_view_base[before if abs(gap_before) <= abs(gap_after) else after].copy()
        span = stamps[after] - stamps[before]
        if before != after and span > 0 and 0 <= gap_before <= span:
            w = gap_before / span
            T[:3, 3] = (1 - w) * self.T_view_base[before][:3, 3]
            T[:3, 3] += w * self.T_view_base[after][:3, 3]
        sx, sy, sz = self.size_m
        lo = np.array([-sx / 2 - margin_m, -sy / 2 - margin_m, -margin_m])
        hi = np.array([sx / 2 + margin_m, sy / 2 + margin_m, sz + margin_m])
        if t_s > stamps[-1]:
            hi[0] += reach_m
        return T, lo, hi


def outside_bodies(points_view: np.ndarray, boxes: list[tuple]) -> np.ndarray:
    """Mask (N,) of the points outside every box (T_view_base, low, high corner in base_link)."""
    keep = np.ones(len(points_view), bool)
    for T, lo, hi in boxes:
        local = (points_view - T[:3, 3]) @ T[:3, :3]
        keep &= ~np.all((local >= lo) & (local <= hi), axis=1)
    return keep
