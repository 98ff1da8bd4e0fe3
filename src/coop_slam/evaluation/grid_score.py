"""How well an occupancy grid matches the truth, where the truth is known (synthetic worlds).

At 5 cm cells a wall lying on a cell border falls, with millimetres of depth noise, into the
cells on both sides of it, and the truth cannot say which one it "is" in; so occupied cells are
matched with a tolerance of one cell (an estimated occupied cell within one cell of a true one is
right, a true one within one cell of an estimated one is found), and the cells next to a true
obstacle are left out of the free-space score. The scores are over what the team mapped:

* ``iou_occupied``: TP / (TP + FP + FN), where FN counts only true obstacle cells next to space the
  team saw free (the far side of a box nobody walked round is not held against the map);
* ``iou_free``: IoU of the estimated free cells and the true free cells among the mapped ones;
* ``coverage_free``: the share of all true free cells mapped free (how much was explored).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..dense.occupancy import FREE, OCCUPIED, OccupancyGrid

_NEIGHBOURS = np.ones((3, 3), np.uint8)


@dataclass
class GridScores:
    iou_occupied: float | None
    iou_free: float | None
    coverage_free: float | None


def _grown(mask: np.ndarray) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), _NEIGHBOURS).astype(bool)


def _ratio(num: int, den: int) -> float | None:
    return float(num) / den if den else None


def grid_scores(
    grid: OccupancyGrid, truth_occupied: np.ndarray, truth_free: np.ndarray
) -> GridScores:
    """Scores of ``grid`` against boolean truth rasters of its shape (see the module)."""
    est_occ, est_free = grid.cells == OCCUPIED, grid.cells == FREE
    near_truth = _grown(truth_occupied)
    tp = int((est_occ & near_truth).sum())
    fp = int((est_occ & ~near_truth).sum())
    fn = int((truth_occupied & _grown(est_free) & ~_grown(est_occ)).sum())
    scored = ~near_truth & (est_occ | est_free)  # mapped, and not next to an obstacle
    a, b = est_free & scored, truth_free & scored
    return GridScores(
        _ratio(tp, tp + fp + fn),
        _ratio(int((a & b).sum()), int((a | b).sum())),
        _ratio(int((est_free & truth_free).sum()), int(truth_free.sum())),
    )
