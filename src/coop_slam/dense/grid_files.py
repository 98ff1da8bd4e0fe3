"""The occupancy grid as map_server's files: a PGM image (occupied black, free white, unknown
grey; its top row is the grid's last, largest y) and a YAML naming it, its resolution and the
origin of its lower-left pixel, so ``rosrun map_server map_server grid.yaml`` serves it."""

from __future__ import annotations

import os

import numpy as np

from .occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyGrid

_PIXEL = {OCCUPIED: 0, FREE: 254, UNKNOWN: 205}  # map_server's trinary convention


def grid_image(grid: OccupancyGrid) -> np.ndarray:
    """The grid as a uint8 image, top row = largest y (as an image viewer shows a map)."""
    image = np.full(grid.cells.shape, _PIXEL[UNKNOWN], np.uint8)
    image[grid.cells == OCCUPIED] = _PIXEL[OCCUPIED]
    image[grid.cells == FREE] = _PIXEL[FREE]
    return image[::-1]


def write_grid(grid: OccupancyGrid, directory: str, name: str = "grid") -> tuple[str, str]:
    """``name.pgm`` and ``name.yaml`` in ``directory``; returns their paths."""
    image = grid_image(grid)
    pgm = os.path.join(directory, f"{name}.pgm")
    with open(pgm, "wb") as f:
        f.write(f"P5\n{image.shape[1]} {image.shape[0]}\n255\n".encode())
        f.write(image.tobytes())
    yaml_path = os.path.join(directory, f"{name}.yaml")
    with open(yaml_path, "w") as f:
        f.write(
            f"image: {name}.pgm\n"
            f"resolution: {grid.cell_m:.6f}\n"
            f"origin: [{grid.origin_xy_m[0]:.6f}, {grid.origin_xy_m[1]:.6f}, 0.0]\n"
            "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
        )
    return pgm, yaml_path
