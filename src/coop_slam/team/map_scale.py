"""Scales of monocular maps on the server: a monocular robot's map has an arbitrary scale of its own
(its client fixes it once, at initialization), so everything about it that is a length needs one
more number before it can sit next to a metric map.

- **Registration**: a keyframe pair with a monocular keyframe is registered as a similarity
  (:func:`register_pair`, :func:`~coop_slam.registration.relative_pose.estimate_similarity`); a pair
  of depth keyframes stays rigid.
- **One scale per robot**, ``s_stored_own`` (:class:`MapScales`): what the server multiplies the
  robot's own map lengths by when a keyframe arrives (:func:`rescale_record`: pose translation and
  map points), so the keyframe store, the pose graph, global BA and the view hold one length unit
  per group and stay rigid. It is 1 until the robot's group merges: a merge's similarity then
  rescales the side without metric scale into the other (the monocular robot into a metric group's
  metres, or the second of two monocular groups into the first's units), once, and the server
  rescales the keyframes it already holds (see :meth:`coop_slam.team.server.TeamServer`).
- **Metric**: a group is metric when it holds a robot with depth (RGB-D, stereo); a monocular
  robot's map is metric once merged into one, shown in its own units before.
- **Refinement**: links of a merged monocular robot to metric robots measure its scale again (their
  similarities' scales, ideally 1); once ``refine_min_links`` agree that it is off by more than
  ``refine_min_change`` (their median), the robot's map is rescaled by that median. A scale per map
  segment is not kept: the server keeps one map transform per robot, so a monocular robot that
  starts a new map segment keeps the scale of its first (the client's new segment is initialized at
  median depth 1 again; its links will refine it).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from ..config import require
from ..errors import CoopSlamError
from ..geometry import invert
from ..ids import KeyframeKey
from ..registration.relative_pose import RegistrationConfig, RelativePoseResult, estimate_similarity
from ..registration.sim3 import sim3_matrix
from ..wire.record import KeyframeRecord
from .groups import MergeGroups
from .keyframe_store import KeyframeStore, is_mono

log = logging.getLogger(__name__)


class MapScaleError(CoopSlamError):
    """An invalid scale (not finite or not positive) for a robot's map."""


@dataclass
class MapScaleConfig:
    """Monocular maps' scales: re-measuring a merged monocular map's scale from its links."""

    # A merged monocular robot's scale is re-estimated from the similarities of its links to metric
    # robots: the median of the last refine_window of them, once at least refine_min_links ...
    refine_min_links: int = 5
    refine_window: int = 15
    # ... when it differs from the current scale by more than this (relative); 0 = never refine.
    refine_min_change: float = 0.005

    def validate(self) -> None:
        require(self.refine_min_links >= 1, "map_scale.refine_min_links must be >= 1")
        require(
            self.refine_window >= self.refine_min_links,
            "map_scale.refine_window must be >= refine_min_links",
        )
        require(self.refine_min_change >= 0, "map_scale.refine_min_change must be >= 0")


def scale_translation(T: np.ndarray, factor: float) -> np.ndarray:
    """A rigid transform with its translation multiplied by ``factor`` (its frames' lengths
    rescaled about their origin)."""
    out = np.array(T, dtype=float, copy=True)
    out[:3, 3] *= factor
    return out


def rescale_record(rec: KeyframeRecord, factor: float) -> KeyframeRecord:
    """A copy of a keyframe whose map lengths (pose translation, map points) are multiplied by
    ``factor``; depths are measured, never rescaled (a monocular keyframe has none)."""
    if not (np.isfinite(factor) and factor > 0):
        raise MapScaleError(f"a map's scale factor must be finite and > 0, got {factor}")
    return dataclasses.replace(
        rec,
        T_map_cam=scale_translation(rec.T_map_cam, factor),
        map_points=(np.asarray(rec.map_points, float) * factor).astype(np.float32),
    )


def chain_similarity(
    T_mapA_camA: np.ndarray, T_a_b: np.ndarray, s_a_b: float, T_mapB_camB: np.ndarray
) -> tuple[np.ndarray, float]:
    """``(T_mapA_mapB, s_mapA_mapB)``: the similarity of B's map in A's from keyframe poses in
    their own maps and a verified similarity of the cameras (as ``p_a = s R p_b + t``)."""
    return split_similarity(T_mapA_camA @ sim3_matrix(T_a_b, s_a_b) @ invert(T_mapB_camB))


def split_similarity(S: np.ndarray) -> tuple[np.ndarray, float]:
    """``(T, scale)`` of a 4x4 ``[[scale R, t], [0, 1]]`` (inverse of ``sim3_matrix``)."""
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    T = np.array(S, dtype=float, copy=True)
    T[:3, :3] /= scale
    return T, scale


def register_pair(
    store: KeyframeStore,
    key_a: KeyframeKey,
    key_b: KeyframeKey,
    cfg: RegistrationConfig,
    rigid,
    **rigid_kw,
) -> RelativePoseResult:
    """Register two stored keyframes: a similarity when either is monocular (its map points in its
    map's units, a rigid estimate would carry the wrong length), else ``rigid(view_a, view_b, cfg,
    **rigid_kw)`` (PnP or 3D-3D). A marker's initial guess is only for the rigid path: it is
    metric, and the similarity path needs none."""
    view_a, view_b = store.view(key_a), store.view(key_b)
    if store.is_mono(key_a) or store.is_mono(key_b):
        return estimate_similarity(view_a, view_b, cfg)
    return rigid(view_a, view_b, cfg, **rigid_kw)


class MapScales:
    """Which robots are monocular, each robot's ``s_stored_own`` and which groups are metric (see
    the module docstring). ``groups`` is the server's merge groups (read only)."""

    def __init__(self, config: MapScaleConfig, groups: MergeGroups):
        config.validate()
        self.config = config
        self.groups = groups
        self._mono: set[int] = set()
        self._metric: set[int] = set()  # monocular maps given metres by other means (markers)
        self._scale: dict[int, float] = {}
        self._link_scales: dict[int, list[float]] = {}  # robot -> log scale corrections

    def note(self, rec: KeyframeRecord) -> None:
        """A keyframe arrived: its camera says whether its robot's map has a metric scale."""
        if is_mono(rec):
            self._mono.add(rec.map_id)

    def is_mono(self, robot_id: int) -> bool:
        return robot_id in self._mono

    def is_metric(self, robot_id: int) -> bool:
        """Whether the robot's map is in metres in the team map: it, or a robot of its group, has
        a camera with depth. Robots not heard from yet count as metric."""
        return any(r not in self._mono or r in self._metric for r in self.groups.members(robot_id))

    def mark_metric(self, robot_id: int) -> None:
        """The robot's map was put in metres without a merge (a marker's scale)."""
        self._metric.add(robot_id)

    def scale(self, robot_id: int) -> float:
        """``s_stored_own``: the robot's own map lengths times this are the server's."""
        return self._scale.get(robot_id, 1.0)

    def to_stored(self, rec: KeyframeRecord) -> KeyframeRecord:
        """An incoming keyframe in the server's units for its robot."""
        s = self.scale(rec.map_id)
        return rec if s == 1.0 else rescale_record(rec, s)

    def rescaled(self, robots, factor: float) -> None:
        """The server multiplied the robots' map lengths by ``factor``."""
        if not (np.isfinite(factor) and factor > 0):
            raise MapScaleError(f"a map's scale factor must be finite and > 0, got {factor}")
        for r in robots:
            self._scale[r] = self.scale(r) * factor
            self._link_scales.pop(r, None)  # measured against the old scale

    def merge_side(self, robot_a: int, robot_b: int, s_a_b: float) -> tuple[str | None, float]:
        """Which side of a merge by a similarity ``s_a_b`` (b's lengths into a's) is rescaled, and
        by what: ``("b", s_a_b)`` when a's group is metric or neither is (the second into the
        first's units), ``("a", 1 / s_a_b)`` when only b's is, ``(None, 1)`` when both are."""
        metric_a, metric_b = self.is_metric(robot_a), self.is_metric(robot_b)
        if metric_a and metric_b:
            return None, 1.0
        if metric_b:
            return "a", 1.0 / s_a_b
        return "b", s_a_b

    def observe_link(
        self, key_a: KeyframeKey, key_b: KeyframeKey, s_a_b: float
    ) -> tuple[int, float] | None:
        """A verified similarity between keyframes of one metric group; returns ``(robot,
        factor)`` when the monocular robot of the pair is due a rescale (see the module doc)."""
        cfg = self.config
        ra, rb = key_a[0], key_b[0]
        if cfg.refine_min_change == 0 or not (np.isfinite(s_a_b) and s_a_b > 0):
            return None
        # Only a link of a monocular robot to a depth robot measures its scale against metres.
        if self.is_mono(rb) and not self.is_mono(ra):
            robot, log_c = rb, np.log(s_a_b)
        elif self.is_mono(ra) and not self.is_mono(rb):
            robot, log_c = ra, -np.log(s_a_b)
        else:
            return None
        if not self.is_metric(robot):
            return None
        seen = self._link_scales.setdefault(robot, [])
        seen.append(float(log_c))
        del seen[: -cfg.refine_window]
        if len(seen) < cfg.refine_min_links:
            return None
        median = float(np.median(seen))
        if abs(median) <= np.log1p(cfg.refine_min_change):
            return None
        return robot, float(np.exp(median))
