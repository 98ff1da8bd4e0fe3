"""A monocular map's metric scale from sightings of another robot's marker.

An ArUco marker of known size on a robot's body gives its pose in the observing camera in metres.
When the observer is monocular (a map in its own units) and the observed robot metric, a few
sightings while the observer moves give the observer's scale: at sighting i the observed body is
at ``s * c_i + R_i p_i`` in the observer's map (its camera centre ``c_i`` in own units, rotation
``R_i``, the marker's metric position ``p_i`` in the camera), and at ``b_i`` in the observed
robot's metric map; one rigid transform relates the two maps, so the scale ``s`` is the one that
lets a rigid fit of the ``b_i`` onto those points leave the least residual. The observed robot
may move (its track is known in metres) or stand still (then the observer's motion alone fixes
``s``). Needs no feature match between the robots, so it works when they see each other but not
the same scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import require
from ..registration.umeyama import umeyama_batch


@dataclass
class MarkerScaleConfig:
    """A monocular map's metres from sightings of a metric robot's marker."""

    enabled: bool = True  # learn an unmerged monocular map's metres from marker sightings
    min_sightings: int = 6  # sightings of one pair before a scale is given
    window: int = 40  # the newest sightings of a pair kept
    # The observer's camera must have moved this far [m] (spread of its centres, at the estimated
    # scale): the scale is a ratio of lengths, unobservable from one spot.
    min_baseline_m: float = 0.3
    max_rms_m: float = 0.05  # rigid-fit residual of an accepted scale [m]
    scale_range: list = field(default_factory=lambda: [1e-3, 1e3])  # metres per own unit searched

    def validate(self) -> None:
        require(self.min_sightings >= 3, "marker_scale.min_sightings must be >= 3")
        require(self.window >= self.min_sightings, "marker_scale.window must be >= min_sightings")
        require(self.min_baseline_m > 0, "marker_scale.min_baseline_m must be > 0")
        require(self.max_rms_m > 0, "marker_scale.max_rms_m must be > 0")
        lo, hi = self.scale_range
        require(0 < lo < hi, "marker_scale.scale_range must be 0 < low < high")


def _fit_rms(scales: np.ndarray, c_own, q, b) -> np.ndarray:
    """RMS of the rigid fit of ``b`` onto ``s * c_own + q`` for each scale."""
    dst = scales[:, None, None] * c_own[None] + q[None]
    src = np.broadcast_to(b, dst.shape)
    T, _ = umeyama_batch(src, dst)
    fitted = np.einsum("hij,nj->hni", T[:, :3, :3], b) + T[:, None, :3, 3]
    return np.sqrt(np.mean(np.sum((fitted - dst) ** 2, axis=2), axis=1))


def estimate_scale(
    c_own: np.ndarray, q: np.ndarray, b: np.ndarray, scale_range=(1e-3, 1e3)
) -> tuple[float, float]:
    """(metres per own unit, fit RMS [m]) from observer camera centres ``c_own`` (N, 3, own
    units), marker positions ``q`` (N, 3, metres, in the observer's map axes: R_i p_i) and the
    observed body positions ``b`` (N, 3, metres, its own map)."""
    c_own, q, b = (np.asarray(x, float).reshape(-1, 3) for x in (c_own, q, b))
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    best = 0.0
    for _ in range(4):  # a log grid, refined around its best point
        grid = np.linspace(lo, hi, 61)
        rms = _fit_rms(np.exp(grid), c_own, q, b)
        k = int(np.argmin(rms))
        best = grid[k]
        step = grid[1] - grid[0]
        lo, hi = best - step, best + step
    s = float(np.exp(best))
    return s, float(_fit_rms(np.array([s]), c_own, q, b)[0])


@dataclass
class _Sightings:
    c_own: list = field(default_factory=list)
    q: list = field(default_factory=list)
    b: list = field(default_factory=list)


class MarkerScale:
    """Sightings per (observer, observed) pair; a scale once they fix one."""

    def __init__(self, config: MarkerScaleConfig):
        config.validate()
        self.config = config
        self._pairs: dict[tuple[int, int], _Sightings] = {}

    def forget(self, observer: int) -> None:
        """The observer's map was rescaled: its centres so far are in other units."""
        for key in [k for k in self._pairs if k[0] == observer]:
            del self._pairs[key]

    def observe(
        self,
        observer: int,
        observed: int,
        T_map_camA: np.ndarray,
        p_cam_m: np.ndarray,
        b_m: np.ndarray,
    ) -> tuple[float, float] | None:
        """One sighting: the observer's camera pose (own units), the marker's metric position in
        that camera, the observed body's metric position in its map. Returns (scale, rms) once
        the pair's sightings fix the scale, else None."""
        cfg = self.config
        s = self._pairs.setdefault((observer, observed), _Sightings())
        s.c_own.append(np.asarray(T_map_camA[:3, 3], float))
        s.q.append(np.asarray(T_map_camA[:3, :3], float) @ np.asarray(p_cam_m, float))
        s.b.append(np.asarray(b_m, float))
        for lst in (s.c_own, s.q, s.b):
            del lst[: -cfg.window]
        if len(s.c_own) < cfg.min_sightings:
            return None
        c = np.array(s.c_own)
        scale, rms = estimate_scale(c, np.array(s.q), np.array(s.b), cfg.scale_range)
        spread = scale * float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1))))
        if spread < cfg.min_baseline_m or rms > cfg.max_rms_m:
            return None
        return scale, rms
