"""Monocular maps' scales on the server, kept in one place.

A monocular map's lengths are in units of its own (:mod:`.map_scale`). Everything that changes
them goes through :class:`ScaleKeeper`: a merge by a similarity rescales the side without metric
scale into the other's units (:meth:`ScaleKeeper.prepare_merge`), links to metric maps re-measure
a merged monocular map's scale (:meth:`ScaleKeeper.observe_link`, applied by
:meth:`ScaleKeeper.apply_due`), sightings of a metric robot's marker give an unmerged one metres
(:meth:`ScaleKeeper.marker_sighting`, :mod:`.marker_scale`). Each is the one operation
:meth:`ScaleKeeper.rescale`: the stored keyframes, the pose graph and the group transforms of the
maps move together. Merges and constraints already made are events: they keep the lengths they
were found in.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import numpy as np

from ..geometry import invert
from ..ids import MapId
from ..wire.record import KeyframeRecord
from .groups import MergeGroups
from .keyframe_store import KeyframeStore, track
from .map_scale import MapScaleConfig, MapScales, rescale_record, scale_translation
from .marker_scale import MarkerScale, MarkerScaleConfig
from .plausibility import interpolate_track
from .pose_graph import TeamPoseGraph
from .results import Verified
from .stitching import graph_call

log = logging.getLogger(__name__)


class ScaleKeeper:
    """``map_name(map_id)`` names a map for the log."""

    def __init__(
        self,
        map_scale: MapScaleConfig,
        marker_scale: MarkerScaleConfig,
        store: KeyframeStore,
        graph: TeamPoseGraph,
        groups: MergeGroups,
        map_name: Callable[[MapId], str],
    ):
        self.scales = MapScales(map_scale, groups)
        self.marker = MarkerScale(marker_scale)
        self.marker_enabled = marker_scale.enabled
        self.store, self.graph, self.groups, self.map_name = store, graph, groups, map_name
        self._due: dict[MapId, float] = {}  # map -> factor its links asked for

    # --- what a map's scale is --------------------------------------------------------------------
    def note(self, rec: KeyframeRecord) -> KeyframeRecord:
        """An arriving keyframe, in the server's units for its map."""
        self.scales.note(rec)
        return self.scales.to_stored(rec)

    def is_mono(self, map_id: MapId) -> bool:
        return self.scales.is_mono(map_id)

    def is_metric(self, map_id: MapId) -> bool:
        """Whether the map is in metres in the team map: it has depth, or it is merged with a map
        that has (a monocular map before that: its own units)."""
        return self.scales.is_metric(map_id)

    def scale(self, map_id: MapId) -> float:
        """``s_stored_own``: the map's own lengths times this are its team map lengths."""
        return self.scales.scale(map_id)

    # --- the one operation ------------------------------------------------------------------------
    def rescale(self, maps, factor: float, about_maps: bool = False) -> None:
        """Multiply the maps' lengths by ``factor`` everywhere the server holds them: the stored
        keyframes, the pose graph (see TeamPoseGraph.rescale_robots for ``about_maps``) and the
        group transforms (rescaled with their whole group only)."""
        maps = set(maps)
        self.scales.rescaled(maps, factor)
        for key in [k for k in self.store.keys() if k[0] in maps]:
            self.store.update(rescale_record(self.store.record(key), factor))
        graph_call(self.graph.rescale_robots, maps, factor, about_maps)
        if not about_maps:
            for m in maps:
                self.groups.set_T_root_map(m, scale_translation(self.groups.T_root_map(m), factor))
        log.info(
            "map lengths of robot(s) %s rescaled by %.4f (%s)",
            sorted(maps),
            factor,
            "each about its map" if about_maps else "their group frame",
        )

    # --- what changes it --------------------------------------------------------------------------
    def prepare_merge(self, v: Verified) -> Verified:
        """A merge by a similarity: the side without metric scale (or the second of two such) is
        rescaled into the other's units, and the match becomes the rigid part in them (its scale
        1 there)."""
        res = v.result
        if res.scale == 1.0:
            return v
        ma, mb = v.key_a[0], v.key_b[0]
        side, factor = self.scales.merge_side(ma, mb, res.scale)
        T_a_b, sigma_trans = res.T_a_b, res.sigma_trans_m
        if side == "b":
            self.rescale(self.groups.members(mb), factor)
        elif side == "a":
            self.rescale(self.groups.members(ma), factor)
            T_a_b, sigma_trans = scale_translation(T_a_b, factor), sigma_trans * factor
        log.info(
            "merge of robots %d and %d by a similarity (scale %.4f): robot(s) %s rescaled by %.4f",
            ma,
            mb,
            res.scale,
            self.groups.members(mb if side == "b" else ma) if side else [],
            factor,
        )
        if side is not None:
            res = dataclasses.replace(res, scale=1.0)
        res = dataclasses.replace(res, T_a_b=T_a_b, sigma_trans_m=sigma_trans)
        return dataclasses.replace(v, result=res)

    def observe_link(self, v: Verified) -> None:
        """A similarity link of a merged monocular map re-measures its scale (see .map_scale);
        a rescale it asks for waits for :meth:`apply_due`."""
        if v.result.scale == 1.0:
            return
        due = self.scales.observe_link(v.key_a, v.key_b, v.result.scale)
        if due is not None:
            map_id, factor = due
            self._due[map_id] = self._due.get(map_id, 1.0) * factor

    def apply_due(self) -> bool:
        """The rescales links asked for (each map about its own frame); whether any."""
        for map_id, factor in self._due.items():
            self.rescale([map_id], factor, about_maps=True)
        applied = bool(self._due)
        self._due.clear()
        return applied

    def marker_sighting(
        self,
        observer: MapId,
        observed: MapId,
        stamp_s: float,
        T_camA_bodyB: np.ndarray,
        T_bodyB_camB: np.ndarray,
    ) -> bool:
        """A monocular observer not yet metric learns its scale from sightings of a metric
        robot's marker (see .marker_scale); its map is then rescaled to metres. Whether it was."""
        ma, mb = observer, observed
        if not self.marker_enabled:
            return False
        if not self.is_mono(ma) or self.is_metric(ma) or not self.is_metric(mb):
            return False
        T_map_camA, T_map_camB = self._pose_at(ma, stamp_s), self._pose_at(mb, stamp_s)
        if T_map_camA is None or T_map_camB is None:
            return False
        b_m = (T_map_camB @ invert(T_bodyB_camB))[:3, 3]
        got = self.marker.observe(ma, mb, T_map_camA, T_camA_bodyB[:3, 3], b_m)
        if got is None:
            return False
        scale, rms = got
        members = self.groups.members(ma)
        self.rescale(members, scale)
        for m in members:
            self.scales.mark_metric(m)
        self.marker.forget(ma)
        log.info(
            "%s: metric scale %.4f m per map unit from sightings of %s's marker (fit %.3f m)",
            self.map_name(ma),
            scale,
            self.map_name(mb),
            rms,
        )
        return True

    def _pose_at(self, map_id: MapId, stamp_s: float) -> np.ndarray | None:
        """A map's camera pose at a stamp: position on its keyframe track, rotation of the
        nearest keyframe; None where its keyframes do not pin it down."""
        recs = self.store.map_records(map_id)
        if not recs:
            return None
        stamps, positions = track(recs)
        position = interpolate_track(stamps, positions, stamp_s)
        if position is None:
            return None
        nearest = min(recs, key=lambda r: abs(r.stamp_s - stamp_s))
        T = np.array(nearest.T_map_cam, dtype=float, copy=True)
        T[:3, 3] = position
        return T
