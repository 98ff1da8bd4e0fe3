"""The 2D occupancy grid of the floor band (the heights a ground robot's body sweeps) from
keyframes' points placed by their current poses -- what a planner such as move_base reads.

Per keyframe: a point in the band marks its cell occupied; the floor it sees, and the space up
to the nearest point in the band, is free. Free space is the keyframe's *fan*: around the
camera, in bins of ``angle_step_deg``, the range up to the nearest point in the band (half a cell
short of it), or, where no point in the band is seen, up to the farthest floor point. Points above
the band say nothing (a table top does not tell what is under it). A cell is occupied when at
least ``min_keyframes`` keyframes saw it occupied and they are at least ``occupied_ratio`` of
those that saw it at all; free when some keyframe saw it free and it is not occupied; else
unknown. Counting keyframes, not points, keeps a wall seen once from close up (hundreds of points)
from outvoting many keyframes that saw through the cell.

The grid is rebuilt from the keyframes on every call, in a frame whose z axis is up and whose
z = 0 is the floor (``T_floor_frame`` maps the keyframes' frame into it)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from ..config import require

OCCUPIED = 100  # nav_msgs/OccupancyGrid values
FREE = 0
UNKNOWN = -1
_SHIFT = 4  # cv2.fillPoly fixed-point bits: vertices to 1/16 cell


@dataclass
class OccupancyConfig:
    cell_m: float = 0.05  # grid resolution [m]
    band_min_m: float = 0.05  # lowest height above the floor a robot's body sweeps [m]
    band_max_m: float = 0.5  # highest [m]
    max_range_m: float = 4.0  # points farther from their camera are left out [m]
    angle_step_deg: float = 0.5  # bins of a keyframe's free-space fan [deg]
    min_keyframes: int = 1  # keyframes that must see a cell occupied
    occupied_ratio: float = 0.35  # ... as a share of the keyframes that saw the cell at all

    def validate(self) -> None:
        require(self.cell_m > 0, "occupancy.cell_m must be > 0 m")
        require(self.band_max_m > self.band_min_m, "occupancy.band_max_m must exceed band_min_m")
        require(self.max_range_m > 0, "occupancy.max_range_m must be > 0 m")
        require(0 < self.angle_step_deg <= 10, "occupancy.angle_step_deg must be in (0, 10]")
        require(self.min_keyframes >= 1, "occupancy.min_keyframes must be >= 1")
        require(0 < self.occupied_ratio <= 1, "occupancy.occupied_ratio must be in (0, 1]")


@dataclass
class OccupancyGrid:
    """Cells row-major from the origin (row = y, column = x, as nav_msgs/OccupancyGrid), values
    OCCUPIED / FREE / UNKNOWN; ``origin_xy_m`` is the outer corner of cell (0, 0)."""

    cells: np.ndarray  # (rows, cols) int8
    cell_m: float
    origin_xy_m: tuple[float, float]

    @property
    def shape(self) -> tuple[int, int]:
        return self.cells.shape

    def cell_of(self, xy_m: np.ndarray) -> np.ndarray:
        """(N, 2) (row, col) of points (N, 2) [m] (may lie outside the grid)."""
        xy = np.asarray(xy_m, np.float64)
        ij = np.floor((xy - np.asarray(self.origin_xy_m)) / self.cell_m).astype(np.int64)
        return ij[:, ::-1]


@dataclass
class _View:
    centre_xy: np.ndarray  # (2,)
    band_xy: np.ndarray  # (N, 2) points in the band
    floor_xy: np.ndarray  # (M, 2) points below it


def _views(views, config: OccupancyConfig, T_floor_frame) -> list[_View]:
    out = []
    for T_frame_cam, pts_cam in views:
        T = np.asarray(T_frame_cam, np.float64)
        if T_floor_frame is not None:
            T = np.asarray(T_floor_frame, np.float64) @ T
        pts = np.asarray(pts_cam, np.float32)
        keep = np.linalg.norm(pts, axis=1) <= config.max_range_m
        pts = pts[keep] @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)
        z = pts[:, 2]
        band = (z >= config.band_min_m) & (z <= config.band_max_m)
        out.append(_View(T[:2, 3].copy(), pts[band, :2], pts[z < config.band_min_m, :2]))
    return out


def _fan(view: _View, config: OccupancyConfig) -> np.ndarray | None:
    """The vertices (K, 2) [m] of the keyframe's free-space fan, or None if it sees nothing."""
    n_bins = int(round(360.0 / config.angle_step_deg))
    r_band = np.full(n_bins, np.inf)
    r_floor = np.zeros(n_bins)
    for xy, reduce_at, out in (
        (view.band_xy, np.minimum.at, r_band),
        (view.floor_xy, np.maximum.at, r_floor),
    ):
        if len(xy) == 0:
            continue
        d = xy - view.centre_xy
        b = (np.floor((np.arctan2(d[:, 1], d[:, 0]) + math.pi) / (2 * math.pi) * n_bins)).astype(
            np.int64
        ) % n_bins
        reduce_at(out, b, np.hypot(d[:, 0], d[:, 1]))
    r = np.where(np.isfinite(r_band), np.maximum(r_band - config.cell_m / 2, 0.0), r_floor)
    if not np.any(r > config.cell_m / 2):
        return None
    a = (np.arange(n_bins) + 0.5) / n_bins * 2 * math.pi - math.pi
    return view.centre_xy + r[:, None] * np.stack([np.cos(a), np.sin(a)], axis=1)


def occupancy_grid(
    views: Iterable[tuple[np.ndarray, np.ndarray]],
    config: OccupancyConfig | None = None,
    T_floor_frame: np.ndarray | None = None,
) -> OccupancyGrid:
    """The grid from (T_frame_cam, points_cam) pairs (see the module's docstring)."""
    config = config or OccupancyConfig()
    placed = _views(views, config, T_floor_frame)
    every = [v.centre_xy[None] for v in placed] + [v.band_xy for v in placed]
    every += [v.floor_xy for v in placed]
    every_xy = np.concatenate(every) if every else np.zeros((0, 2))
    cell = config.cell_m
    if len(every_xy) == 0:
        return OccupancyGrid(np.full((1, 1), UNKNOWN, np.int8), cell, (0.0, 0.0))
    origin = np.floor(every_xy.min(axis=0) / cell) * cell - 2 * cell
    cols, rows = (np.ceil((every_xy.max(axis=0) - origin) / cell).astype(int) + 3).tolist()
    grid = OccupancyGrid(
        np.zeros((rows, cols), np.int8), cell, (float(origin[0]), float(origin[1]))
    )
    occupied = np.zeros(rows * cols, np.int32)
    free = np.zeros((rows, cols), np.int32)
    for view in placed:
        if len(view.band_xy):
            ij = grid.cell_of(view.band_xy)
            occupied[np.unique(ij[:, 0] * cols + ij[:, 1])] += 1
        fan = _fan(view, config)
        if fan is None:
            continue
        px = (fan - origin) / cell  # (x, y) in cells
        lo = np.maximum(np.floor(px.min(axis=0)).astype(int), 0)
        hi = np.minimum(np.ceil(px.max(axis=0)).astype(int) + 1, [cols, rows])
        canvas = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
        # Cell (i, j) covers [j, j+1) x [i, i+1) in cells; fillPoly's pixel centres are at
        # integers, so vertices shift by half a cell.
        vertices = np.rint((px - lo - 0.5) * (1 << _SHIFT)).astype(np.int32)
        cv2.fillPoly(canvas, [vertices], 1, lineType=cv2.LINE_8, shift=_SHIFT)
        free[lo[1] : hi[1], lo[0] : hi[0]] += canvas
    occupied = occupied.reshape(rows, cols)
    is_occupied = (occupied >= config.min_keyframes) & (
        occupied >= config.occupied_ratio * np.maximum(occupied, free)
    )
    grid.cells[:] = np.where(is_occupied, OCCUPIED, np.where(free > 0, FREE, UNKNOWN))
    return grid
