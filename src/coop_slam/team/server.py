"""The server's pure core: team keyframe store, shared-vocabulary database, place-recognition
stitching (BoW retrieval -> consistency -> PnP RANSAC -> two-view BA -> acceptance) and merge
groups.

Wrong merges are worse than late ones: a candidate must be temporally consistent and pass the
registration's geometric acceptance tests before two maps are joined.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from ..bow import Vocabulary
from ..bow.database import ConsistencyChecker, ConsistencyConfig, DatabaseConfig, KeyframeDatabase
from ..config import require
from ..errors import CoopSlamError
from ..geometry import invert, transform_error, transform_points
from ..keyframe import ACTION_NEW, ACTION_REMOVE, ACTION_UPDATE, KeyframeRecord
from ..registration.keyframe import KeyframeView, project
from ..registration.relative_pose import (
    RegistrationConfig,
    RelativePoseResult,
    estimate_3d3d,
    estimate_pnp,
)
from .fusion import fuse_points, gather_map_points, robot_colours, voxel_downsample
from .global_ba import (
    GlobalBaConfig,
    GlobalBaError,
    GlobalBaResult,
    count_observations,
    global_bundle_adjustment,
)
from .groups import MergeGroups, chain_map_transform
from .merge_order import plan_merge_steps
from .pose_graph import PoseGraphConfig, PoseGraphError, TeamPoseGraph

log = logging.getLogger(__name__)

TYPE_PLACE_RECOGNITION = "place_recognition"
TYPE_RENDEZVOUS = "rendezvous"


class ServerError(CoopSlamError):
    """Keyframes or requests the server cannot take (unknown robot, inconsistent ids, ...)."""


@dataclass
class PlaceRecognitionConfig:
    enabled: bool = True
    min_consecutive: int = 2  # consecutive consistent queries before a candidate is verified
    max_verifications: int = 2  # candidates geometrically verified per keyframe (bounds the cost)
    # A merge joins two maps on one constraint, so it needs more support than a loop / in-group
    # link (which the pose graph weighs against the rest); the next keyframes usually bring it.
    merge_min_inliers: int = 60
    database: DatabaseConfig = field(default_factory=DatabaseConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)

    def validate(self) -> None:
        require(self.min_consecutive >= 1, "place_recognition.min_consecutive must be >= 1")
        require(self.max_verifications >= 1, "place_recognition.max_verifications must be >= 1")
        require(self.merge_min_inliers >= 1, "place_recognition.merge_min_inliers must be >= 1")
        self.database.validate()
        self.registration.validate()


@dataclass
class RendezvousConfig:
    auto: bool = True  # test the time-aligned latest keyframes of unmerged robots continuously
    window_s: float = 2.0  # keyframes closer in time than this count as simultaneous [s]
    request_window_s: float = 2.0  # keyframes around a sighting / operator request [s]
    # A marker sighting of a not-yet-merged robot becomes a request at most this often per
    # observer/observed pair: each costs up to max_pairs verifications [s].
    sighting_period_s: float = 1.0
    # A merge needs this many verified inliers (as place_recognition.merge_min_inliers): robots
    # facing each other see a little of the same side walls, enough for a weak, biased fit.
    merge_min_inliers: int = 60
    min_bow_score: float = 0.03  # BoW L1 score a pair needs before 3D-3D verification
    max_pairs: int = 4  # keyframe pairs verified per rendezvous request
    # The automatic test has no cue of its own: identical textures seen at the same time in two
    # places pass any two-view check, so it merges only once this many verifications from
    # different keyframes of the joining robot agree on the map transform (within the tolerance).
    auto_confirmations: int = 2
    confirm_trans_m: float = 0.05
    confirm_rot_deg: float = 2.0
    # A sighting / operator request says two robots are together, which rules out look-alike
    # places: for this long after it their co-observations merge on one verification, and a
    # merge between them by any path is a rendezvous [s].
    together_s: float = 5.0
    # Two robots' cameras are never closer than this at one time: the synthetic robots are 0.4 m
    # wide, and two people carrying cameras stand at least about this far apart. A verification,
    # rendezvous or place recognition, of keyframes taken within window_s of each other is a
    # look-alike place if, at the time of a keyframe of either robot in that window, it puts the
    # other robot's camera closer than this, or where the keyframe sees surfaces straight
    # through the other robot. Two buildings with identical posters, driven in step, verify
    # 0.08-0.23 m apart or 0.4-0.6 m ahead in view; the synthetic rendezvous at 1.3 m and more.
    # 0 = off (both tests), as for one camera's recording split into robots (scripts/demo
    # --split), which may well be in one spot at one time [m].
    min_separation_m: float = 0.3
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)

    def validate(self) -> None:
        require(self.window_s > 0, "rendezvous.window_s must be > 0")
        require(self.request_window_s > 0, "rendezvous.request_window_s must be > 0")
        require(self.sighting_period_s >= 0, "rendezvous.sighting_period_s must be >= 0")
        require(self.merge_min_inliers >= 1, "rendezvous.merge_min_inliers must be >= 1")
        require(0 <= self.min_bow_score <= 1, "rendezvous.min_bow_score must be in [0, 1]")
        require(self.max_pairs >= 1, "rendezvous.max_pairs must be >= 1")
        require(self.auto_confirmations >= 1, "rendezvous.auto_confirmations must be >= 1")
        require(self.confirm_trans_m > 0, "rendezvous.confirm_trans_m must be > 0")
        require(self.confirm_rot_deg > 0, "rendezvous.confirm_rot_deg must be > 0")
        require(self.together_s >= 0, "rendezvous.together_s must be >= 0")
        require(self.min_separation_m >= 0, "rendezvous.min_separation_m must be >= 0")
        self.registration.validate()


@dataclass
class LoopClosureConfig:
    """Constraints between keyframes already in one group: a robot's own loop closures and further
    links between robots merged earlier (the place-recognition path, within the team map)."""

    enabled: bool = True
    min_separation_s: float = 5.0  # a robot's own candidate must be at least this much older [s]
    min_interval_kf: int = 2  # keyframes of a robot between two constraints it adds
    # A constraint needs as many verified inliers as a merge: registration accepts from 30, and on
    # RedKitchen keyframe pairs one accepted estimate with 35 inliers was 30 cm / 4.4 deg off --
    # within the gate below, whose slack also widens the constraint's robust kernel.
    min_inliers: int = 60
    # A verified constraint further than this from the current estimate is refused (the robust
    # kernel is the second line of defence): indoor drift between revisits is well below it.
    gate_trans_m: float = 1.0
    gate_rot_deg: float = 15.0
    # Loop and merge factors take the registration's BA marginal std, inflated (pixel noise is not
    # independent in practice) and floored: a well-measured constraint outweighs odometry drift.
    sigma_scale: float = 3.0
    min_sigma_trans_m: float = 0.01
    min_sigma_rot_deg: float = 0.3

    def validate(self) -> None:
        require(self.min_separation_s >= 0, "loops.min_separation_s must be >= 0")
        require(self.min_interval_kf >= 0, "loops.min_interval_kf must be >= 0")
        require(self.min_inliers >= 1, "loops.min_inliers must be >= 1")
        require(self.gate_trans_m > 0, "loops.gate_trans_m must be > 0")
        require(self.gate_rot_deg > 0, "loops.gate_rot_deg must be > 0")
        require(self.sigma_scale > 0, "loops.sigma_scale must be > 0")
        require(self.min_sigma_trans_m > 0, "loops.min_sigma_trans_m must be > 0")
        require(self.min_sigma_rot_deg > 0, "loops.min_sigma_rot_deg must be > 0")


@dataclass
class _OpenRequest:
    robot_a: int
    robot_b: int
    stamp_s: float
    T_init: np.ndarray | None  # camera A -> camera B from the marker, when there is one


@dataclass
class ServerConfig:
    robots: list[int] = field(default_factory=lambda: [1, 2])  # robot ids the server accepts
    place_recognition: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)
    rendezvous: RendezvousConfig = field(default_factory=RendezvousConfig)
    loops: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    global_ba: GlobalBaConfig = field(default_factory=GlobalBaConfig)
    pose_graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    optimize_every: int = 5  # incremental (iSAM2) update every N keyframes; full after each merge
    cloud_voxel_m: float = 0.05  # voxel size of the stitched team cloud [m]
    fuse_radius_m: float = 0.03  # points of different robots closer than this become one [m]
    unmerged_offset_m: float = 30.0  # unmerged groups are shown this far apart along x [m]

    def validate(self) -> None:
        require(self.optimize_every >= 1, "server: optimize_every must be >= 1")
        require(self.cloud_voxel_m > 0, "server: cloud_voxel_m must be > 0")
        require(self.fuse_radius_m >= 0, "server: fuse_radius_m must be >= 0")
        self.pose_graph.validate()
        require(len(self.robots) >= 1, "server: robots must list at least one robot id")
        require(all(r >= 1 for r in self.robots), "server: robot ids must be >= 1")
        require(len(set(self.robots)) == len(self.robots), "server: robot ids must be unique")
        self.place_recognition.validate()
        self.rendezvous.validate()
        self.loops.validate()
        self.global_ba.validate()


@dataclass
class MergeResult:
    type: str
    robot_a: int  # reference robot (its group's frame is kept)
    robot_b: int
    keyframe_a: int
    keyframe_b: int
    stamp_s: float  # stamp of the keyframe that triggered the merge
    T_mapA_mapB: np.ndarray
    T_camA_camB: np.ndarray
    inliers: int
    residual_px: float
    group: list[int]


@dataclass
class ConstraintResult:
    """A verified constraint inside one group: a loop closure (same robot) or a further link
    between two merged robots."""

    type: str
    key_a: tuple[int, int]
    key_b: tuple[int, int]
    stamp_s: float
    T_camA_camB: np.ndarray
    inliers: int
    residual_px: float


@dataclass
class _Verified:
    """A verified cross-group match waiting for the merge plan."""

    kind: str
    key_a: tuple[int, int]
    key_b: tuple[int, int]
    result: RelativePoseResult
    stamp_s: float


# A robot's position between two keyframes is interpolated only across gaps up to this long [s]:
# a robot's path bends little in a second, so the straight line between them errs by
# centimetres, well under rendezvous.min_separation_m.
_TRACK_GAP_S = 1.0


# What of a robot surely surrounds its camera (housing, mount, body) [m], and how deep its body
# reaches behind that [m]: a keyframe whose keypoints around where another robot's camera would
# be (at least _SEE_THROUGH_MIN_KEYPOINTS of them, nearly all) lie farther than that looks
# straight through the other robot.
_BODY_RADIUS_M = 0.1
_BODY_DEPTH_M = 0.3
_SEE_THROUGH_MIN_KEYPOINTS = 5
_SEE_THROUGH_FRACTION = 0.8


def _sees_through(rec: KeyframeRecord, c_cam: np.ndarray) -> bool:
    """Whether keyframe ``rec`` sees surfaces behind the point ``c_cam`` (its camera frame)
    all around it, where another robot's camera would be."""
    cam = rec.camera
    if c_cam[2] < 2 * _BODY_RADIUS_M:
        return False
    u, v = project(c_cam[None], cam.K)[0]
    if not (0 <= u < cam.width and 0 <= v < cam.height):
        return False
    radius_px = cam.fx * _BODY_RADIUS_M / c_cam[2]
    uv = rec.keypoints[:, :2]
    near = (np.hypot(uv[:, 0] - u, uv[:, 1] - v) <= radius_px) & (rec.depths_m > 0)
    if near.sum() < _SEE_THROUGH_MIN_KEYPOINTS:
        return False
    beyond = rec.depths_m[near] > c_cam[2] + _BODY_DEPTH_M
    return bool(beyond.mean() >= _SEE_THROUGH_FRACTION)


def _interpolate_track(stamps_s: np.ndarray, positions: np.ndarray, stamp_s: float):
    """Position at ``stamp_s`` on a time-ordered track: its keyframe at that stamp, else the
    straight line between the keyframes just before and after, when each is within _TRACK_GAP_S;
    None when they do not pin it down (a gap, before the first or after the last keyframe)."""
    after = int(np.searchsorted(stamps_s, stamp_s))  # first keyframe at or after stamp_s
    if after < len(stamps_s) and stamps_s[after] == stamp_s:
        return positions[after]
    if after == 0 or after == len(stamps_s):
        return None
    t0, t1 = stamps_s[after - 1], stamps_s[after]
    if t1 - stamp_s > _TRACK_GAP_S or stamp_s - t0 > _TRACK_GAP_S:
        return None
    w = (stamp_s - t0) / (t1 - t0)
    return (1.0 - w) * positions[after - 1] + w * positions[after]


def _pair(a: int, b: int) -> tuple[int, int]:
    """A robot pair as the key of pair tables (match counts, pending merges)."""
    return (min(a, b), max(a, b))


@dataclass
class _Stored:
    record: KeyframeRecord
    view: KeyframeView | None = None


class TeamServer:
    """Consumes validated keyframes from all robots and stitches their maps."""

    def __init__(self, config: ServerConfig, vocabulary: Vocabulary):
        config.validate()
        self.config = config
        self.vocabulary = vocabulary
        self.known_robots = set(config.robots)
        self.groups = MergeGroups(config.robots)
        pr = config.place_recognition
        self.database = KeyframeDatabase(pr.database)
        self.consistency = ConsistencyChecker(ConsistencyConfig(min_consecutive=pr.min_consecutive))
        self.keyframes: dict[tuple[int, int], _Stored] = {}
        self.merges: list[MergeResult] = []
        self.constraints: list[ConstraintResult] = []  # loop closures and in-group links
        self.rejected_constraints = 0  # verified, but too far from the current estimate
        self.match_counts: dict[tuple[int, int], int] = {}  # robot pair -> keyframe matches
        self._pending: dict[tuple[int, int], _Verified] = {}
        # Cued requests (marker sighting, operator) not verified yet: the keyframes that show the
        # shared scene often reach the server just after the cue. robot pair -> _OpenRequest
        self._open_requests: dict[tuple[int, int], _OpenRequest] = {}
        self._seen_together: dict[tuple[int, int], float] = {}  # robot pair -> latest cue [s]
        self._kf_count: dict[int, int] = {}  # keyframes received per robot
        self._last_constraint: dict[int, int] = {}  # robot -> its keyframe count at the last one
        self._need_full = False
        # (robot, map point id) pairs that merges / loops matched: one physical point each
        self.point_links: list[tuple[tuple[int, int], tuple[int, int]]] = []
        self.global_ba_runs: list[GlobalBaResult] = []
        # (low robot, high robot) -> [((key_low, key_high), T_mapLow_mapHigh)] of automatic
        # co-observations, for their confirmation
        self._co_observations: dict[tuple[int, int], list] = {}
        self.keyframe_ms: list[float] = []  # server time per incoming keyframe
        self.verifications = 0
        self.graph = TeamPoseGraph(config.pose_graph)
        self.optimize_ms: list[float] = []
        self._since_optimize = 0

    # --- keyframes --------------------------------------------------------------------------------
    def add_keyframe(self, rec: KeyframeRecord) -> list[MergeResult]:
        """Store (or update / remove) one keyframe; returns the merges it caused."""
        t0 = time.perf_counter()
        rec.validate(self.known_robots)
        key = (rec.robot_id, rec.keyframe_id)
        merges: list[MergeResult] = []
        if rec.action == ACTION_REMOVE:
            if key in self.keyframes:
                del self.keyframes[key]
                self.database.remove(*key)
                self._graph_call(self.graph.remove_keyframe, *key)
        elif rec.action == ACTION_UPDATE and key in self.keyframes:
            # Local BA moved the pose / points; descriptors (and so the BoW vector) are unchanged.
            self.keyframes[key] = _Stored(rec)
            self._graph_call(self.graph.update_keyframe, *key, rec.T_map_cam)
        elif rec.action in (ACTION_NEW, ACTION_UPDATE):
            if key in self.keyframes:
                raise ServerError(
                    f"keyframe {rec.keyframe_id} of robot {rec.robot_id} was "
                    "already received as new"
                )
            bow, _ = self.vocabulary.transform(rec.descriptors)
            covisible = [(rec.robot_id, int(k)) for k in rec.covisible_ids]
            self.keyframes[key] = _Stored(rec)
            self.database.add(rec.robot_id, rec.keyframe_id, bow, covisible)
            self._graph_call(
                self.graph.add_keyframe,
                rec.robot_id,
                rec.keyframe_id,
                rec.T_map_cam,
                self.groups.T_root_map(rec.robot_id),
                [int(k) for k in rec.covisible_ids],
            )
            self._kf_count[rec.robot_id] = self._kf_count.get(rec.robot_id, 0) + 1
            if self.config.rendezvous.auto:
                merges = self._co_observation(rec)
            if not merges and self._open_requests:  # robots seen together: a rendezvous
                merges = self._retry_requests(rec)
            if not merges and self.config.place_recognition.enabled:
                merges = self._place_recognition(rec, bow, covisible)
        self._since_optimize += 1
        if merges or self._need_full:
            self.optimize(full=True)
            if merges and self.config.global_ba.after_merge:
                self._global_ba_if_cheap(merges[-1].robot_a)
        elif self._since_optimize >= self.config.optimize_every:
            self.optimize(full=False)
        self.keyframe_ms.append(1e3 * (time.perf_counter() - t0))
        return merges

    # --- team optimization ------------------------------------------------------------------------
    def _graph_call(self, fn, *args) -> None:
        try:
            fn(*args)
        except PoseGraphError as exc:  # the graph must never take the server down
            log.warning("pose graph: %s", exc)

    def optimize(self, full: bool = True) -> None:
        """Optimize the team pose graph and move every robot's map to its optimized place."""
        self._since_optimize = 0
        self._need_full = False
        try:
            stats = self.graph.optimize_full() if full else self.graph.optimize_incremental()
        except (PoseGraphError, RuntimeError) as exc:
            log.warning("pose graph optimization failed: %s", exc)
            return
        self.optimize_ms.append(stats.time_ms)
        for robot in self.groups.robots:
            if robot in self.graph.robots and self.graph.keyframe_ids(robot):
                self.groups.set_T_root_map(robot, self.graph.T_world_map(robot))

    def _global_ba_if_cheap(self, robot_id: int) -> None:
        members = set(self.groups.members(robot_id))
        n = count_observations(s.record for k, s in self.keyframes.items() if k[0] in members)
        if n > self.config.global_ba.auto_max_observations:
            log.info(
                "global BA after the merge skipped: %d observations > %d (call the service)",
                n,
                self.config.global_ba.auto_max_observations,
            )
            return
        try:
            self.global_bundle_adjustment(robot_id)
        except GlobalBaError as exc:
            log.warning("global BA after the merge: %s", exc)

    def global_bundle_adjustment(self, robot_id: int | None = None) -> GlobalBaResult:
        """Bundle-adjust every keyframe and map point of robot_id's group (default: the world
        group) with the points matched by merges and loops linked; the refined poses become the
        pose graph's estimate and odometry (see TeamPoseGraph.adopt_estimates)."""
        robot_id = min(self.known_robots) if robot_id is None else int(robot_id)
        if robot_id not in self.known_robots:
            raise GlobalBaError(
                f"robot {robot_id} is unknown to the server "
                f"(known: {sorted(self.known_robots)})"
            )
        members = set(self.groups.members(robot_id))
        keys = sorted(k for k in self.keyframes if k[0] in members)
        if not keys:
            raise GlobalBaError(f"robot {robot_id}'s group {sorted(members)} has no keyframes yet")
        records = [self.keyframes[k].record for k in keys]
        poses = {k: self.T_group_cam(*k) for k in keys}
        links = [(a, b) for a, b in self.point_links if a[0] in members and b[0] in members]
        root = min(members)
        fixed = {min(k for k in keys if k[0] == root)} if any(k[0] == root for k in keys) else None
        result = global_bundle_adjustment(records, poses, links, fixed, self.config.global_ba)
        self._graph_call(self.graph.adopt_estimates, result.poses)
        self.optimize(full=True)
        self.global_ba_runs.append(result)
        log.info(
            "global BA of group %s: %d keyframes, %d points, %d observations (%d outliers), "
            "reprojection RMS %.2f -> %.2f px, %.0f ms",
            sorted(members),
            result.keyframes,
            result.points,
            result.observations,
            result.outliers,
            result.rms_before,
            result.rms_after,
            result.time_ms,
        )
        return result

    def _add_factor(self, kind: str, key_a, key_b, res: RelativePoseResult, robust_k=None) -> None:
        """A verified relative pose into the pose graph (loop factor within one robot, merge factor
        between two), its matched map points into the links for global BA."""
        sig_rot, sig_trans = self._sigmas(res)
        if key_a[0] == key_b[0]:
            self._graph_call(
                self.graph.add_loop,
                key_a[0],
                key_a[1],
                key_b[1],
                res.T_a_b,
                "loop",
                sig_rot,
                sig_trans,
                robust_k,
            )
        else:
            self._graph_call(
                self.graph.add_merge,
                key_a[0],
                key_a[1],
                key_b[0],
                key_b[1],
                res.T_a_b,
                kind,
                sig_rot,
                sig_trans,
                robust_k,
            )
        self._record_links(key_a, key_b, res)

    def _record_links(self, key_a, key_b, res: RelativePoseResult) -> None:
        """Map points matched by an accepted registration are one physical point."""
        ids_a = self.keyframes[key_a].record.map_point_ids
        ids_b = self.keyframes[key_b].record.map_point_ids
        for ia, ib in np.asarray(res.inlier_idx, int).reshape(-1, 2):
            if ia < len(ids_a) and ib < len(ids_b) and ids_a[ia] and ids_b[ib]:
                self.point_links.append(((key_a[0], int(ids_a[ia])), (key_b[0], int(ids_b[ib]))))

    def corrected_keyframes(self, robot_id: int, last: int = 20) -> dict[int, np.ndarray]:
        """Optimized poses (in the robot's own map frame) of its ``last`` newest keyframes."""
        if robot_id not in self.graph.robots:
            return {}
        T_map_world = np.linalg.inv(self.groups.T_root_map(robot_id))
        poses = self.graph.keyframe_poses(robot_id)
        return {k: T_map_world @ poses[k] for k in sorted(poses)[-last:]}

    def _view_offsets(self) -> dict[int, np.ndarray]:
        """robot -> shift of its group on screen: unmerged groups are drawn apart along x so
        their maps do not overlap."""
        world_root = min(self.known_robots)
        roots = sorted({self.groups.root(r) for r in self.groups.robots} - {world_root})
        order = [world_root] + roots
        offsets = {}
        for robot in self.groups.robots:
            offsets[robot] = np.eye(4)
            offsets[robot][0, 3] = (
                order.index(self.groups.root(robot)) * self.config.unmerged_offset_m
            )
        return offsets

    def T_view_map(self, robot_id: int) -> np.ndarray:
        """Where a robot's map is drawn: its group frame, unmerged groups shifted along x."""
        return self._view_offsets()[robot_id] @ self.groups.T_root_map(robot_id)

    def T_group_cam(self, robot_id: int, keyframe_id: int) -> np.ndarray:
        """A keyframe's pose in its group frame: the optimized one when the pose graph has it,
        else the client's pose moved by the robot's map transform."""
        try:
            return self.graph.T_world_cam(robot_id, keyframe_id)
        except PoseGraphError:
            rec = self.keyframes[(robot_id, keyframe_id)].record
            return self.groups.T_root_map(robot_id) @ rec.T_map_cam

    def optimized_keyframes(self, robot_id: int) -> dict[int, np.ndarray]:
        """keyframe id -> T_group_cam of every stored keyframe of a robot (``world`` when
        :meth:`T_world_map` says the robot is merged with the world group)."""
        ids = sorted(k for (r, k) in self.keyframes if r == robot_id)
        return {k: self.T_group_cam(robot_id, k) for k in ids}

    def team_view(self) -> tuple[dict[int, np.ndarray], list[tuple[str, np.ndarray, np.ndarray]]]:
        """Optimized keyframe positions per robot and merge / constraint edges (type, position a,
        position b), in the frame the team cloud is drawn in."""

        offsets = self._view_offsets()

        def position(key):
            return (offsets[key[0]] @ self.T_group_cam(*key))[:3, 3]

        paths = {}
        for robot in sorted({r for r, _ in self.keyframes}):
            poses = self.optimized_keyframes(robot)
            paths[robot] = np.array([(offsets[robot] @ T)[:3, 3] for T in poses.values()])
        links = [
            (m.type, (m.robot_a, m.keyframe_a), (m.robot_b, m.keyframe_b)) for m in self.merges
        ]
        links += [(c.type, c.key_a, c.key_b) for c in self.constraints]
        edges = [
            (kind, position(ka), position(kb))
            for kind, ka, kb in links
            if ka in self.keyframes and kb in self.keyframes
        ]
        return paths, edges

    def team_cloud(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stitched cloud (points (N, 3) in each group's frame, rgb (N, 3) uint8 per robot,
        robot ids (N,)): each keyframe's points moved with its optimized pose, duplicates of
        overlapping maps fused, voxel-downsampled. Groups other than the world group are shifted
        along x so unmerged maps do not overlap on screen."""
        cfg = self.config
        records = [s.record for s in self.keyframes.values()]
        if not records:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64)

        offsets = self._view_offsets()

        def T_view_map_of(rec):
            T_group_cam = self.T_group_cam(rec.robot_id, rec.keyframe_id)
            return offsets[rec.robot_id] @ T_group_cam @ invert(rec.T_map_cam)

        points, robots, ids = gather_map_points(records, T_view_map_of, per_keyframe=True)
        points, ids, robots = fuse_points(points, robots, ids, radius_m=cfg.fuse_radius_m)
        points, robots = voxel_downsample(points, robots, cfg.cloud_voxel_m)
        return points, robot_colours(robots), robots

    def _view(self, key) -> KeyframeView:
        stored = self.keyframes[key]
        if stored.view is None:
            r = stored.record
            stored.view = KeyframeView(r.uv_px, r.descriptors, r.depths_m, r.camera.K)
        return stored.view

    def _place_recognition(self, rec: KeyframeRecord, bow, covisible) -> list[MergeResult]:
        """BoW query over every robot's keyframes: matches in other groups become merges (in the
        order the merge plan gives), matches inside the own group loop closures / extra links."""
        rb, key_b = rec.robot_id, (rec.robot_id, rec.keyframe_id)
        loops = self.config.loops
        candidates = [
            c
            for c in self.database.query(
                bow, rb, rec.keyframe_id, covisible=covisible, other_robots_only=not loops.enabled
            )
            if c.key in self.keyframes
            and not (
                c.key[0] == rb
                and rec.stamp_s - self.keyframes[c.key].record.stamp_s < loops.min_separation_s
            )
        ]
        consistent = self.consistency.check(rb, candidates, self.database)
        cross = [k for k in consistent if not self.groups.same_group(k[0], rb)]
        inner = [k for k in consistent if self.groups.same_group(k[0], rb)]
        for k in cross:
            pair = _pair(k[0], rb)
            self.match_counts[pair] = self.match_counts.get(pair, 0) + 1
        budget = self.config.place_recognition.max_verifications
        verified_roots = set()
        for cand_key in cross:
            root = self.groups.root(cand_key[0])
            if budget == 0 or root in verified_roots:
                continue
            budget -= 1
            res = self._verify_pnp(cand_key, key_b)
            if res.accepted and res.n_inliers < self.config.place_recognition.merge_min_inliers:
                log.info(
                    "place recognition %s - %s: %d inliers, fewer than a merge needs (%d)",
                    cand_key,
                    key_b,
                    res.n_inliers,
                    self.config.place_recognition.merge_min_inliers,
                )
            elif res.accepted and not self._look_alike("place recognition", cand_key, key_b, res):
                verified_roots.add(root)
                # Seen at (about) the same time or while known to be together, it is a
                # rendezvous, whichever path verified it.
                dt = abs(self.keyframes[cand_key].record.stamp_s - rec.stamp_s)
                kind = (
                    TYPE_RENDEZVOUS
                    if dt <= self.config.rendezvous.window_s
                    or self._together(cand_key[0], rb, rec.stamp_s)
                    else TYPE_PLACE_RECOGNITION
                )
                self._pending[_pair(cand_key[0], rb)] = _Verified(
                    kind, cand_key, key_b, res, rec.stamp_s
                )
        merges = self._apply_merge_plan()
        due = self._kf_count.get(rb, 0) - self._last_constraint.get(rb, -(10**9))
        if merges or not inner or budget == 0 or due < loops.min_interval_kf:
            return merges
        for cand_key in inner[:budget]:
            res = self._verify_pnp(cand_key, key_b)
            if res.accepted and self._add_constraint(
                TYPE_PLACE_RECOGNITION, cand_key, key_b, res, rec.stamp_s
            ):
                break
        return merges

    def _verify_pnp(self, key_a, key_b) -> RelativePoseResult:
        self.verifications += 1
        res = estimate_pnp(
            self._view(key_a), self._view(key_b), self.config.place_recognition.registration
        )
        log.debug("place recognition %s vs %s: %s", key_a, key_b, res.reason)
        return res

    def _sigmas(self, res: RelativePoseResult) -> tuple[float, float]:
        """(rotation [rad], translation [m]) std of a loop / merge factor from the registration."""
        cfg = self.config.loops
        rot_deg = max(cfg.min_sigma_rot_deg, cfg.sigma_scale * res.sigma_rot_deg)
        trans_m = max(cfg.min_sigma_trans_m, cfg.sigma_scale * res.sigma_trans_m)
        if not np.isfinite(rot_deg * trans_m):  # no marginals: the pose graph's defaults
            return None, None
        return float(np.radians(rot_deg)), float(trans_m)

    def _apply_merge_plan(self) -> list[MergeResult]:
        """Execute the verified cross-group matches in merge order (DSM-SLAM): the pair of groups
        sharing the most keyframe matches first; matches left linking robots of one group after
        that become extra constraints."""
        if not self._pending:
            return []
        counts = {pair: max(1, self.match_counts.get(pair, 0)) for pair in self._pending}
        merges = []
        for step in plan_merge_steps(counts, self.groups.groups()):
            v = self._pending.pop(_pair(step.robot_a, step.robot_b))
            merges.append(self._merge(v.kind, v.key_a, v.key_b, v.result, v.stamp_s))
        for v in self._pending.values():
            self._add_constraint(v.kind, v.key_a, v.key_b, v.result, v.stamp_s)
        self._pending.clear()
        return merges

    def _add_constraint(
        self, kind: str, key_a, key_b, res: RelativePoseResult, stamp_s: float
    ) -> bool:
        """A verified relative pose between keyframes of one group goes into the pose graph as a
        robust loop (same robot) or merge (two robots) factor, unless it contradicts the current
        estimate by more than the gate. A full optimization follows."""
        loops = self.config.loops
        if res.n_inliers < loops.min_inliers:
            log.info(
                "constraint %s - %s skipped: %d inliers, fewer than loops.min_inliers (%d)",
                key_a,
                key_b,
                res.n_inliers,
                loops.min_inliers,
            )
            return False
        try:
            T_est = invert(self.graph.T_world_cam(*key_a)) @ self.graph.T_world_cam(*key_b)
        except PoseGraphError as exc:
            log.warning("constraint %s - %s skipped: %s", key_a, key_b, exc)
            return False
        dt, dr = transform_error(res.T_a_b, T_est)
        if dt > loops.gate_trans_m or dr > loops.gate_rot_deg:
            self.rejected_constraints += 1
            log.info(
                "constraint %s - %s refused: %.2f m / %.1f deg from the current estimate",
                key_a,
                key_b,
                dt,
                dr,
            )
            return False
        sig_rot, sig_trans = self._sigmas(res)
        # The disagreement the gate let through is drift of the odometry chain, not an error of
        # this (precise) constraint: the kernel is widened by it, else the robust loss would
        # down-weight exactly the loops that correct the most drift. A constraint that later
        # disagrees with the rest of the graph by more is still down-weighted.
        k = self.graph.config.robust_k
        if sig_rot is not None:
            k *= float(np.sqrt(1.0 + (dt / sig_trans) ** 2 + (np.radians(dr) / sig_rot) ** 2))
        self._add_factor(kind, key_a, key_b, res, robust_k=k)
        self.constraints.append(
            ConstraintResult(
                "loop" if key_a[0] == key_b[0] else kind,
                key_a,
                key_b,
                stamp_s,
                res.T_a_b,
                int(res.n_inliers),
                float(res.residual_px),
            )
        )
        self._last_constraint[key_b[0]] = self._kf_count.get(key_b[0], 0)
        self._need_full = True
        log.info(
            "%s constraint %s - %s (%d inliers, %.2f px; %.3f m / %.2f deg from estimate)",
            self.constraints[-1].type,
            key_a,
            key_b,
            res.n_inliers,
            res.residual_px,
            dt,
            dr,
        )
        return True

    # --- rendezvous -------------------------------------------------------------------------------
    def _near_in_time(
        self, robot_id: int, stamp_s: float, window_s: float, latest_fallback: bool = False
    ) -> list[tuple[int, int]]:
        """Keys of robot_id's keyframes within window_s of stamp_s, nearest first. A robot that
        stands still makes no new keyframes: with ``latest_fallback`` its latest keyframe before
        the window stands for what it sees. Only for requests that bring their own cue (a marker
        sighting, an operator): for the automatic test, being seen at the same time is part of the
        evidence (identical textures in two places pass any geometric check)."""
        keys = [
            (k, abs(s.record.stamp_s - stamp_s))
            for k, s in self.keyframes.items()
            if k[0] == robot_id and abs(s.record.stamp_s - stamp_s) <= window_s
        ]
        if not keys and latest_fallback:
            before = [
                (k, s.record.stamp_s)
                for k, s in self.keyframes.items()
                if k[0] == robot_id and s.record.stamp_s < stamp_s
            ]
            return [max(before, key=lambda ks: ks[1])[0]] if before else []
        return [k for k, _ in sorted(keys, key=lambda kd: kd[1])]

    def _co_observation(self, rec: KeyframeRecord) -> list[MergeResult]:
        """Automatic rendezvous: the new keyframe against other unmerged robots' keyframes taken
        at (about) the same time, pre-filtered by BoW similarity, verified 3D-3D."""
        key_b = (rec.robot_id, rec.keyframe_id)
        cfg = self.config.rendezvous
        for other in self.groups.robots:
            if self.groups.same_group(other, rec.robot_id):
                continue
            cued = self._together(other, rec.robot_id, rec.stamp_s)
            for key_a in self._near_in_time(other, rec.stamp_s, cfg.window_s)[:2]:
                merge = self._verify_rendezvous(key_a, key_b, rec.stamp_s, confirm=not cued)
                if merge is not None:
                    return [merge]
        return []

    def _together(self, robot_a: int, robot_b: int, stamp_s: float) -> bool:
        """Whether a sighting / operator request put the two robots together shortly before
        (or after: keyframes reach the server late) stamp_s."""
        cue = self._seen_together.get(_pair(robot_a, robot_b))
        return cue is not None and abs(stamp_s - cue) <= self.config.rendezvous.together_s

    def _confirmed(self, key_a, key_b, res: RelativePoseResult) -> bool:
        """Whether earlier automatic verifications of this robot pair (either direction, other
        keyframes) agree with this one on the map transform; this one is remembered either way."""
        cfg = self.config.rendezvous
        T = chain_map_transform(
            self.keyframes[key_a].record.T_map_cam,
            res.T_a_b,
            self.keyframes[key_b].record.T_map_cam,
        )
        if key_a[0] > key_b[0]:  # one direction per pair: T_mapLow_mapHigh
            T, key_a, key_b = invert(T), key_b, key_a
        hits = self._co_observations.setdefault((key_a[0], key_b[0]), [])
        tolerance = (cfg.confirm_trans_m, cfg.confirm_rot_deg)
        agreeing = {
            keys
            for keys, T_prev in hits
            if key_a not in keys
            and key_b not in keys
            and all(e <= tol for e, tol in zip(transform_error(T, T_prev), tolerance))
        }
        hits.append(((key_a, key_b), T))
        if len(agreeing) + 1 < cfg.auto_confirmations:
            log.info(
                "co-observation %s - %s verified (%d inliers); waiting for %d more agreeing",
                key_a,
                key_b,
                res.n_inliers,
                cfg.auto_confirmations - 1 - len(agreeing),
            )
            return False
        return True

    def _track(self, robot_id: int, map_segment: int) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_s (K,), camera positions (K, 3) in its map) of a robot's keyframes of one map
        segment, in time order."""
        track = sorted(
            (
                (s.record.stamp_s, s.record.T_map_cam[:3, 3])
                for k, s in self.keyframes.items()
                if k[0] == robot_id and s.record.map_segment == map_segment
            ),
            key=lambda sp: sp[0],  # stamps only: equal stamps must not compare the arrays
        )
        if not track:
            return np.zeros(0), np.zeros((0, 3))
        return np.array([t for t, _ in track]), np.array([p for _, p in track])

    def _position_at(self, robot_id: int, map_segment: int, stamp_s: float) -> np.ndarray | None:
        """Where the robot's camera was at ``stamp_s`` in its map (see _interpolate_track)."""
        return _interpolate_track(*self._track(robot_id, map_segment), stamp_s)

    def _physically_impossible(self, key_a, key_b, T_a_b: np.ndarray) -> str | None:
        """Why ``T_a_b`` (keyframe b's camera in keyframe a's) cannot hold, or None.

        It fixes where each robot's map lies in the other's. Then, at the time of every keyframe
        of either robot within rendezvous.window_s of the pair (as far as the other robot's
        keyframes tell where it was then): the two cameras must be min_separation_m apart, and
        a keyframe cannot see surfaces straight through the other robot's body."""
        cfg = self.config.rendezvous
        rec_a, rec_b = self.keyframes[key_a].record, self.keyframes[key_b].record
        T_mapA_mapB = rec_a.T_map_cam @ T_a_b @ invert(rec_b.T_map_cam)
        lo = min(rec_a.stamp_s, rec_b.stamp_s) - cfg.window_s
        hi = max(rec_a.stamp_s, rec_b.stamp_s) + cfg.window_s
        for viewer, other, T_mapV_mapO in (
            (rec_a, rec_b, T_mapA_mapB),
            (rec_b, rec_a, invert(T_mapA_mapB)),
        ):
            other_track = self._track(other.robot_id, other.map_segment)
            for key, stored in self.keyframes.items():
                rec = stored.record
                if key[0] != viewer.robot_id or rec.map_segment != viewer.map_segment:
                    continue
                if not lo <= rec.stamp_s <= hi:
                    continue
                p_other = _interpolate_track(*other_track, rec.stamp_s)
                if p_other is None:
                    continue
                c = transform_points(invert(rec.T_map_cam) @ T_mapV_mapO, p_other[None])[0]
                if np.linalg.norm(c) < cfg.min_separation_m:
                    return (
                        f"robot {other.robot_id}'s camera {np.linalg.norm(c):.2f} m from robot "
                        f"{viewer.robot_id}'s keyframe {key[1]} at its time"
                    )
                if _sees_through(rec, c):
                    return (
                        f"robot {viewer.robot_id}'s keyframe {key[1]} sees past where robot "
                        f"{other.robot_id} would stand, {c[2]:.2f} m ahead"
                    )
        return None

    def _look_alike(self, kind: str, key_a, key_b, res: RelativePoseResult) -> bool:
        """Whether a verified pair of keyframes taken at about the same time (rendezvous
        window_s) is physically impossible (see _physically_impossible): then the two places
        only look alike. Farther apart in time, each robot's drift would blur the test."""
        cfg = self.config.rendezvous
        dt = abs(self.keyframes[key_a].record.stamp_s - self.keyframes[key_b].record.stamp_s)
        if cfg.min_separation_m <= 0 or key_a[0] == key_b[0] or dt > cfg.window_s:
            return False
        why = self._physically_impossible(key_a, key_b, res.T_a_b)
        if why is None:
            return False
        log.info("%s %s - %s: a look-alike place: %s", kind, key_a, key_b, why)
        return True

    def _verify_rendezvous(
        self, key_a, key_b, stamp_s: float, T_init=None, prior_sigma=None, confirm=False
    ) -> MergeResult | None:
        cfg = self.config.rendezvous
        score = self.vocabulary.score(self.database.bow(*key_a), self.database.bow(*key_b))
        if score < cfg.min_bow_score and T_init is None:
            return None
        self.verifications += 1
        res = estimate_3d3d(
            self._view(key_a),
            self._view(key_b),
            cfg.registration,
            T_init=T_init,
            prior_sigma=prior_sigma,
        )
        log.debug("rendezvous %s vs %s (bow %.3f): %s", key_a, key_b, score, res.reason)
        if not res.accepted:
            return None
        if self._look_alike("rendezvous", key_a, key_b, res):
            return None
        if res.n_inliers < cfg.merge_min_inliers:
            log.info(
                "rendezvous %s - %s: %d inliers, fewer than a merge needs (%d)",
                key_a,
                key_b,
                res.n_inliers,
                cfg.merge_min_inliers,
            )
            return None
        if confirm and not self._confirmed(key_a, key_b, res):
            return None
        self._pending[_pair(key_a[0], key_b[0])] = _Verified(
            TYPE_RENDEZVOUS, key_a, key_b, res, stamp_s
        )
        merges = self._apply_merge_plan()
        return merges[0] if merges else None

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
        for r in (robot_a, robot_b):
            if r not in self.known_robots:
                return (
                    None,
                    f"robot {r} is unknown to the server (known: {sorted(self.known_robots)})",
                )
        if robot_a == robot_b:
            return None, "a rendezvous needs two different robots"
        if self.groups.same_group(robot_a, robot_b):
            return None, f"robots {robot_a} and {robot_b} are already merged"
        cfg = self.config.rendezvous
        if stamp_s is None:
            latest = [
                max(
                    (s.record.stamp_s for k, s in self.keyframes.items() if k[0] == r), default=None
                )
                for r in (robot_a, robot_b)
            ]
            if None in latest:
                return None, "no keyframes yet from one of the robots"
            stamp_s = max(latest)  # now; a robot that stands still falls back to its latest
        pair = _pair(robot_a, robot_b)
        self._seen_together[pair] = max(stamp_s, self._seen_together.get(pair, stamp_s))
        keys_a = self._near_in_time(robot_a, stamp_s, cfg.request_window_s, latest_fallback=True)
        keys_b = self._near_in_time(robot_b, stamp_s, cfg.request_window_s, latest_fallback=True)
        if not keys_a or not keys_b:
            return (
                None,
                f"no keyframes of both robots within {cfg.request_window_s} s of {stamp_s:.2f} s",
            )
        T_init = None
        if T_camA_bodyB is not None and T_bodyB_camB is not None:
            # The sighting is at the marker's image time; keyframes are close to it in time.
            T_init = T_camA_bodyB @ T_bodyB_camB
        request = _OpenRequest(robot_a, robot_b, stamp_s, T_init)
        merge = self._verify_request(request, keys_a[:3], keys_b[:3], cfg.max_pairs)
        if merge is not None:
            return merge, f"merged ({merge.inliers} inliers, {merge.residual_px:.2f} px)"
        self._open_requests[_pair(robot_a, robot_b)] = request
        return None, (
            f"no verified overlap between robots {robot_a} and {robot_b} around "
            f"{stamp_s:.2f} s yet: not merged (a marker sighting alone is not enough); "
            f"keyframes up to {stamp_s + cfg.request_window_s:.2f} s will be tried as they arrive"
        )

    def _verify_request(self, request: _OpenRequest, keys_a, keys_b, max_pairs: int):
        """Verify keyframe pairs of a cued request, closest in time first; the merge or None."""
        pairs = sorted(
            ((ka, kb) for ka in keys_a for kb in keys_b),
            key=lambda p: abs(
                self.keyframes[p[0]].record.stamp_s - self.keyframes[p[1]].record.stamp_s
            ),
        )
        prior = (np.radians(10.0), 0.2) if request.T_init is not None else None
        for key_a, key_b in pairs[:max_pairs]:
            # The merge happens when both the cue and the keyframes exist.
            stamp_s = max(
                request.stamp_s,
                self.keyframes[key_a].record.stamp_s,
                self.keyframes[key_b].record.stamp_s,
            )
            merge = self._verify_rendezvous(key_a, key_b, stamp_s, request.T_init, prior)
            if merge is not None:
                return merge
        return None

    def _retry_requests(self, rec: KeyframeRecord) -> list[MergeResult]:
        """A new keyframe taken within the window of an open cued request of its robot is
        verified against the other robot's keyframes nearest the cue; requests whose window has
        passed (or whose robots merged meanwhile) are closed."""
        window = self.config.rendezvous.request_window_s
        for pair, request in list(self._open_requests.items()):
            if self.groups.same_group(request.robot_a, request.robot_b) or (
                rec.robot_id in pair and rec.stamp_s > request.stamp_s + window
            ):
                del self._open_requests[pair]
                continue
            if rec.robot_id not in pair or abs(rec.stamp_s - request.stamp_s) > window:
                continue
            key_new = (rec.robot_id, rec.keyframe_id)
            other = request.robot_b if rec.robot_id == request.robot_a else request.robot_a
            keys_other = self._near_in_time(other, request.stamp_s, window, latest_fallback=True)
            if rec.robot_id == request.robot_a:
                merge = self._verify_request(request, [key_new], keys_other[:2], 2)
            else:
                merge = self._verify_request(request, keys_other[:2], [key_new], 2)
            if merge is not None:
                del self._open_requests[pair]
                log.info("rendezvous request %s / %s: merged on a later keyframe", *pair)
                return [merge]
        return []

    def _merge(
        self, kind: str, key_a, key_b, res: RelativePoseResult, stamp_s: float
    ) -> MergeResult:
        rec_a, rec_b = self.keyframes[key_a].record, self.keyframes[key_b].record
        T_mapA_mapB = chain_map_transform(rec_a.T_map_cam, res.T_a_b, rec_b.T_map_cam)
        group = self.groups.merge(key_a[0], key_b[0], T_mapA_mapB)
        self._add_factor(kind, key_a, key_b, res)
        merge = MergeResult(
            kind,
            key_a[0],
            key_b[0],
            key_a[1],
            key_b[1],
            stamp_s,
            T_mapA_mapB,
            res.T_a_b,
            int(res.n_inliers),
            float(res.residual_px),
            group,
        )
        self.merges.append(merge)
        self.consistency.reset(key_b[0])
        log.info(
            "merged robot %d into robot %d's map (%s, %d inliers, %.2f px): group %s",
            key_b[0],
            key_a[0],
            kind,
            merge.inliers,
            merge.residual_px,
            group,
        )
        return merge

    # --- team frame -------------------------------------------------------------------------------
    def T_world_map(self, robot_id: int) -> tuple[np.ndarray, bool]:
        """Robot's map in its group's frame, and whether that group is the world (holds robot 1 /
        the smallest id of the team)."""
        world_root = min(self.known_robots)
        return self.groups.T_root_map(robot_id), self.groups.root(robot_id) == world_root
