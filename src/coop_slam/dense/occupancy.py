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
from .dense_cloud import place

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
class PlacedViews:
    """Keyframes' points placed in one frame: camera centres (K, 3), points (N, 3) float32 and
    each point's keyframe (N,) (an index into the centres)."""

    centres: np.ndarray
    points: np.ndarray
    keyframe_of: np.ndarray

    @classmethod
    def of(cls, centres, points_per_view: list[np.ndarray]) -> PlacedViews:
        """From each view's camera centre (3,) and its points, placed already."""
        if not len(points_per_view):
            return cls(np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0, np.int64))
        keyframe_of = [np.full(len(p), k, np.int64) for k, p in enumerate(points_per_view)]
        return cls(
            np.asarray(centres, np.float64).reshape(-1, 3),
            np.concatenate(points_per_view).astype(np.float32, copy=False),
            np.concatenate(keyframe_of),
        )

    def moved(self, T_new_frame: np.ndarray) -> PlacedViews:
        """The same views in another frame."""
        T = np.asarray(T_new_frame, np.float64)
        R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
        return PlacedViews(
            self.centres @ T[:3, :3].T + T[:3, 3], self.points @ R.T + t, self.keyframe_of
        )


def place_views(
    views: Iterable[tuple[np.ndarray, np.ndarray]], T_floor_frame: np.ndarray | None = None
) -> PlacedViews:
    """(T_frame_cam, points_cam) pairs placed in the floor's frame (``T_floor_frame``: from the
    poses' frame; None: the same)."""
    T_floor = np.eye(4) if T_floor_frame is None else np.asarray(T_floor_frame, np.float64)
    poses = [T_floor @ np.asarray(T, np.float64) for T, _ in views]
    points = [
        place([(T, np.asarray(p, np.float32).reshape(-1, 3))]) for T, (_, p) in zip(poses, views)
    ]
    return PlacedViews.of([T[:3, 3] for T in poses], points)


def occupancy_grid(
    views: Iterable[tuple[np.ndarray, np.ndarray]],
    config: OccupancyConfig | None = None,
    T_floor_frame: np.ndarray | None = None,
) -> OccupancyGrid:
    """The grid from (T_frame_cam, points_cam) pairs (see the module's docstring)."""
    return grid_of_placed(place_views(views, T_floor_frame), config)


def grid_of_placed(
    placed: PlacedViews, config: OccupancyConfig | None = None, floor_z_m: float = 0.0
) -> OccupancyGrid:
    """The grid of views already placed in a frame whose z axis is up and whose floor is at
    ``floor_z_m``. All keyframes at once: the per-keyframe work is array indexing, but for one
    polygon fill each."""
    config = config or OccupancyConfig()
    cell = config.cell_m
    if len(placed.centres) == 0:
        return OccupancyGrid(np.full((1, 1), UNKNOWN, np.int8), cell, (0.0, 0.0))
    centres, points, kf = placed.centres, placed.points, placed.keyframe_of
    rel = points - centres[kf].astype(np.float32)
    near = np.einsum("ij,ij->i", rel, rel) <= config.max_range_m**2
    z = points[:, 2] - np.float32(floor_z_m)
    band = near & (z >= config.band_min_m) & (z <= config.band_max_m)
    low = near & (z < config.band_min_m)
    seen_xy = points[band | low, :2]
    lo_xy = np.minimum(centres[:, :2].min(axis=0), seen_xy.min(axis=0, initial=np.inf))
    hi_xy = np.maximum(centres[:, :2].max(axis=0), seen_xy.max(axis=0, initial=-np.inf))
    origin = np.floor(lo_xy / cell) * cell - 2 * cell
    cols, rows = (np.ceil((hi_xy - origin) / cell).astype(int) + 3).tolist()
    grid = OccupancyGrid(
        np.zeros((rows, cols), np.int8), cell, (float(origin[0]), float(origin[1]))
    )
    # Occupied: the keyframes that have a point of the band in a cell, each counted once.
    ij = grid.cell_of(points[band, :2])
    seen = np.unique(kf[band] * (rows * cols) + ij[:, 0] * cols + ij[:, 1])
    occupied = np.bincount(seen % (rows * cols), minlength=rows * cols).reshape(rows, cols)
    free = np.zeros((rows, cols), np.int32)
    for fan in _fans(rel, kf, band, low, len(centres), centres[:, :2], config):
        px = (fan - origin) / cell  # (x, y) in cells
        lo = np.maximum(np.floor(px.min(axis=0)).astype(int), 0)
        hi = np.minimum(np.ceil(px.max(axis=0)).astype(int) + 1, [cols, rows])
        canvas = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
        # Cell (i, j) covers [j, j+1) x [i, i+1) in cells; fillPoly's pixel centres are at
        # integers, so vertices shift by half a cell.
        vertices = np.rint((px - lo - 0.5) * (1 << _SHIFT)).astype(np.int32)
        cv2.fillPoly(canvas, [vertices], 1, lineType=cv2.LINE_8, shift=_SHIFT)
        free[lo[1] : hi[1], lo[0] : hi[0]] += canvas
    is_occupied = (occupied >= config.min_keyframes) & (
        occupied >= config.occupied_ratio * np.maximum(occupied, free)
    )
    grid.cells[:] = np.where(is_occupied, OCCUPIED, np.where(free > 0, FREE, UNKNOWN))
    return grid


def _fans(rel, kf, band, low, n_views: int, centres_xy, config: OccupancyConfig):
    """The vertices (B, 2) [m] of the free-space fan of each keyframe that sees something: per
    bin of each keyframe, the range to its nearest band point, else to its farthest floor
    point."""
    n_bins = int(round(360.0 / config.angle_step_deg))
    r_band = np.full(n_views * n_bins, np.inf)
    r_floor = np.zeros(n_views * n_bins)
    for mask, reduce_at, out in ((band, np.minimum.at, r_band), (low, np.maximum.at, r_floor)):
        d = rel[mask, :2].astype(np.float64)
        b = np.floor((np.arctan2(d[:, 1], d[:, 0]) + math.pi) / (2 * math.pi) * n_bins)
        reduce_at(out, kf[mask] * n_bins + b.astype(np.int64) % n_bins, np.hypot(d[:, 0], d[:, 1]))
    r = np.where(np.isfinite(r_band), np.maximum(r_band - config.cell_m / 2, 0.0), r_floor)
    r = r.reshape(n_views, n_bins)
    a = (np.arange(n_bins) + 0.5) / n_bins * 2 * math.pi - math.pi
    unit = np.stack([np.cos(a), np.sin(a)], axis=1)
    for k in np.nonzero(np.any(r > config.cell_m / 2, axis=1))[0]:
        yield centres_xy[k] + r[k, :, None] * unit
