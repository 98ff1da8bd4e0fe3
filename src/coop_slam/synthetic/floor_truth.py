"""What the synthetic world is, in the terms a dense map is scored in: the cells of a floor band
its surfaces cross (occupied), the cells inside its buildings and off its obstacles (free), and the
distance of points to its surfaces -- all in a frame ``T_frame_world`` away from the world's."""

from __future__ import annotations

import cv2
import numpy as np

from ..dense.occupancy import OccupancyGrid
from .world import World

_SHIFT = 4  # cv2.line fixed-point bits


def _grid_px(grid: OccupancyGrid, xy: np.ndarray) -> np.ndarray:
    """Fixed-point (col, row) pixel coordinates of points (N, 2) in the grid's frame [m]."""
    px = (np.asarray(xy) - np.asarray(grid.origin_xy_m)) / grid.cell_m - 0.5
    return np.rint(px * (1 << _SHIFT)).astype(np.int32)


def band_truth(
    world: World, grid: OccupancyGrid, T_frame_world: np.ndarray, band_m: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """(occupied, free) boolean rasters of ``grid``'s shape: cells a surface crosses between the
    band's heights above the floor (world z = 0), and cells inside a building, off every obstacle
    and not occupied. The frame must be level with the world's (a rotation about z)."""
    lo, hi = band_m
    occupied = np.zeros(grid.cells.shape, np.uint8)
    R, t = T_frame_world[:3, :3], T_frame_world[:3, 3]
    for s in world.surfaces:
        corners = s.origin_world + np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float) @ np.stack(
            [s.edge_u_world, s.edge_v_world]
        )
        z0, z1 = corners[:, 2].min(), corners[:, 2].max()
        if z1 < lo or z0 > hi or s.kind in ("floor", "ceiling"):
            continue
        xy = (corners @ R.T + t)[:, :2]
        px = _grid_px(grid, xy)
        if z1 - z0 < 1e-6:  # horizontal: a box top inside the band
            cv2.fillPoly(occupied, [px], 1, shift=_SHIFT)
        else:
            for a, b in ((0, 1), (1, 2), (2, 3), (3, 0)):
                cv2.line(occupied, tuple(px[a]), tuple(px[b]), 1, 1, cv2.LINE_8, _SHIFT)
    occupied = occupied.astype(bool)
    rows, cols = grid.cells.shape
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    centres = (
        np.asarray(grid.origin_xy_m) + (np.stack([jj, ii], -1).reshape(-1, 2) + 0.5) * grid.cell_m
    )
    centres_world = (np.column_stack([centres, np.zeros(len(centres))]) - t) @ R
    free = world.is_free(centres_world[:, :2]).reshape(rows, cols) & ~occupied
    return occupied, free


def surface_distances(
    world: World, points_frame: np.ndarray, T_frame_world: np.ndarray
) -> np.ndarray:
    """Distance [m] of each point (N, 3) in the frame to the nearest of the world's surfaces (the
    exact point-to-rectangle distance)."""
    R, t = T_frame_world[:3, :3], T_frame_world[:3, 3]
    pts = (np.asarray(points_frame, float) - t) @ R  # in the world frame
    best = np.full(len(pts), np.inf)
    for s in world.surfaces:
        u, v = s.edge_u_world, s.edge_v_world
        d = pts - s.origin_world
        # The surfaces are rectangles: u and v are orthogonal.
        su = np.clip(d @ u / (u @ u), 0.0, 1.0)
        sv = np.clip(d @ v / (v @ v), 0.0, 1.0)
        nearest = s.origin_world + su[:, None] * u + sv[:, None] * v
        best = np.minimum(best, np.linalg.norm(pts - nearest, axis=1))
    return best
