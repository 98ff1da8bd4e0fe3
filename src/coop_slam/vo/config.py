"""Parameters of the client's RGB-D, stereo or monocular visual odometry (features, tracking,
keyframes, local mapping).

Loaded with :func:`coop_slam.config.load_config` / ``load_yaml_config`` (section ``vo`` of
``config/client.yaml``). Units are in the field names or comments; pixel thresholds refer to pyramid
level 0 and are scaled by ``scale_factor ** octave`` where the comment says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import require


@dataclass
class VoConfig:
    # --- ORB features -----------------------------------------------------------------------------
    n_features: int = 1000  # keypoints kept per frame after grid bucketing
    n_detect: int = 2500  # FAST candidates detected before bucketing (>= n_features)
    scale_factor: float = 1.2  # pyramid scale between levels
    n_levels: int = 8  # pyramid levels
    fast_threshold: int = 7  # FAST threshold [grey levels]; low, the grid keeps the best per cell
    grid_cell_px: int = 40  # bucketing cell size at level 0 [px]; scaled by scale_factor**octave
    edge_threshold_px: int = 19  # border without features [px] (ORB patch radius)
    min_depth_m: float = 0.3  # keypoint depths outside [min, max] are treated as missing [m]
    max_depth_m: float = 6.0
    depth_edge_px: int = 0  # depth within this radius must agree, else the keypoint gets none [px]
    depth_edge_ratio: float = 0.05  # ... agree = within this fraction of the depth
    close_depth_m: float = 6.0  # depth used in the stereo-like residual up to here [m]; its pixel
    # sigma already makes the depth uncertainty grow with z^2, so no hard cut is needed for RGB-D
    virtual_baseline_m: float = 0.08  # baseline of the virtual stereo pair built from depth [m]

    # --- stereo (rectified pairs; ORB-SLAM2's stereo matching) ----------------------------------
    stereo_max_descriptor_distance: int = 75  # Hamming gate of a left/right match [bits]
    stereo_row_tolerance_px: float = 2.0  # rows of a match differ by at most this x level scale
    stereo_patch_radius_px: int = 5  # patch radius of the subpixel refinement [level px]
    stereo_search_px: int = 5  # columns searched either side of the descriptor match [level px]
    # Points farther than this many baselines are used without depth: their disparity is a few
    # pixels and its error dominates (ORB-SLAM2's 40).
    stereo_close_baselines: float = 40.0

    # --- colour / depth calibration ---------------------------------------------------------------
    # Colour intrinsics overriding the camera model given to the odometry (0 = use the model) [px].
    color_fx: float = 0.0
    color_fy: float = 0.0
    color_cx: float = 0.0
    color_cy: float = 0.0
    # Depth camera intrinsics when the depth image is NOT registered to the colour image (0 = it is,
    # pixel (u, v) of both images sees the same point) [px].
    depth_fx: float = 0.0
    depth_fy: float = 0.0
    depth_cx: float = 0.0
    depth_cy: float = 0.0
    # Position of the depth camera's optical centre in the colour camera frame (rotation assumed
    # identity), i.e. the translation of T_color_depth [m]. Used only with depth_fx > 0.
    depth_in_color_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])

    # --- tracking ---------------------------------------------------------------------------------
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

    # --- PnP / relocalization ---------------------------------------------------------------------
    pnp_ratio: float = 0.8  # Lowe ratio for brute-force descriptor matching
    pnp_reprojection_px: float = 4.0  # RANSAC inlier threshold [px]
    pnp_iterations: int = 200  # RANSAC iterations
    pnp_min_inliers: int = 20  # fewer RANSAC inliers = failure
    reloc_keyframes: int = 15  # recent keyframes tried for relocalization
    reloc_keyframes_per_frame: int = 5  # keyframes tried per lost frame (bounds the time per frame)
    reloc_min_inliers: int = 50  # pose inliers needed to accept a relocalization
    max_lost_frames: int = 10  # lost frames before a new map segment is started
    # ... more while a server-assisted relocalization is under way (the team's local map asked)
    assist_wait_frames: int = 30

    # --- keyframes --------------------------------------------------------------------------------
    # Keypoints with depth needed to start a map (monocular: points the two views triangulate).
    min_init_points: int = 100
    keyframe_max_frames: int = 30  # insert a keyframe at least this often (if tracking is weak)
    keyframe_min_frames: int = 0  # never insert two keyframes closer than this in frames
    # ORB-SLAM2 RGB-D value; 0.6 made 2.5x fewer keyframes on RedKitchen and 0.5-0.9 cm more ATE
    keyframe_ref_ratio: float = 0.75  # tracked / reference keyframe points below this -> keyframe
    keyframe_close_tracked: int = 100  # "too few close points": tracked close < this ...
    keyframe_close_untracked: int = 70  # ... and untracked close > this
    keyframe_min_tracked: int = 250  # fewer tracked points than this -> keyframe (0 = off)
    keyframe_min_inliers: int = 15  # a keyframe needs at least this many tracked points

    # --- local mapping ----------------------------------------------------------------------------
    threaded: bool = True  # local mapping in a background thread, BA in a worker process
    # Mapping steps wait for the frame being tracked, at most this long [s] (see local_mapping).
    mapping_yield_max_s: float = 0.1
    new_points_max: int = 600  # new map points created per keyframe from depth (closest first)
    fuse_neighbors: int = 10  # covisible keyframes searched to fuse duplicate points
    fuse_radius_px: float = 3.0  # projection search radius for fusion [px], scaled by octave
    cull_found_ratio: float = 0.25  # recent points found / visible below this are removed
    cull_min_observations: int = 2  # recent points seen by fewer keyframes after 2 KFs are removed
    ba_enabled: bool = True
    ba_window: int = 8  # keyframes optimized by local BA (newest + best covisible)
    ba_max_fixed: int = 8  # keyframes held fixed around the window (most covisible first)
    # A free-moving monocular camera's scale is held only by its keyframes' shared points: a wider
    # window keeps it from drifting (see the monocular section of config/client.yaml). RGB-D and
    # stereo measure scale in every keyframe; with planar_motion the height prior holds a monocular
    # map's scale and these are not used (wider windows measured worse there).
    ba_window_mono: int = 16
    ba_max_fixed_mono: int = 16
    ba_iterations: int = 5  # Levenberg-Marquardt iterations per local BA
    ba_huber_mono: float = 2.447  # Huber threshold of (u, v) factors [whitened px], sqrt(5.991)
    ba_huber_stereo: float = 2.796  # Huber threshold of (u, v, u_right) factors, sqrt(7.815)
    # A keyframe local BA moved less than both of these since it was last sent is not sent again
    # (each update goes whole). Off by default: on RedKitchen as 2 robots, 2 mm /
    # 0.05 deg cut the keyframe stream 2.7 -> 1.1 MB/s per robot but cost 0.2-0.3 cm team ATE.
    update_min_trans_m: float = 0.0  # [m]
    update_min_rot_deg: float = 0.0  # [deg]
    # Ground robot: the camera sits fixed on a base that drives on one level floor, so it keeps
    # its height and its tilt. Local BA then holds keyframes to that (soft) plane; it removes the
    # pitch / height drift of views with little 3D structure (facing a wall in a turn). Off for
    # hand-held, flying or legged cameras.
    planar_motion: bool = False
    planar_up_cam: list = field(default_factory=lambda: [0.0, -1.0, 0.0])  # floor normal in the
    # camera optical frame (level camera: -y); the client node takes it from ~T_base_cam
    planar_sigma_height_m: float = 0.01  # camera height std about its start height [m]
    planar_sigma_tilt_deg: float = 0.2  # camera roll / pitch std about its start tilt [deg]
    kf_culling: bool = True
    kf_cull_redundancy: float = 0.9  # fraction of points seen by >= kf_cull_observers other KFs
    kf_cull_observers: int = 3

    # --- monocular cameras (no depth: two-view initialization, points from triangulation) -------
    # The map starts from a reference frame and a later one with enough parallax
    # (vo.initialization); a reference older than this is replaced by the current frame [s].
    mono_init_max_age_s: float = 2.0
    # Median parallax the two views need [deg]. ORB-SLAM's 1 deg (for a different statistic: its
    # 51st largest parallax) kept a robot driving down the synthetic revisit corridor waiting
    # 1.07 s; 0.75 initializes it in 0.93 s, as accurately (each point still needs 1 deg).
    mono_init_min_parallax_deg: float = 0.75
    # ... when the views fit a homography. With little translation its decomposition is poorly
    # conditioned: on RedKitchen a homography at 1.2 deg median parallax (3 cm baseline) was off
    # by 2.5 deg in rotation and 105 deg in translation direction, and the map it started lost
    # its scale (Sim(3) ATE 38 cm; waiting for 1.5 deg: 3.6 cm).
    mono_init_min_parallax_homography_deg: float = 1.5
    keyframe_ref_ratio_mono: float = 0.9  # ORB-SLAM2's monocular keyframe_ref_ratio
    # A monocular keyframe waits for local mapping to be free (ORB-SLAM2), and at least this many
    # frames after the last one: in lock-step local mapping is always free by the next frame, and
    # without a floor every other frame became a keyframe (baselines too short to triangulate).
    keyframe_min_frames_mono: int = 4
    # Points seen by fewer keyframes 2 keyframes after their creation are removed (ORB-SLAM2's
    # monocular 3: a point triangulated from 2 keyframes that no third one sees is suspect).
    cull_min_observations_mono: int = 3
    # New points of a keyframe: triangulated with its best covisible keyframes (ORB-SLAM2's 20)
    # whose baseline is at least this fraction of their median scene depth.
    triangulation_neighbors: int = 20
    triangulation_min_baseline_ratio: float = 0.01
    triangulation_max_descriptor_distance: int = 50  # Hamming gate (ORB-SLAM's TH_LOW) [bits]
    triangulation_ratio: float = 0.9  # best / second best among keypoints on the epipolar line
    triangulation_min_parallax_deg: float = 1.0  # rays meeting at less give no point [deg]

    @property
    def depth_registered(self) -> bool:
        return self.depth_fx <= 0

    def color_camera(self, camera):
        """``camera`` with the colour intrinsics overridden where this config sets them."""
        import dataclasses

        return dataclasses.replace(
            camera,
            fx=self.color_fx or camera.fx,
            fy=self.color_fy or camera.fy,
            cx=self.color_cx or camera.cx,
            cy=self.color_cy or camera.cy,
        )

    def validate(self) -> None:
        require(self.n_features > 0, "vo.n_features must be positive")
        require(self.n_detect >= self.n_features, "vo.n_detect must be >= vo.n_features")
        require(self.scale_factor > 1.0, "vo.scale_factor must be > 1")
        require(1 <= self.n_levels <= 16, "vo.n_levels must be in 1..16")
        require(0 < self.fast_threshold < 256, "vo.fast_threshold must be in 1..255")
        require(self.grid_cell_px >= 8, "vo.grid_cell_px must be >= 8")
        require(0 < self.min_depth_m < self.max_depth_m, "need 0 < vo.min_depth_m < vo.max_depth_m")
        require(self.virtual_baseline_m > 0, "vo.virtual_baseline_m must be positive")
        require(
            0 < self.stereo_max_descriptor_distance <= 256,
            "vo.stereo_max_descriptor_distance must be in 1..256",
        )
        require(self.stereo_row_tolerance_px > 0, "vo.stereo_row_tolerance_px must be > 0")
        require(self.stereo_patch_radius_px >= 1, "vo.stereo_patch_radius_px must be >= 1")
        require(self.stereo_search_px >= 1, "vo.stereo_search_px must be >= 1")
        require(self.stereo_close_baselines > 0, "vo.stereo_close_baselines must be > 0")
        require(len(self.depth_in_color_m) == 3, "vo.depth_in_color_m must be [x, y, z] in metres")
        depth_intr = (self.depth_fx, self.depth_fy, self.depth_cx, self.depth_cy)
        require(
            all(v == 0 for v in depth_intr) or (self.depth_fx > 0 and self.depth_fy > 0),
            "vo.depth_fx and vo.depth_fy must both be > 0 when the depth camera is given",
        )
        require(
            self.search_radius_px > 0 and self.search_radius_refine_px > 0,
            "search radii must be > 0",
        )
        require(
            0 < self.max_descriptor_distance <= 256, "vo.max_descriptor_distance must be in 1..256"
        )
        require(0 < self.ratio_test <= 1.0, "vo.ratio_test must be in (0, 1]")
        require(self.min_tracked >= 6, "vo.min_tracked must be >= 6")
        require(
            self.pose_iterations > 0 and self.pose_rounds > 0, "pose optimization needs iterations"
        )
        require(0 < self.keyframe_ref_ratio <= 1.0, "vo.keyframe_ref_ratio must be in (0, 1]")
        require(self.max_lost_frames >= 0, "vo.max_lost_frames must be >= 0")
        require(self.mapping_yield_max_s >= 0, "vo.mapping_yield_max_s must be >= 0 [s]")
        require(self.assist_wait_frames >= 0, "vo.assist_wait_frames must be >= 0")
        require(
            self.max_speed_m_s > 0 and self.max_turn_rate_deg_s > 0,
            "vo.max_speed_m_s and vo.max_turn_rate_deg_s must be > 0",
        )
        require(
            self.ba_window >= 1 and self.ba_window_mono >= 1 and self.ba_iterations >= 1,
            "local BA needs a window (vo.ba_window, vo.ba_window_mono) and iterations",
        )
        require(
            self.ba_max_fixed >= 0 and self.ba_max_fixed_mono >= 0,
            "vo.ba_max_fixed and vo.ba_max_fixed_mono must be >= 0",
        )
        require(
            len(self.planar_up_cam) == 3 and np.linalg.norm(self.planar_up_cam) > 0.5,
            "vo.planar_up_cam must be a unit 3-vector [x, y, z] in the camera optical frame",
        )
        require(
            self.planar_sigma_height_m > 0 and self.planar_sigma_tilt_deg > 0,
            "vo.planar_sigma_height_m and vo.planar_sigma_tilt_deg must be > 0",
        )
        require(0 < self.kf_cull_redundancy <= 1.0, "vo.kf_cull_redundancy must be in (0, 1]")
        require(self.mono_init_max_age_s > 0, "vo.mono_init_max_age_s must be > 0")
        require(self.mono_init_min_parallax_deg >= 0, "vo.mono_init_min_parallax_deg must be >= 0")
        require(
            self.mono_init_min_parallax_homography_deg >= 0,
            "vo.mono_init_min_parallax_homography_deg must be >= 0",
        )
        require(
            0 < self.keyframe_ref_ratio_mono <= 1.0, "vo.keyframe_ref_ratio_mono must be in (0, 1]"
        )
        require(
            self.keyframe_min_frames_mono >= 0, "vo.keyframe_min_frames_mono must be >= 0 [frames]"
        )
        require(self.cull_min_observations_mono >= 2, "vo.cull_min_observations_mono must be >= 2")
        require(self.triangulation_neighbors >= 1, "vo.triangulation_neighbors must be >= 1")
        require(
            self.triangulation_min_baseline_ratio >= 0,
            "vo.triangulation_min_baseline_ratio must be >= 0",
        )
        require(
            0 < self.triangulation_max_descriptor_distance <= 256,
            "vo.triangulation_max_descriptor_distance must be in 1..256",
        )
        require(0 < self.triangulation_ratio <= 1.0, "vo.triangulation_ratio must be in (0, 1]")
        require(
            0 <= self.triangulation_min_parallax_deg < 90,
            "vo.triangulation_min_parallax_deg must be in [0, 90)",
        )
        require(
            self.update_min_trans_m >= 0 and self.update_min_rot_deg >= 0,
            "vo.update_min_trans_m and vo.update_min_rot_deg must be >= 0",
        )
