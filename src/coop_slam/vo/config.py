"""Parameters of the client's RGB-D, stereo or monocular visual odometry, one section per concern
(features, depth, stereo matching, calibration, tracking, relocalization, keyframes, local mapping,
triangulation, local BA, ground robots, monocular start), and per camera kind (``rgbd``, ``stereo``,
``mono``) the values that differ for it: :meth:`VoConfig.for_sensor` gives the odometry of one
camera its resolved configuration.

Loaded with :func:`coop_slam.config.load_config` / ``load_yaml_config`` (section ``vo`` of
``config/client.yaml``; every key with its unit: docs/configuration.md). Pixel thresholds refer
to pyramid level 0 and are scaled by ``scale_factor ** octave`` where the comment says so.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..config import load_config, merge_overrides, require
from .dense_depth import DenseDepthConfig


@dataclass
class FeatureConfig:
    """ORB features."""

    n_features: int = 1000  # keypoints kept per frame after grid bucketing
    n_detect: int = 2500  # FAST candidates detected before bucketing (>= n_features)
    scale_factor: float = 1.2  # pyramid scale between levels
    n_levels: int = 8  # pyramid levels
    fast_threshold: int = 7  # FAST threshold [grey levels]; low, the grid keeps the best per cell
    # Each level is detected at this threshold first [grey levels], and at fast_threshold only when
    # that finds fewer keypoints than the level wants (at most fast_threshold: one pass). On for
    # stereo cameras (20) by vo.sensors.stereo.features, where a camera kind turns it off.
    fast_threshold_first: int = 0
    grid_cell_px: int = 40  # bucketing cell size at level 0 [px]; scaled by scale_factor**octave
    edge_threshold_px: int = 19  # border without features [px] (ORB patch radius)
    # Threads extracting a frame (its images' pyramid levels, largest first, to whichever is free;
    # a stereo pair's two images together). 2: the odometry's own core and one more.
    threads: int = 2

    def validate(self) -> None:
        require(self.n_features > 0, "vo.features.n_features must be positive")
        require(1 <= self.threads <= 64, "vo.features.threads must be in 1..64")
        require(self.n_detect >= self.n_features, "vo.features.n_detect must be >= n_features")
        require(self.scale_factor > 1.0, "vo.features.scale_factor must be > 1")
        require(1 <= self.n_levels <= 16, "vo.features.n_levels must be in 1..16")
        require(0 < self.fast_threshold < 256, "vo.features.fast_threshold must be in 1..255")
        require(
            0 <= self.fast_threshold_first < 256,
            "vo.features.fast_threshold_first must be in 0..255",
        )
        require(self.grid_cell_px >= 8, "vo.features.grid_cell_px must be >= 8")
        require(
            self.edge_threshold_px >= 16,
            "vo.features.edge_threshold_px must be >= 16 (a keypoint's orientation patch has a "
            "15 px radius)",
        )


@dataclass
class DepthConfig:
    """What a keypoint's depth is worth (RGB-D; a stereo pair's from its disparity)."""

    min_depth_m: float = 0.3  # keypoint depths outside [min, max] are treated as missing [m]
    max_depth_m: float = 6.0  # [m]
    edge_px: int = 0  # depth within this radius must agree, else the keypoint gets none [px]
    edge_ratio: float = 0.05  # ... agree = within this fraction of the depth
    # Depth used in the stereo-like residual up to here [m]; its pixel sigma already makes the
    # depth uncertainty grow with z^2, so no hard cut is needed for RGB-D.
    close_depth_m: float = 6.0
    virtual_baseline_m: float = 0.08  # baseline of the virtual stereo pair built from depth [m]

    def validate(self) -> None:
        require(
            0 < self.min_depth_m < self.max_depth_m,
            "need 0 < vo.depth.min_depth_m < vo.depth.max_depth_m",
        )
        require(self.virtual_baseline_m > 0, "vo.depth.virtual_baseline_m must be positive")


@dataclass
class StereoConfig:
    """Left/right matching of rectified pairs (ORB-SLAM2's stereo matching)."""

    max_descriptor_distance: int = 75  # Hamming gate of a left/right match [bits]
    row_tolerance_px: float = 2.0  # rows of a match differ by at most this x level scale [px]
    patch_radius_px: int = 5  # patch radius of the subpixel refinement [level px]
    search_px: int = 5  # columns searched either side of the descriptor match [level px]
    # Points farther than this many baselines are used without depth: their disparity is a few
    # pixels and its error dominates (ORB-SLAM2's 40).
    close_baselines: float = 40.0
    # Added to every measured disparity [px]: a rectified pair whose calibration leaves the rows
    # right but the columns off by a constant (the KITTI clip's: 0.2, measured against ground
    # truth) biases every depth, far ones most, and the odometry's scale with them.
    disparity_offset_px: float = 0.0

    def validate(self) -> None:
        require(
            0 < self.max_descriptor_distance <= 256,
            "vo.stereo.max_descriptor_distance must be in 1..256",
        )
        require(self.row_tolerance_px > 0, "vo.stereo.row_tolerance_px must be > 0")
        require(self.patch_radius_px >= 1, "vo.stereo.patch_radius_px must be >= 1")
        require(self.search_px >= 1, "vo.stereo.search_px must be >= 1")
        require(self.close_baselines > 0, "vo.stereo.close_baselines must be > 0")


@dataclass
class CalibrationConfig:
    """The colour and depth cameras when the camera model does not say all (0 = it does)."""

    # Colour intrinsics overriding the camera model given to the odometry (0 = use the model) [px].
    color_fx: float = 0.0
    color_fy: float = 0.0
    color_cx: float = 0.0
    color_cy: float = 0.0
    # Depth camera intrinsics when the depth image is NOT registered to the colour image (0 = it
    # is: pixel (u, v) of both images sees the same point) [px].
    depth_fx: float = 0.0
    depth_fy: float = 0.0
    depth_cx: float = 0.0
    depth_cy: float = 0.0
    # Position of the depth camera's optical centre in the colour camera frame (rotation assumed
    # identity): the translation of T_color_depth [m]. Used only with depth_fx > 0.
    depth_in_color_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])

    @property
    def depth_registered(self) -> bool:
        return self.depth_fx <= 0

    def color_camera(self, camera):
        """``camera`` with the colour intrinsics overridden where this config sets them."""
        return dataclasses.replace(
            camera,
            fx=self.color_fx or camera.fx,
            fy=self.color_fy or camera.fy,
            cx=self.color_cx or camera.cx,
            cy=self.color_cy or camera.cy,
        )

    def validate(self) -> None:
        require(
            len(self.depth_in_color_m) == 3,
            "vo.calibration.depth_in_color_m must be [x, y, z] in metres",
        )
        depth_intr = (self.depth_fx, self.depth_fy, self.depth_cx, self.depth_cy)
        require(
            all(v == 0 for v in depth_intr) or (self.depth_fx > 0 and self.depth_fy > 0),
            "vo.calibration.depth_fx and depth_fy must both be > 0 when the depth camera is given",
        )


@dataclass
class TrackingConfig:
    """Tracking the local map: projection search and motion-only pose optimization."""

    search_radius_px: float = 12.0  # first projection search around the motion prediction [px]
    search_radius_refine_px: float = 4.0  # second search after the first pose update [px]
    max_descriptor_distance: int = 80  # Hamming gate for projection matches [bits]
    ratio_test: float = 0.9  # best/second best distance ratio within a search window
    check_orientation: bool = True  # rotation-histogram consistency of frame-to-map matches
    min_tracked: int = 30  # fewer pose inliers than this = tracking failure
    local_keyframes: int = 20  # keyframes whose points form the local map
    pose_iterations: int = 10  # Gauss-Newton iterations per robust round of pose optimization
    pose_rounds: int = 4  # rounds of (optimize, reclassify outliers)
    chi2_mono: float = 5.991  # 95 % outlier gate, 2 dof (u, v) [whitened px^2]
    chi2_stereo: float = 7.815  # 95 % outlier gate, 3 dof (u, v, u_right) [whitened px^2]
    # A pose that moved faster than this since the previous frame is a tracking failure: no
    # robot (hand-held, wheeled, a car on KITTI at 12 m/s) moves that fast.
    max_speed_m_s: float = 40.0  # [m/s]
    max_turn_rate_deg_s: float = 900.0  # [deg/s]

    def validate(self) -> None:
        require(
            0 < self.search_radius_px < np.inf and 0 < self.search_radius_refine_px < np.inf,
            "vo.tracking search radii must be finite and > 0 [px]",
        )
        require(
            0 < self.max_descriptor_distance <= 256,
            "vo.tracking.max_descriptor_distance must be in 1..256",
        )
        require(0 < self.ratio_test <= 1.0, "vo.tracking.ratio_test must be in (0, 1]")
        require(self.min_tracked >= 6, "vo.tracking.min_tracked must be >= 6")
        require(
            self.pose_iterations > 0 and self.pose_rounds > 0,
            "vo.tracking: pose optimization needs iterations and rounds",
        )
        require(
            self.max_speed_m_s > 0 and self.max_turn_rate_deg_s > 0,
            "vo.tracking.max_speed_m_s and max_turn_rate_deg_s must be > 0",
        )


@dataclass
class RelocalizationConfig:
    """Finding the camera again when tracking is lost (PnP against keyframes), and giving up."""

    pnp_ratio: float = 0.8  # Lowe ratio for brute-force descriptor matching
    pnp_reprojection_px: float = 4.0  # RANSAC inlier threshold [px]
    pnp_iterations: int = 200  # RANSAC iterations
    pnp_min_inliers: int = 20  # fewer RANSAC inliers = failure
    keyframes: int = 15  # recent keyframes tried for relocalization
    keyframes_per_frame: int = 5  # keyframes tried per lost frame (bounds the time per frame)
    min_inliers: int = 50  # pose inliers needed to accept a relocalization
    max_lost_frames: int = 10  # lost frames before a new map segment is started
    # ... more while a server-assisted relocalization is under way (the team's local map asked)
    assist_wait_frames: int = 30

    def validate(self) -> None:
        require(self.max_lost_frames >= 0, "vo.relocalization.max_lost_frames must be >= 0")
        require(self.assist_wait_frames >= 0, "vo.relocalization.assist_wait_frames must be >= 0")


@dataclass
class KeyframeConfig:
    """When a tracked frame becomes a keyframe (ORB-SLAM2's rule), and culling keyframes."""

    # Keypoints with depth needed to start a map (monocular: points the two views triangulate).
    min_init_points: int = 100
    max_frames: int = 30  # insert a keyframe at least this often (if tracking is weak) [frames]
    min_frames: int = 0  # never insert two keyframes closer than this [frames]
    ref_ratio: float = 0.75  # tracked / reference keyframe points below this -> keyframe
    close_tracked: int = 100  # "too few close points": tracked close < this ...
    close_untracked: int = 70  # ... and untracked close > this
    min_tracked: int = 250  # fewer tracked points than this -> keyframe (0 = off)
    min_inliers: int = 15  # a keyframe needs at least this many tracked points
    culling: bool = True  # cull keyframes whose points other keyframes see
    cull_redundancy: float = 0.9  # fraction of points seen by >= cull_observers other keyframes
    cull_observers: int = 3

    def validate(self) -> None:
        require(0 < self.ref_ratio <= 1.0, "vo.keyframes.ref_ratio must be in (0, 1]")
        require(self.min_frames >= 0, "vo.keyframes.min_frames must be >= 0 [frames]")
        require(0 < self.cull_redundancy <= 1.0, "vo.keyframes.cull_redundancy must be in (0, 1]")


@dataclass
class MappingConfig:
    """Local mapping: new map points, fusing and culling them."""

    # Mapping steps wait for the frame being tracked, at most this long [s] (see local_mapping).
    yield_max_s: float = 0.1
    new_points_max: int = 600  # new map points created per keyframe from depth (closest first)
    fuse_neighbors: int = 10  # covisible keyframes searched to fuse duplicate points
    fuse_radius_px: float = 3.0  # projection search radius for fusion [px], scaled by octave
    cull_found_ratio: float = 0.25  # recent points found / visible below this are removed
    cull_min_observations: int = 2  # recent points seen by fewer keyframes after 2 are removed
    # A keyframe local BA moved less than both of these since it was last sent is not sent again
    # (each update goes whole). 0 = every update goes (docs/tuning.md).
    update_min_trans_m: float = 0.0  # [m]
    update_min_rot_deg: float = 0.0  # [deg]

    def validate(self) -> None:
        require(self.yield_max_s >= 0, "vo.mapping.yield_max_s must be >= 0 [s]")
        require(
            0 < self.fuse_radius_px < np.inf, "vo.mapping.fuse_radius_px must be finite and > 0"
        )
        require(self.cull_min_observations >= 2, "vo.mapping.cull_min_observations must be >= 2")
        require(
            self.update_min_trans_m >= 0 and self.update_min_rot_deg >= 0,
            "vo.mapping.update_min_trans_m and update_min_rot_deg must be >= 0",
        )


@dataclass
class TriangulationConfig:
    """New points of a keyframe triangulated with its covisible keyframes (monocular)."""

    neighbors: int = 20  # best covisible keyframes tried (ORB-SLAM2's 20)
    min_baseline_ratio: float = 0.01  # their baseline / median scene depth at least this
    max_descriptor_distance: int = 50  # Hamming gate (ORB-SLAM's TH_LOW) [bits]
    ratio: float = 0.9  # best / second best among keypoints on the epipolar line
    min_parallax_deg: float = 1.0  # rays meeting at less give no point [deg]

    def validate(self) -> None:
        require(self.neighbors >= 1, "vo.triangulation.neighbors must be >= 1")
        require(self.min_baseline_ratio >= 0, "vo.triangulation.min_baseline_ratio must be >= 0")
        require(
            0 < self.max_descriptor_distance <= 256,
            "vo.triangulation.max_descriptor_distance must be in 1..256",
        )
        require(0 < self.ratio <= 1.0, "vo.triangulation.ratio must be in (0, 1]")
        require(
            0 <= self.min_parallax_deg < 90, "vo.triangulation.min_parallax_deg must be in [0, 90)"
        )


@dataclass
class LocalBaConfig:
    """Local bundle adjustment of the newest keyframes and their points."""

    enabled: bool = True  # false: no local BA (the map keeps the poses tracking gave)
    window: int = 8  # keyframes optimized (newest + best covisible)
    max_fixed: int = 8  # keyframes held fixed around the window (most covisible first)
    iterations: int = 5  # Levenberg-Marquardt iterations per local BA
    huber_mono: float = 2.447  # Huber threshold of (u, v) factors [whitened px], sqrt(5.991)
    huber_stereo: float = 2.796  # Huber threshold of (u, v, u_right) factors, sqrt(7.815)
    # How much nicer (Linux nice, 0..19) the BA's process runs than the odometry: where both want
    # a core, tracking gets it; 0 = the same priority (docs/tuning.md).
    worker_nice: int = 10

    def validate(self) -> None:
        require(
            self.window >= 1 and self.iterations >= 1,
            "vo.ba needs a window and iterations (vo.ba.window, vo.ba.iterations >= 1)",
        )
        require(self.max_fixed >= 0, "vo.ba.max_fixed must be >= 0")
        require(0 <= self.worker_nice <= 19, "vo.ba.worker_nice must be in 0..19")


@dataclass
class PlanarConfig:
    """Ground robots: the camera sits fixed on a base that drives on one level floor, so it keeps
    its height and its tilt. Local BA then holds keyframes to that (soft) plane; it removes the
    pitch / height drift of views with little 3D structure (facing a wall in a turn). Off for
    hand-held, flying or legged cameras."""

    enabled: bool = False  # the camera is on a ground robot (client.launch ground_robot:=true)
    # The floor normal in the camera optical frame (level camera: -y); the client node takes it
    # from ~T_base_cam.
    up_cam: list = field(default_factory=lambda: [0.0, -1.0, 0.0])
    sigma_height_m: float = 0.01  # camera height std about its start height [m]
    sigma_tilt_deg: float = 0.2  # camera roll / pitch std about its start tilt [deg]

    def validate(self) -> None:
        require(
            len(self.up_cam) == 3 and np.linalg.norm(self.up_cam) > 0.5,
            "vo.planar.up_cam must be a unit 3-vector [x, y, z] in the camera optical frame",
        )
        require(
            self.sigma_height_m > 0 and self.sigma_tilt_deg > 0,
            "vo.planar.sigma_height_m and sigma_tilt_deg must be > 0",
        )


@dataclass
class MonoStartConfig:
    """A monocular map's start: a reference frame and a later one with enough parallax
    (vo.initialization)."""

    max_age_s: float = 2.0  # a reference older than this is replaced by the current frame [s]
    min_parallax_deg: float = 0.75  # median parallax the two views need [deg] (docs/tuning.md)
    # ... when the views fit a homography: with little translation its decomposition is poorly
    # conditioned (docs/tuning.md) [deg].
    min_parallax_homography_deg: float = 1.5

    def validate(self) -> None:
        require(self.max_age_s > 0, "vo.mono_init.max_age_s must be > 0")
        require(
            self.min_parallax_deg >= 0 and self.min_parallax_homography_deg >= 0,
            "vo.mono_init parallaxes must be >= 0",
        )


SECTIONS = (
    "features",
    "depth",
    "stereo",
    "calibration",
    "tracking",
    "relocalization",
    "keyframes",
    "mapping",
    "triangulation",
    "ba",
    "planar",
    "mono_init",
    "dense",
)
SENSOR_KINDS = ("rgbd", "stereo", "mono")


def _stereo_defaults() -> dict:
    # Two images to extract a frame: each level at FAST 20 first (features.py; KITTI 0.77x, EuRoC
    # 0.8x). Not for the others: the mixed team's monocular robot kept its scale worse with it
    # (team ATE 2.1, 1.0, 2.9 against 0.7, 1.1, 1.4 cm), the synthetic RGB-D robot's ATE spread
    # wider (median 0.52 against 0.40 cm over 10 runs), and RedKitchen's levels mostly fall back.
    return {"features": {"fast_threshold_first": 20}}


def _mono_defaults() -> dict:
    # ORB-SLAM2's monocular values: keyframes at a lower ratio of tracked points, but waiting for
    # local mapping and a few frames (else every other frame, baselines too short to triangulate);
    # points a third keyframe must see; a wider local BA window (the scale lives in the shared
    # points only; docs/tuning.md). With planar.enabled the height prior holds the scale and the
    # window is not widened.
    return {
        "keyframes": {"ref_ratio": 0.9, "min_frames": 4},
        "mapping": {"cull_min_observations": 3},
        "ba": {"window": 16, "max_fixed": 16},
    }


@dataclass
class VoConfig:
    """The client's visual odometry (section ``vo`` of config/client.yaml)."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    relocalization: RelocalizationConfig = field(default_factory=RelocalizationConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    ba: LocalBaConfig = field(default_factory=LocalBaConfig)
    planar: PlanarConfig = field(default_factory=PlanarConfig)
    mono_init: MonoStartConfig = field(default_factory=MonoStartConfig)
    dense: DenseDepthConfig = field(default_factory=DenseDepthConfig)
    threaded: bool = True  # local mapping in a background thread, BA in a worker process
    # Per camera kind (rgbd, stereo, mono), the values of the sections above that differ for it,
    # nested as above (given values merge with these key by key).
    sensors: dict = field(
        default_factory=lambda: {"stereo": _stereo_defaults(), "mono": _mono_defaults()}
    )

    def validate(self) -> None:
        for section in SECTIONS:
            getattr(self, section).validate()
        unknown = sorted(set(self.sensors) - set(SENSOR_KINDS))
        require(not unknown, f"vo.sensors: unknown camera kind(s) {unknown}; kinds: {SENSOR_KINDS}")
        for sensor in SENSOR_KINDS:
            self.for_sensor(sensor)  # every camera kind's values load (their keys are named)

    def for_sensor(self, sensor: str) -> "VoConfig":
        """The configuration of one camera kind's odometry: the sections with that kind's values
        on top (a ground robot's monocular camera keeps the common local BA window)."""
        overrides = dict(self.sensors.get(sensor) or {})
        if sensor == "mono" and self.planar.enabled:
            overrides.pop("ba", None)
        out = {}
        for section in SECTIONS:
            current = getattr(self, section)
            if section in overrides:
                values = merge_overrides(dataclasses.asdict(current), overrides.pop(section))
                prefix = f"vo.sensors.{sensor}.{section}."
                current = load_config(type(current), values, prefix=prefix)
            out[section] = current
        require(
            not overrides,
            f"vo.sensors.{sensor}: unknown section(s) {sorted(overrides)}; sections: "
            f"{list(SECTIONS)}",
        )
        return dataclasses.replace(self, **out)
