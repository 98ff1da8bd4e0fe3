"""The team map's files: the stitched sparse cloud and the dense cloud as PLY, the occupancy
grid as map_server files and a picture, and -- where the world is known (synthetic runs) -- how
well they match it: ``grid_iou`` / ``grid_free_iou`` / ``grid_free_coverage``
(:mod:`.grid_score`, in the floor band of the grid's default configuration) and
``dense_surface_rmse_m`` (RMS distance of the dense cloud's points to the true surfaces)."""

from __future__ import annotations

import os
from dataclasses import dataclass

import cv2
import numpy as np

from ..dense.grid_files import grid_image, write_grid
from ..dense.occupancy import OccupancyConfig, OccupancyGrid
from ..synthetic.floor_truth import band_truth, surface_distances
from ..synthetic.world import World, build_world
from .grid_score import grid_scores
from .plots import write_ply
from .run_data import RunData

DENSE_KEYS = ("grid_iou", "grid_free_iou", "grid_free_coverage", "dense_surface_rmse_m")
_PICTURE_PX_PER_CELL = 4


@dataclass
class DenseTruth:
    """The synthetic world and where it lies in the team's ``world`` frame; ``level``: whether
    that frame's z = 0 is the world's floor (ground robots; a hand-held camera's map is not)."""

    world: World
    T_frame_world: np.ndarray
    level: bool = True


def world_of(meta: dict) -> dict | None:
    """What a run's source metadata says of its synthetic world (None: not synthetic)."""
    if "world" not in meta:
        return None
    layout, hand_held = meta["world"].get("layout"), bool(meta.get("hand_held"))
    return {"layout": layout, "seed": int(meta.get("seed", 0)), "hand_held": hand_held}


def dense_truth(world: dict | None, T_frame_world: np.ndarray) -> DenseTruth | None:
    """The truth of a run's world (:func:`world_of`) placed in the team's frame."""
    if not world:
        return None
    built = build_world(world["layout"], world["seed"])
    return DenseTruth(built, np.asarray(T_frame_world, float), not world["hand_held"])


def _picture(grid: OccupancyGrid, truth_occupied: np.ndarray | None, path: str) -> None:
    """The grid as seen in RViz (occupied dark, free light, unknown grey), true obstacles red."""
    grey = grid_image(grid)
    image = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    if truth_occupied is not None:
        image[truth_occupied[::-1]] = (40, 40, 220)
        image[(grey == 0) & truth_occupied[::-1]] = (0, 0, 0)
    k = max(1, min(_PICTURE_PX_PER_CELL, 2400 // max(image.shape)))
    cv2.imwrite(path, cv2.resize(image, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST))


def _dense_picture(points: np.ndarray, rgb: np.ndarray, z_slice: tuple, path: str) -> None:
    """Top view of the dense map coloured by height, beside a 10 cm slice coloured by robot (a
    wall two robots placed apart is drawn twice there)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, cut) = plt.subplots(1, 2, figsize=(14, 6.5))
    order = np.argsort(points[:, 2])
    top.scatter(points[order, 0], points[order, 1], c=points[order, 2], s=1, cmap="viridis")
    top.set_title("dense team map, top view (colour: height)")
    band = (points[:, 2] >= z_slice[0]) & (points[:, 2] < z_slice[1])
    cut.scatter(points[band, 0], points[band, 1], c=rgb[band] / 255.0, s=1)
    cut.set_title(f"slice z {z_slice[0]:.2f}-{z_slice[1]:.2f} m (colour: robot)")
    for ax in (top, cut):
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def map_results(out_dir: str, run: RunData, truth: DenseTruth | None) -> tuple[dict, str | None]:
    """Write ``team_map.ply``, ``team_map_dense.ply`` (with ``dense.png``), ``grid.pgm`` +
    ``grid.yaml`` and ``grid.png`` of the run's last team map into ``out_dir``: (the report's
    dense keys, None where not known; the sparse PLY's path or None)."""
    ply = os.path.join(out_dir, "team_map.ply") if run.team_cloud is not None else None
    if ply:
        write_ply(ply, *run.team_cloud)
    return _dense_results(out_dir, run, truth), ply


def _dense_results(out_dir: str, run: RunData, truth: DenseTruth | None) -> dict:
    out = {k: None for k in DENSE_KEYS}
    if run.dense_cloud is not None:
        points, rgb = run.dense_cloud
        write_ply(os.path.join(out_dir, "team_map_dense.ply"), points, rgb)
        if len(points):
            # Ground robots: the floor band; else where most of the map is.
            level = truth is not None and truth.level
            z = run.grid_z_m + 0.25 if level else float(np.median(points[:, 2]))
            _dense_picture(points, rgb, (z - 0.05, z + 0.05), os.path.join(out_dir, "dense.png"))
        if truth is not None and len(points):
            d = surface_distances(truth.world, points, truth.T_frame_world)
            out["dense_surface_rmse_m"] = float(np.sqrt(np.mean(d**2)))
    if run.grid is None:
        return out
    write_grid(run.grid, out_dir)
    truth_occupied = None
    if truth is not None and truth.level:
        band = OccupancyConfig()
        truth_occupied, truth_free = band_truth(
            truth.world, run.grid, truth.T_frame_world, (band.band_min_m, band.band_max_m)
        )
        scores = grid_scores(run.grid, truth_occupied, truth_free)
        out.update(
            grid_iou=scores.iou_occupied,
            grid_free_iou=scores.iou_free,
            grid_free_coverage=scores.coverage_free,
        )
    _picture(run.grid, truth_occupied, os.path.join(out_dir, "grid.png"))
    return out
