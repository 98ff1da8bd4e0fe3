"""The server's pure core: takes every robot's keyframes and stitches their maps into one team map.

The data flow, one module per stage:

1. :mod:`.keyframe_store` -- the keyframes and their BoW vectors in the team database;
2. :mod:`.rendezvous` -- robots seeing one scene at once (co-observation, marker sightings,
   operator requests) and :mod:`.place_recognition` -- a robot seeing a place another mapped,
   both checked by :mod:`.plausibility` (look-alike places);
3. :mod:`.stitching` -- verified matches become merges between groups (:mod:`.groups`,
   :mod:`.merge_order`) or constraints inside one;
4. :mod:`.pose_graph` and :mod:`.global_ba` -- the team map's optimization;
5. :mod:`.view` -- the stitched cloud and paths as shown.

Monocular robots' maps have a scale of their own (:mod:`.map_scale`): matches involving one are
similarities, a merge rescales the side without metric scale, and the server converts the robot's
keyframes to its group's units as they arrive, so stages 3-5 stay rigid; every change of a map's
scale goes through :mod:`.scale_keeper`.

:class:`TeamServer` runs them in that order for each keyframe. A group's frame is the map of its
smallest robot; the group holding the team's smallest robot id is the one published as ``world``.
"""

from __future__ import annotations

import functools
import logging
import time
from typing import Callable

import numpy as np

from ..bow import Vocabulary
from ..errors import CoopSlamError
from ..geometry import invert
from ..ids import MapId, RobotId
from ..wire.record import ACTION_NEW, ACTION_REMOVE, ACTION_UPDATE, KeyframeRecord
from .config import ServerConfig
from .dense_map import DenseKeyframe, DenseMap, DenseMapBuilder, body_tracks
from .global_ba import GlobalBaError, GlobalBaResult, count_observations, global_bundle_adjustment
from .groups import MergeGroups
from .keyframe_store import KeyframeStore, StoredKeyframe, stored_keyframe
from .map_scale import rescale_record, scale_translation
from .overlap_links import OverlapLinks
from .place_recognition import PlaceRecognition
from .pose_feedback import PoseFeedback
from .pose_graph import PoseGraphError, TeamPoseGraph
from .rendezvous import Rendezvous
from .results import TYPE_PLACE_RECOGNITION, MergeResult, Verified, map_pair
from .scale_keeper import ScaleKeeper
from .segments import MapSegments
from .stitching import Stitcher, graph_call
from .view import build_cloud, cloud_snapshot, team_paths_and_edges, view_offsets

log = logging.getLogger(__name__)


class ServerError(CoopSlamError):
    """Keyframes or requests the server cannot take (unknown robot, inconsistent ids, ...)."""


class TeamServer:
    """Consumes validated keyframes from all robots and stitches their maps."""

    def __init__(self, config: ServerConfig, vocabulary: Vocabulary):
        config.validate()
        self.config = config
        self.vocabulary = vocabulary
        self.known_robots = set(config.robots)
        self.world_robot = min(self.known_robots)  # its group is published as ``world``
        self.groups = MergeGroups(config.robots)
        # Stages below work on map ids: a robot's first map segment has its id, a later one (a
        # client that lost tracking for good, or restarted) a map of its own (see .segments).
        self.segments = MapSegments(config.robots)
        self.store = KeyframeStore(vocabulary, config.place_recognition.database)
        self.graph = TeamPoseGraph(config.pose_graph)
        self._kf_count: dict[int, int] = {}  # keyframes received per robot
        # Monocular maps' scales: every change to them goes through the keeper.
        self.scale_keeper = ScaleKeeper(
            config.map_scale,
            config.marker_scale,
            self.store,
            self.graph,
            self.groups,
            self.map_name,
        )
        self.scales = self.scale_keeper.scales  # (read only: which maps are monocular, metric)
        self.dense = DenseMapBuilder(config.dense)  # decoded depth images, kept between builds
        self.links = OverlapLinks(config.links, self.store, lambda key: self.T_group_cam(*key))
        self.stitcher = Stitcher(
            config.loops,
            self.store,
            self.groups,
            self.graph,
            lambda robot: self._kf_count.get(robot, 0),
            self.links,
            self.scale_keeper.prepare_merge,
            self.scale_keeper.observe_link,
            self.map_name,
        )
        self.rendezvous = Rendezvous(config.rendezvous, self.store, self.groups, self.scales)
        self.place_recognition = PlaceRecognition(
            config.place_recognition,
            config.loops,
            config.rendezvous,
            self.store,
            self.groups,
            self.scales,
        )
        self.pose_feedback = PoseFeedback(config.pose_feedback)
        self.global_ba_runs: list[GlobalBaResult] = []
        self.keyframe_ms: list[float] = []  # server time per incoming keyframe
        self.optimize_ms: list[float] = []
        self.map_moved = False  # the last call optimized the team map (robots' maps moved)
        # The global BA after a merge: at once (False), or left for the caller to run when it has
        # time (True; :attr:`global_ba_due` names the group), off the keyframe messages' path.
        self.defer_global_ba = False
        self.global_ba_due: int | None = None
        self._since_optimize = self._updates_since = 0

    # --- what the stages found --------------------------------------------------------------------
    @property
    def merges(self) -> list[MergeResult]:
        return self.stitcher.merges

    @property
    def constraints(self):
        """Loop closures and links inside groups (:class:`.results.ConstraintResult`)."""
        return self.stitcher.constraints

    @property
    def rejected_constraints(self) -> int:
        return self.stitcher.rejected_constraints

    @property
    def verifications(self) -> int:
        return (
            self.place_recognition.verifications
            + self.rendezvous.verifications
            + self.links.verifications
        )

    # --- keyframes --------------------------------------------------------------------------------
    def add_keyframe(self, rec: KeyframeRecord, pulled: bool = False) -> list[MergeResult]:
        """Store (or update / remove) one keyframe; returns the merges it caused. ``pulled``: a
        keyframe the server asked for, whose place the pull planner found consistent already
        (its place recognition verifies at once)."""
        t0 = time.perf_counter()
        self.map_moved = False
        rec.validate(self.known_robots)
        rec = self._stored(rec)
        key = rec.key
        merges: list[MergeResult] = []
        if rec.action != ACTION_REMOVE:
            rec = self.scale_keeper.note(rec)
        if rec.action == ACTION_REMOVE:
            if self.store.remove(key):
                graph_call(self.graph.remove_keyframe, *key)
        elif rec.action == ACTION_UPDATE and key in self.store:
            # Local BA moved the pose / points; descriptors (and so the BoW vector) are unchanged.
            self.store.update(rec)
            graph_call(self.graph.update_keyframe, *key, rec.T_map_cam)
        elif rec.action in (ACTION_NEW, ACTION_UPDATE):
            if key in self.store:
                raise ServerError(
                    f"keyframe {rec.keyframe_id} of {self.map_name(rec.map_id)} was "
                    "already received as new"
                )
            bow, covisible = self.store.add(rec)
            graph_call(
                self.graph.add_keyframe,
                rec.map_id,
                rec.keyframe_id,
                rec.T_map_cam,
                self.groups.T_root_map(rec.map_id),
                [int(k) for k in rec.covisible_ids],
            )
            self._kf_count[rec.map_id] = self._kf_count.get(rec.map_id, 0) + 1
            merges = self._stitch(rec, bow, covisible, pulled)
        if self.scale_keeper.apply_due():
            self.stitcher.need_full = True
        if rec.action == ACTION_UPDATE:
            self._updates_since += 1
        else:
            self._since_optimize += 1
        if merges:
            self._settle(merges)
        elif self.stitcher.need_full:
            self.optimize(full=True)
        elif (
            self._since_optimize >= self.config.optimize_every
            or self._updates_since >= self.config.optimize_every_updates
        ):
            self.optimize(full=False)
        self.keyframe_ms.append(1e3 * (time.perf_counter() - t0))
        return merges

    def _stored(self, rec: KeyframeRecord) -> StoredKeyframe:
        """The keyframe as the keyframe of its robot's map segment's map."""
        mid, new = self.segments.map_id(rec.robot_id, rec.map_segment)
        if new and mid != rec.robot_id:
            self.groups.add_map(mid)
            log.warning(
                "robot %d started map segment %d (tracking lost for good, or a restarted "
                "client): a new map (map id %d) until it merges with the team map again",
                rec.robot_id,
                rec.map_segment,
                mid,
            )
        return stored_keyframe(rec, mid)

    def robot_of(self, map_id: MapId) -> RobotId:
        """The robot a map id belongs to (see .segments)."""
        return self.segments.robot_of(map_id)

    def stored_record(self, robot_id: RobotId, segment: int, keyframe_id: int):
        """The keyframe as stored, in the robot's own units as it sent it (None when the server
        does not hold it): what a delta update, or a keyframe sharing its descriptors, leaves out
        comes from here. (The server stores a monocular map's keyframes in the units of the group
        it merged into; a completed message is scaled into them again when it is taken.)"""
        mid = self.segments.find(robot_id, segment)
        key = (mid, int(keyframe_id))
        if mid is None or key not in self.store:
            return None
        rec, s = self.store.record(key), self.scales.scale(mid)
        return rec if s == 1.0 else rescale_record(rec, 1.0 / s)

    def map_name(self, map_id: MapId) -> str:
        """A map id as the user knows it: ``robot 2``, ``robot 2 (map segment 1)``."""
        robot = self.robot_of(map_id)
        if map_id == robot:
            return f"robot {robot}"
        return f"robot {robot} (map segment {self.segments.segment_of(map_id)})"

    def current_map(self, robot_id: RobotId) -> MapId:
        """The map id of a robot's newest map segment (the map its client works in now)."""
        return self.segments.current(robot_id)

    def robot_keyframes(self, robot_id: RobotId) -> dict[int, tuple[float, np.ndarray]]:
        """keyframe id -> (stamp_s, T_group_cam) of a robot's keyframes in the group of its
        newest segment (older segments not merged back into that group are left out)."""
        cur = self.current_map(robot_id)
        out = {}
        for mid in self.segments.maps_of(robot_id):
            if self.groups.same_group(mid, cur):
                for kf, T in self.optimized_keyframes(mid).items():
                    out[kf] = (self.store.stamp((mid, kf)), T)
        return dict(sorted(out.items()))

    def robot_groups(self) -> list[list[int]]:
        """The groups by robot (a robot with a segment outside its newest map's group appears in
        two)."""
        return sorted({tuple(sorted({self.robot_of(m) for m in g})) for g in self.groups.groups()})

    def _stitch(self, rec: KeyframeRecord, bow, covisible, pulled: bool) -> list[MergeResult]:
        """A new keyframe through the stitching stages: rendezvous (automatic, then open
        requests), then place recognition; the first that merges ends it."""
        rdv = self.rendezvous
        if self.config.rendezvous.auto:
            merges = self._merge_verified([rdv.co_observation(rec)])
            if merges:
                return merges
        if rdv.has_open_requests:  # robots seen together: a rendezvous
            merges = self._merge_verified([rdv.retry_requests(rec)])
            if merges:
                return merges
        merges = []
        if self.config.place_recognition.enabled:
            merges = self._place_recognition(rec, bow, covisible, pulled)
        if not merges:
            self._overlap_link(rec)
        return merges

    def _overlap_link(self, rec: KeyframeRecord) -> None:
        """A merged robot's new keyframe against the keyframe of another robot of its group that
        sees most of its scene (see :mod:`.overlap_links`), when the robot is due a constraint."""
        others = set(self.groups.members(rec.map_id)) - {rec.map_id}
        if (
            not others
            or not self.config.links.enabled
            or not self.stitcher.constraint_due(rec.map_id)
        ):
            return
        key_b = rec.key
        candidates = [k for k in self.store.keys() if k[0] in others]
        for key_a in self.links.best_partners(key_b, candidates):
            v = self.links.verify(key_a, key_b, rec.stamp_s)
            if v is not None:
                self.stitcher.add_constraint(v)

    def _place_recognition(
        self, rec: KeyframeRecord, bow, covisible, pulled: bool
    ) -> list[MergeResult]:
        """Matches in other groups become merges (in the order the merge plan gives); consistent
        candidates inside the own group are verified as loop closures / further links."""
        found = self.place_recognition.query(rec, bow, covisible, consistent_already=pulled)
        for v in found.cross:
            v.kind = self.rendezvous.kind_of(v)
        merges = self._merge_verified(found.cross)
        key_b = rec.key
        if (
            merges
            or not found.inner
            or found.budget == 0
            or not self.stitcher.constraint_due(rec.map_id)
        ):
            return merges
        for cand_key in found.inner[: found.budget]:
            res = self.place_recognition.verify(cand_key, key_b)
            if res.accepted and self.stitcher.add_constraint(
                Verified(TYPE_PLACE_RECOGNITION, cand_key, key_b, res, rec.stamp_s)
            ):
                break
        return merges

    def _merge_verified(self, verified: list[Verified | None]) -> list[MergeResult]:
        """Verified cross-group matches through the merge plan; the merges made."""
        pending = {map_pair(v.key_a[0], v.key_b[0]): v for v in verified if v is not None}
        merges = self.stitcher.apply_plan(pending, self.place_recognition.match_counts)
        for m in merges:
            self.place_recognition.merged(m.map_b)
        return merges

    # --- monocular maps' scales (see .scale_keeper) ---------------------------------------------
    def is_metric(self, map_id: MapId) -> bool:
        """Whether the robot's map is in metres in the team map: it has depth, or it is merged
        with a robot that has (a monocular robot before that: its own map's units)."""
        return self.scale_keeper.is_metric(map_id)

    def map_scale(self, map_id: MapId) -> float:
        """``s_stored_own``: the robot's own map lengths times this are its team map lengths (and
        those of its keyframes' poses and map points here); 1 unless it is monocular and merged.
        Its ``T_group_map`` acts on its map so rescaled: a client point p of its map is at
        ``T_group_map @ (scale * p)``."""
        return self.scale_keeper.scale(map_id)

    # --- rendezvous cues --------------------------------------------------------------------------
    def request_rendezvous(
        self,
        robot_a: int,
        robot_b: int,
        stamp_s: float | None = None,
        T_camA_bodyB: np.ndarray | None = None,
        T_bodyB_camB: np.ndarray | None = None,
    ) -> tuple[MergeResult | None, str]:
        """Operator trigger or marker sighting: robots a and b are together (at stamp_s, default
        their latest keyframes). A marker pose, when given, is only an initial guess and a weak
        prior; the merge still needs verified feature correspondences. Returns (merge, message)."""
        self.map_moved = False
        for r in (robot_a, robot_b):
            if r not in self.known_robots:
                return (
                    None,
                    f"robot {r} is unknown to the server (known: {sorted(self.known_robots)})",
                )
        if robot_a == robot_b:
            return None, "a rendezvous needs two different robots"
        robot_a, robot_b = self.current_map(robot_a), self.current_map(robot_b)
        if self.groups.same_group(robot_a, robot_b):
            return None, f"robots {robot_a} and {robot_b} are already merged"
        T_init = None
        if T_camA_bodyB is not None and T_bodyB_camB is not None:
            # The sighting is at the marker's image time; keyframes are close to it in time.
            T_init = T_camA_bodyB @ T_bodyB_camB
        v, why = self.rendezvous.request(robot_a, robot_b, stamp_s, T_init)
        merges = self._merge_verified([v])
        if not merges:
            return None, why
        self._settle(merges)
        merge = merges[0]
        return merge, f"merged ({merge.inliers} inliers, {merge.residual_px:.2f} px)"

    def sighting(
        self,
        observer: int,
        observed: int,
        stamp_s: float,
        T_camA_bodyB: np.ndarray | None = None,
        T_bodyB_camB: np.ndarray | None = None,
    ) -> tuple[MergeResult | None, str] | None:
        """A marker sighting of robot ``observed`` by ``observer`` at ``stamp_s`` is a rendezvous
        request (see :meth:`request_rendezvous`), at most once per pair and
        ``rendezvous.sighting_period_s``; None when it is not one."""
        if T_camA_bodyB is not None and T_bodyB_camB is not None:
            ma, mb = self.current_map(observer), self.current_map(observed)
            if self.scale_keeper.marker_sighting(ma, mb, stamp_s, T_camA_bodyB, T_bodyB_camB):
                self.stitcher.need_full = True
        if not self.rendezvous.sighting_due(observer, observed, stamp_s):
            return None
        return self.request_rendezvous(observer, observed, stamp_s, T_camA_bodyB, T_bodyB_camB)

    # --- team optimization ------------------------------------------------------------------------
    def optimize(self, full: bool = True) -> None:
        """Optimize the team pose graph and move every robot's map to its optimized place."""
        self._since_optimize = self._updates_since = 0
        self.stitcher.need_full = False
        self.map_moved = True
        for m in self.graph.robots:
            # A monocular map's scale drifts along its path; its loops and links measure it.
            self.graph.set_scale_drift(m, self.scales.is_mono(m))
        try:
            stats = self.graph.optimize_full() if full else self.graph.optimize_incremental()
        except (PoseGraphError, RuntimeError) as exc:
            log.warning("pose graph optimization failed: %s", exc)
            return
        self.optimize_ms.append(stats.time_ms)
        for robot in self.groups.robots:
            if robot in self.graph.robots and self.graph.keyframe_ids(robot):
                self.groups.set_T_root_map(robot, self.graph.T_group_map(robot))

    def _settle(self, merges: list[MergeResult]) -> None:
        """After merges: a full optimization (and global BA when cheap); each merge then reports
        its transforms as the optimization placed the maps, which rests on all its pairs."""
        self.optimize(full=True)
        if self.config.global_ba.after_merge:
            if self.defer_global_ba:
                self.global_ba_due = merges[-1].map_a
            else:
                self._global_ba_if_cheap(merges[-1].map_a)
        for m in merges:
            key_a, key_b = (m.map_a, m.keyframe_a), (m.map_b, m.keyframe_b)
            if key_a in self.store and key_b in self.store:
                # In a's map lengths, as registered: a monocular map's graph lengths there are
                # its local scale times them.
                T = invert(self.T_group_cam(*key_a)) @ self.T_group_cam(*key_b)
                m.T_camA_camB = scale_translation(T, 1.0 / self.local_scale(*key_a))
            m.T_mapA_mapB = invert(self.T_group_map(m.map_a)) @ self.T_group_map(m.map_b)

    def global_ba_is_cheap(self, map_id: MapId) -> bool:
        """Whether the automatic global BA after a merge runs for this robot's group: metric,
        and at most ``global_ba.auto_max_observations`` observations."""
        if not self.is_metric(map_id):
            return False  # monocular maps only: nothing would hold the group's scale
        members = set(self.groups.members(map_id))
        n = count_observations(r for r in self.store.records() if r.map_id in members)
        if n > self.config.global_ba.auto_max_observations:
            log.info(
                "global BA after the merge skipped: %d observations > %d (call the service)",
                n,
                self.config.global_ba.auto_max_observations,
            )
            return False
        return True

    def _global_ba_if_cheap(self, map_id: MapId) -> None:
        if not self.global_ba_is_cheap(map_id):
            return
        try:
            self.global_bundle_adjustment(map_id)
        except GlobalBaError as exc:
            log.warning("global BA after the merge: %s", exc)

    def global_bundle_adjustment(self, robot_id: RobotId | None = None) -> GlobalBaResult:
        """Bundle-adjust every keyframe and map point of robot_id's group (default: the world
        group) with the points matched by merges and loops linked; the refined poses become the
        pose graph's estimate and odometry (see TeamPoseGraph.adopt_estimates)."""
        robot_id = self.world_robot if robot_id is None else int(robot_id)
        if robot_id not in self.known_robots:
            raise GlobalBaError(
                f"robot {robot_id} is unknown to the server "
                f"(known: {sorted(self.known_robots)})"
            )
        robot_id = self.current_map(robot_id)
        members = set(self.groups.members(robot_id))
        if not self.is_metric(robot_id):
            raise GlobalBaError(
                f"robot {robot_id}'s group {sorted(members)} has monocular maps only: global BA "
                "needs a robot with depth to hold the scale"
            )
        keys = sorted(k for k in self.store.keys() if k[0] in members)
        if not keys:
            raise GlobalBaError(f"robot {robot_id}'s group {sorted(members)} has no keyframes yet")
        records = [self.store.record(k) for k in keys]
        poses = {k: self.T_group_cam(*k) for k in keys}
        links = [
            (a, b) for a, b in self.stitcher.point_links if a[0] in members and b[0] in members
        ]
        root = min(members)
        fixed = {min(k for k in keys if k[0] == root)} if any(k[0] == root for k in keys) else None
        result = global_bundle_adjustment(records, poses, links, fixed, self.config.global_ba)
        graph_call(self.graph.adopt_estimates, result.poses, result.components)
        self.optimize(full=True)
        self.global_ba_runs.append(result)
        log.info(
            "global BA of group %s: %d keyframes (%d apart by shared points), %d points, "
            "%d observations (%d outliers), reprojection RMS %.2f -> %.2f px, %.0f ms",
            sorted(members),
            result.keyframes,
            len(set(result.components.values())),
            result.points,
            result.observations,
            result.outliers,
            result.rms_before,
            result.rms_after,
            result.time_ms,
        )
        return result

    # --- the team map -----------------------------------------------------------------------------
    def T_group_map(self, map_id: MapId) -> np.ndarray:
        """A robot's map in its group's frame."""
        return self.groups.T_root_map(map_id)

    def in_world(self, map_id: MapId) -> bool:
        """Whether the robot's group is the world group (holds the team's smallest robot id)."""
        return self.groups.root(map_id) == self.world_robot

    def T_group_cam(self, map_id: MapId, keyframe_id: int) -> np.ndarray:
        """A keyframe's pose in its group frame: the optimized one when the pose graph has it,
        else the client's pose moved by the robot's map transform."""
        try:
            return self.graph.T_group_cam(map_id, keyframe_id)
        except PoseGraphError:
            rec = self.store.record((map_id, keyframe_id))
            return self.groups.T_root_map(map_id) @ rec.T_map_cam

    def local_scale(self, map_id: MapId, keyframe_id: int) -> float:
        """A keyframe's lengths in the team map against its map's (see
        :meth:`.pose_graph.TeamPoseGraph.local_scale`; 1 outside the pose graph)."""
        try:
            return self.graph.local_scale(map_id, keyframe_id)
        except PoseGraphError:
            return 1.0

    def optimized_keyframes(self, map_id: MapId) -> dict[int, np.ndarray]:
        """keyframe id -> T_group_cam of every stored keyframe of a robot."""
        return {k: self.T_group_cam(map_id, k) for k in self.store.keyframe_ids(map_id)}

    def corrected_keyframes(self, map_id: MapId, last: int = 20) -> dict[int, np.ndarray]:
        """Optimized poses (in the robot's own map frame, its lengths times :meth:`map_scale`)
        of its ``last`` newest keyframes."""
        if map_id not in self.graph.robots:
            return {}
        T_map_group = np.linalg.inv(self.groups.T_root_map(map_id))
        poses = self.graph.keyframe_poses(map_id)
        return {k: T_map_group @ poses[k] for k in sorted(poses)[-last:]}

    def client_frame(self, map_id: int) -> np.ndarray | None:
        """``T_map_group``: the group frame in the map's own frame as its client has it now, read
        off at its newest keyframe (stored client pose against the optimized one); None when the
        pose graph holds none of its keyframes."""
        if map_id not in self.graph.robots:
            return None
        poses_group = self.graph.keyframe_poses(map_id)
        stored = [k for k in poses_group if (map_id, k) in self.store]
        if not stored:
            return None
        newest = max(stored)
        return self.store.record((map_id, newest)).T_map_cam @ invert(poses_group[newest])

    def pose_corrections(self, map_id: int) -> dict[int, np.ndarray]:
        """The optimized poses to send the robot of a map now, in its map frame and its own
        units (a monocular map's: lengths divided by :meth:`map_scale`): those that moved since
        last sent, and the newest (see :mod:`.pose_feedback`).

        The frame is read off at the newest keyframe's client pose as stored now, not from the
        group transform of the last optimization: a re-anchored map frame moves every keyframe
        rigidly, which is no correction, and a client applying it would slide its whole map
        (and its current pose) at each optimization."""
        T_map_group = self.client_frame(map_id)
        if T_map_group is None:
            return {}
        poses_group = self.graph.keyframe_poses(map_id)
        client = {
            k: self.store.record((map_id, k)).T_map_cam
            for k in poses_group
            if (map_id, k) in self.store
        }
        ids = list(poses_group)
        moved = np.einsum("ij,njk->nik", T_map_group, np.stack([poses_group[k] for k in ids]))
        selected = self.pose_feedback.select(map_id, dict(zip(ids, moved)), client)
        scale = self.map_scale(map_id)
        return {k: scale_translation(T, 1.0 / scale) for k, T in selected.items()}

    def _offsets(self) -> dict[int, np.ndarray]:
        return view_offsets(self.groups, self.world_robot, self.config.unmerged_offset_m)

    def team_view(self) -> tuple[dict[int, np.ndarray], list[tuple[str, np.ndarray, np.ndarray]]]:
        """Optimized keyframe positions per robot and merge / constraint edges, as drawn (see
        :func:`.view.team_paths_and_edges`)."""
        return team_paths_and_edges(
            self.store.keys(), self._offsets(), self.T_group_cam, self.merges, self.constraints
        )

    def team_cloud(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stitched cloud as drawn (see :func:`.view.build_cloud`)."""
        return self.team_cloud_job()()

    def team_cloud_job(self) -> Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The stitched cloud of the team map as it is now, to build later or in another thread
        (the slow part: fusing duplicates), while the server takes further keyframes."""
        snapshot = cloud_snapshot(
            self.store.records(), self._offsets(), self.T_group_cam, self.local_scale
        )
        return functools.partial(
            build_cloud, snapshot, self.config.fuse_radius_m, self.config.cloud_voxel_m
        )

    def dense_map_job(self, bodies: dict | None = None) -> Callable[[], DenseMap] | None:
        """The dense team map as it is now, to build later or in another thread (see
        :mod:`.dense_map`); None when it is off or no keyframe brought a depth image.
        ``bodies``: robot id -> (T_base_cam, body size (x, y, z) [m]) of the robots described,
        whose bodies their teammates' keyframes leave out."""
        if not self.config.dense.enabled:
            return None
        offsets, tracks = self._offsets(), {}
        snapshot = []
        for rec in self.store.records():
            if not self.is_metric(rec.map_id):  # metres only
                continue
            T_view_cam = offsets[rec.map_id] @ self.T_group_cam(rec.map_id, rec.keyframe_id)
            group = self.groups.root(rec.map_id)
            if rec.robot_id in (bodies or {}):
                tracks.setdefault((rec.robot_id, group), []).append((rec.stamp_s, T_view_cam))
            if len(rec.depth_image):  # a monocular map's keyframes bring none
                snapshot.append(
                    DenseKeyframe(
                        rec.key,
                        rec.robot_id,
                        rec.stamp_s,
                        rec.depth_image,
                        rec.camera,
                        T_view_cam,
                        group,
                        self.in_world(rec.map_id),
                    )
                )
        if not snapshot:
            return None
        maps = {r: self.current_map(r) for r in self.known_robots}
        T_world_maps = {
            r: self.groups.T_root_map(m)
            for r, m in maps.items()
            if self.config.dense.robot_grids and self.in_world(m)
        }
        tracks = body_tracks(tracks, bodies or {})
        return functools.partial(self.dense.build, snapshot, tracks, T_world_maps)
