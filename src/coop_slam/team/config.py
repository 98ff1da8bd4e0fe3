"""Configuration of the server (section ``server`` of ``config/server.yaml``): one dataclass per
stage -- place recognition, rendezvous, constraints inside a group, links where merged maps
overlap, global BA, pose graph, monocular maps' scales -- and
:class:`ServerConfig` holding them. Loaded by :func:`coop_slam.config.load_yaml_config`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..bow.database import DatabaseConfig
from ..config import require
from ..registration.relative_pose import RegistrationConfig
from .assisted_relocalization import AssistConfig
from .clocks import ClockConfig
from .dense_map import DenseMapConfig
from .global_ba import GlobalBaConfig
from .map_scale import MapScaleConfig
from .marker_scale import MarkerScaleConfig
from .overlap_links import OverlapLinkConfig
from .pose_feedback import PoseFeedbackConfig
from .pose_graph import PoseGraphConfig
from .pull import PullConfig


@dataclass
class PlaceRecognitionConfig:
    """A robot seeing a place another robot (or itself) mapped: BoW retrieval, then registration."""

    enabled: bool = True  # look for other robots' places in every new keyframe
    min_consecutive: int = 2  # consecutive consistent queries before a candidate is verified
    max_verifications: int = 2  # candidates geometrically verified per keyframe (bounds the cost)
    # A merge joins two maps on one constraint, so it needs more support than a loop / in-group
    # link (which the pose graph weighs against the rest); the next keyframes usually bring it.
    merge_min_inliers: int = 60
    # ... when a side is monocular (a similarity): its keyframes hold fewer 3D points (only what
    # local mapping triangulated), 3D-3D inliers are counted on them alone; ORB-SLAM accepts a
    # monocular loop on 40.
    merge_min_inliers_similarity: int = 40
    database: DatabaseConfig = field(default_factory=DatabaseConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)

    def validate(self) -> None:
        require(self.min_consecutive >= 1, "place_recognition.min_consecutive must be >= 1")
        require(self.max_verifications >= 1, "place_recognition.max_verifications must be >= 1")
        require(self.merge_min_inliers >= 1, "place_recognition.merge_min_inliers must be >= 1")
        require(
            self.merge_min_inliers_similarity >= 1,
            "place_recognition.merge_min_inliers_similarity must be >= 1",
        )
        self.database.validate()
        self.registration.validate()


@dataclass
class RendezvousConfig:
    """Robots seeing one scene at once: co-observation, marker sightings, operator requests."""

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
    auto_max_verifications: int = 4  # automatic test: 3D-3D verifications per new keyframe
    # ... and at most this many per second of data time over the whole team (a budget that
    # refills with the keyframes' stamps, holding 2 x auto_max_verifications): eight unmerged
    # robots at 4 per keyframe spent half the server's time on it. Data time, not wall time, so
    # lock-step results do not depend on the machine's speed. 0 = no limit [1/s]
    auto_verifications_per_s: float = 8.0
    confirm_trans_m: float = 0.05
    confirm_rot_deg: float = 2.0
    confirm_scale_rel: float = 0.03  # and, for a monocular map, on its scale (relative)
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
        require(self.auto_max_verifications >= 1, "rendezvous.auto_max_verifications must be >= 1")
        require(
            self.auto_verifications_per_s >= 0,
            "rendezvous.auto_verifications_per_s must be >= 0 (0: no limit)",
        )
        require(self.request_window_s > 0, "rendezvous.request_window_s must be > 0")
        require(self.sighting_period_s >= 0, "rendezvous.sighting_period_s must be >= 0")
        require(self.merge_min_inliers >= 1, "rendezvous.merge_min_inliers must be >= 1")
        require(0 <= self.min_bow_score <= 1, "rendezvous.min_bow_score must be in [0, 1]")
        require(self.max_pairs >= 1, "rendezvous.max_pairs must be >= 1")
        require(self.auto_confirmations >= 1, "rendezvous.auto_confirmations must be >= 1")
        require(self.confirm_trans_m > 0, "rendezvous.confirm_trans_m must be > 0")
        require(self.confirm_rot_deg > 0, "rendezvous.confirm_rot_deg must be > 0")
        require(self.confirm_scale_rel > 0, "rendezvous.confirm_scale_rel must be > 0")
        require(self.together_s >= 0, "rendezvous.together_s must be >= 0")
        require(self.min_separation_m >= 0, "rendezvous.min_separation_m must be >= 0")
        self.registration.validate()


@dataclass
class LoopClosureConfig:
    """Constraints between keyframes already in one group: a robot's own loop closures and further
    links between robots merged earlier (the place-recognition path, within the team map)."""

    enabled: bool = True  # close loops within a robot's map and link merged robots
    min_separation_s: float = 5.0  # a robot's own candidate must be at least this much older [s]
    min_interval_kf: int = 2  # keyframes of a robot between two constraints it adds
    # A constraint with this many verified inliers (as a merge) may move the map up to the gate;
    # registration accepts fewer, and such estimates can be far off yet within the gate, whose
    # slack also widens the constraint's robust kernel (docs/tuning.md).
    min_inliers: int = 60
    # A verified constraint further than this from the current estimate is refused (the robust
    # kernel is the second line of defence): indoor drift between revisits is well below it.
    gate_trans_m: float = 1.0
    gate_rot_deg: float = 15.0
    # A constraint with fewer inliers (but accepted by registration) must agree with the current
    # estimate within this: on real images most verified pairs between merged robots have 30-60.
    weak_gate_trans_m: float = 0.1
    weak_gate_rot_deg: float = 3.0
    # Loop and merge factors take the registration's BA marginal std, inflated (pixel noise is not
    # independent in practice) and floored: a well-measured constraint outweighs odometry drift.
    sigma_scale: float = 3.0
    min_sigma_trans_m: float = 0.01
    min_sigma_rot_deg: float = 0.3
    # ... and for a similarity (a monocular side) its scale's, in log scale.
    min_sigma_log_scale: float = 0.01
    # A constraint further than this from the current estimate makes the next optimization a full
    # one (batch Levenberg-Marquardt over the team graph); a closer one, the common case for links
    # between merged robots, is absorbed by the next incremental (iSAM2) update. A full run after
    # every constraint grows with the team graph and bounds how many robots the server keeps up
    # with; the thresholds trade that against the team map's quality (docs/tuning.md).
    full_above_trans_m: float = 0.1
    full_above_rot_deg: float = 3.0
    # ... or a similarity's scale this far (relative) from the graph's local scales there.
    full_above_scale: float = 0.03

    def validate(self) -> None:
        require(self.min_separation_s >= 0, "loops.min_separation_s must be >= 0")
        require(self.min_interval_kf >= 0, "loops.min_interval_kf must be >= 0")
        require(self.min_inliers >= 1, "loops.min_inliers must be >= 1")
        require(self.gate_trans_m > 0, "loops.gate_trans_m must be > 0")
        require(
            self.full_above_trans_m >= 0
            and self.full_above_rot_deg >= 0
            and self.full_above_scale >= 0,
            "loops.full_above_trans_m, full_above_rot_deg and full_above_scale must be >= 0",
        )
        require(self.gate_rot_deg > 0, "loops.gate_rot_deg must be > 0")
        require(self.weak_gate_trans_m > 0, "loops.weak_gate_trans_m must be > 0")
        require(self.weak_gate_rot_deg > 0, "loops.weak_gate_rot_deg must be > 0")
        require(self.sigma_scale > 0, "loops.sigma_scale must be > 0")
        require(self.min_sigma_trans_m > 0, "loops.min_sigma_trans_m must be > 0")
        require(self.min_sigma_rot_deg > 0, "loops.min_sigma_rot_deg must be > 0")
        require(self.min_sigma_log_scale > 0, "loops.min_sigma_log_scale must be > 0")


@dataclass
class ServerConfig:
    robots: list[int] = field(default_factory=lambda: [1, 2])  # robot ids the server accepts
    place_recognition: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)
    rendezvous: RendezvousConfig = field(default_factory=RendezvousConfig)
    loops: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    links: OverlapLinkConfig = field(default_factory=OverlapLinkConfig)
    global_ba: GlobalBaConfig = field(default_factory=GlobalBaConfig)
    pose_graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    map_scale: MapScaleConfig = field(default_factory=MapScaleConfig)
    marker_scale: MarkerScaleConfig = field(default_factory=MarkerScaleConfig)
    pose_feedback: PoseFeedbackConfig = field(default_factory=PoseFeedbackConfig)
    pull: PullConfig = field(default_factory=PullConfig)
    assisted_relocalization: AssistConfig = field(default_factory=AssistConfig)
    clock: ClockConfig = field(default_factory=ClockConfig)
    dense: DenseMapConfig = field(default_factory=DenseMapConfig)
    optimize_every: int = 5  # incremental (iSAM2) update every N keyframes; full after each merge
    # ... or every N updates of keyframes (local BA moved them a little): a client sends several
    # per keyframe, and an incremental update after each 5 messages grew with the team graph
    optimize_every_updates: int = 40
    cloud_voxel_m: float = 0.05  # voxel size of the stitched team cloud [m]
    fuse_radius_m: float = 0.03  # points of different robots closer than this become one [m]
    unmerged_offset_m: float = 30.0  # unmerged groups are shown this far apart along x [m]

    def validate(self) -> None:
        require(self.optimize_every >= 1, "server: optimize_every must be >= 1")
        require(self.optimize_every_updates >= 1, "server: optimize_every_updates must be >= 1")
        require(self.cloud_voxel_m > 0, "server: cloud_voxel_m must be > 0")
        require(self.fuse_radius_m >= 0, "server: fuse_radius_m must be >= 0")
        self.pose_graph.validate()
        require(len(self.robots) >= 1, "server: robots must list at least one robot id")
        require(all(r >= 1 for r in self.robots), "server: robot ids must be >= 1")
        require(len(set(self.robots)) == len(self.robots), "server: robot ids must be unique")
        self.place_recognition.validate()
        self.rendezvous.validate()
        self.loops.validate()
        self.links.validate()
        self.global_ba.validate()
        self.map_scale.validate()
        self.marker_scale.validate()
        self.dense.validate()
        self.pose_feedback.validate()
        self.pull.validate()
        self.assisted_relocalization.validate()
        self.clock.validate()
