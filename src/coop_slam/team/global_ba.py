"""Global bundle adjustment of a merged group: every keyframe pose and map point of the group's
robots, in the group frame, refined together (GTSAM, through the client's BA solver).

Landmarks are the maps' points, keyed ``(map_id, map_point_id)``. Points that the server
matched across keyframes (merge and loop inliers) are *linked* and become one landmark, so the
maps are tied together by shared points, not only by the pose-graph constraints. Observations and
factors are those of :func:`coop_slam.vo.local_ba.run_local_ba` (stereo-like factor from depth,
projection factor without, Huber, sigma = scale**octave px); the gauge is the group's first
keyframe, held fixed. One camera model per problem: robots with different intrinsics are refused.

Keyframes that share no map points with the fixed one (``component_min_shared``), directly or
through others (a low-bandwidth robot's keyframes pulled far apart), form a component whose pose
the images do not tie to the rest: each such component keeps its pose-graph placement (its first
keyframe is held too; without depth also the one farthest from it, for its scale), and only poses
within one component are refined against each other (``GlobalBaResult.components``). Within a
component, neighbouring keyframes of a metric map are also tied by the robot's own odometry
(weakly): what the shared points hardly measure keeps the shape the robot gave it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from ..config import require
from ..errors import CoopSlamError
from ..geometry import invert, se3, transform_points
from ..optim.bundle import BaProblem, run_local_ba
from ..registration.camera import RegistrationError
from ..registration.umeyama import umeyama
from .keyframe_store import is_mono

log = logging.getLogger(__name__)

Landmark = tuple[int, int]  # (robot_id, map_point_id)


class GlobalBaError(CoopSlamError):
    """A group the global bundle adjustment cannot take (no keyframes, mixed cameras, ...)."""


@dataclass
class GlobalBaConfig:
    """Bundle adjustment of a merged group's keyframes and points, after a merge or on request."""

    iterations: int = 10  # Levenberg-Marquardt iterations
    min_observations: int = 2  # landmarks seen by fewer keyframes are left out
    virtual_baseline_m: float = 0.08  # of the stereo-like depth factor, as the client's [m]
    # Noise of the measured disparity fx * baseline / depth [px]. 0: estimated from the data --
    # a first pass with a weak depth factor (1 px, as ORB-SLAM), then disparity_sigma_scale x the
    # robust spread (MAD) of its disparity residuals, within the range below: real depth that is
    # not exactly registered to colour comes out weak, good depth strong. > 0: that value, one
    # pass.
    disparity_sigma_px: float = 0.0
    disparity_sigma_scale: float = 2.0
    min_disparity_sigma_px: float = 0.03
    max_disparity_sigma_px: float = 1.0
    min_depth_m: float = 0.3  # depth range used by that factor [m]
    max_depth_m: float = 6.0
    scale_factor: float = 1.2  # ORB pyramid of the clients
    n_levels: int = 8
    # Ground robots (the clients' vo.planar.enabled): every keyframe is held softly at its robot's
    # camera height and tilt, as the clients' local BA holds it; without this the global BA frees
    # exactly what views with little 3D structure cannot fix (docs/tuning.md). The floor is the
    # group frame's xy plane (a map frame is its robot's base at the start, z up, REP-103).
    planar_motion: bool = False
    planar_sigma_height_m: float = 0.01  # [m]
    planar_sigma_tilt_deg: float = 0.2  # [deg]
    # Keyframes observing fewer landmarks together than this are not tied by them: each set of
    # keyframes tied so is held at its first keyframe (see the module docstring; ORB-SLAM's
    # covisibility graph uses 15).
    component_min_shared: int = 15
    after_merge: bool = True  # run automatically after a merge when the problem is small enough
    # A monocular map whose keyframes the BA bent by more than this share of their spread (RMS
    # of positions after a similarity to its poses before the BA, against their RMS distance from
    # their centroid) keeps its pose-graph poses: its keyframes share few points (a budgeted
    # client sends a third of them whole), which hold its scale along the path only weakly, while
    # the client's odometry holds it. Measured: 0.150 m on a ~12 m path bent by the BA; a share
    # keeps a group of monocular maps (in its own unit) judged alike.
    mono_max_bend: float = 0.01
    # Each metric map keeps the shape its robot's odometry gave it: consecutive keyframes of a map
    # segment are tied by their relative pose in the robot's map, with these sigmas plus the
    # per-metre ones times their distance (rotation [rad], translation [m]). A budgeted robot's
    # keyframes held whole can share few points across a gap, and without this the BA swung the
    # keyframes before such a gap as a block, which the images hardly measure; weak (4x the pose
    # graph's odometry sigmas), so that what the images do measure still moves them.
    # odometry_rot_sigma_rad or odometry_trans_sigma_m 0: no such prior.
    odometry_rot_sigma_rad: float = 0.02
    odometry_trans_sigma_m: float = 0.04
    odometry_rot_sigma_per_m: float = 0.02
    odometry_trans_sigma_per_m: float = 0.08
    auto_max_observations: int = 40000  # ... i.e. its keyframes hold at most this many map-point
    # observations (a few seconds on this machine)

    def validate(self) -> None:
        require(self.iterations >= 1, "global_ba.iterations must be >= 1")
        require(self.mono_max_bend > 0, "global_ba.mono_max_bend must be > 0 (a share)")
        require(self.min_observations >= 2, "global_ba.min_observations must be >= 2")
        require(self.virtual_baseline_m > 0, "global_ba.virtual_baseline_m must be > 0")
        require(
            0 < self.min_depth_m < self.max_depth_m, "global_ba: need 0 < min_depth_m < max_depth_m"
        )
        require(self.disparity_sigma_px >= 0, "global_ba.disparity_sigma_px must be >= 0")
        require(self.disparity_sigma_scale > 0, "global_ba.disparity_sigma_scale must be > 0")
        require(
            0 < self.min_disparity_sigma_px <= self.max_disparity_sigma_px,
            "global_ba: need 0 < min_disparity_sigma_px <= max_disparity_sigma_px",
        )
        require(self.scale_factor > 1, "global_ba.scale_factor must be > 1")
        require(self.n_levels >= 1, "global_ba.n_levels must be >= 1")
        require(self.component_min_shared >= 1, "global_ba.component_min_shared must be >= 1")
        require(self.auto_max_observations >= 0, "global_ba.auto_max_observations must be >= 0")
        for name in ("rot_sigma_rad", "trans_sigma_m", "rot_sigma_per_m", "trans_sigma_per_m"):
            require(
                getattr(self, f"odometry_{name}") >= 0, f"global_ba.odometry_{name} must be >= 0"
            )
        require(
            self.planar_sigma_height_m > 0 and self.planar_sigma_tilt_deg > 0,
            "global_ba: planar_sigma_height_m and planar_sigma_tilt_deg must be > 0",
        )


@dataclass
class GlobalBaResult:
    poses: dict  # KeyframeKey -> refined T_group_cam
    keyframes: int
    points: int
    observations: int
    outliers: int  # observations beyond the chi-square gate after optimization
    disparity_sigma_px: float  # disparity noise used in the (last) pass
    rms_before: float  # RMS reprojection error [px] of the inlier observations, before
    rms_after: float  # ... and after (robust: the 95 % best observations)
    time_ms: float
    # KeyframeKey -> component: keyframes tied by shared map points, directly or through others
    # (component 0 holds the fixed keyframe when it is in the group; each other one is held at
    # its first keyframe).
    components: dict = field(default_factory=dict)


class _Landmarks:
    """Union-find over (robot, map point id): linked points become one landmark."""

    def __init__(self):
        self.parent: dict[Landmark, Landmark] = {}

    def find(self, a: Landmark) -> Landmark:
        self.parent.setdefault(a, a)
        while self.parent[a] != a:
            self.parent[a] = self.parent[self.parent[a]]
            a = self.parent[a]
        return a

    def union(self, a: Landmark, b: Landmark) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def _points_cam(problem: BaProblem, T_map_cam: np.ndarray, points: np.ndarray, mask=None):
    """(O, 3) observed landmarks in their observing camera's frame (observations in ``mask``)."""
    mask = slice(None) if mask is None else mask
    T_cam_map = np.linalg.inv(T_map_cam)[problem.obs_kf[mask]]
    p_map = points[problem.obs_pt[mask]]
    return np.einsum("nij,nj->ni", T_cam_map[:, :3, :3], p_map) + T_cam_map[:, :3, 3]


def _reprojection_rms_px(problem: BaProblem, T_map_cam: np.ndarray, points: np.ndarray) -> float:
    """RMS image reprojection error [px] over the best 95 % of the observations (outliers would
    dominate a plain RMS)."""
    pc = _points_cam(problem, T_map_cam, points)
    z = np.maximum(pc[:, 2], 1e-6)
    du = problem.fx * pc[:, 0] / z + problem.cx - problem.obs_uv[:, 0]
    dv = problem.fy * pc[:, 1] / z + problem.cy - problem.obs_uv[:, 1]
    e2 = np.sort(du**2 + dv**2)
    return float(np.sqrt(np.mean(e2[: max(1, int(0.95 * len(e2)))])))


def disparity_spread_px(problem: BaProblem, T_map_cam: np.ndarray, points: np.ndarray) -> float:
    """Robust standard deviation (1.4826 MAD) of measured minus predicted disparity [px] over the
    observations with depth: how well the depth agrees with the geometry of the images."""
    stereo = np.isfinite(problem.obs_u_right)
    if not np.any(stereo):
        return float("nan")
    pc = _points_cam(problem, T_map_cam, points, stereo)
    d_pred = problem.fx * problem.baseline_m / np.maximum(pc[:, 2], 1e-6)
    r = problem.obs_uv[stereo, 0] - problem.obs_u_right[stereo] - d_pred
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def count_observations(records) -> int:
    """Upper bound of a problem's size: keypoints with a map point over all keyframes."""
    return int(sum(np.count_nonzero(r.map_point_ids) for r in records))


def keyframe_components(
    n_keyframes: int, obs_kf: np.ndarray, obs_pt: np.ndarray, min_shared: int = 1
) -> np.ndarray:
    """Component label per keyframe: two keyframes observing at least ``min_shared`` landmarks
    together are connected (a point or two leave their relative pose free)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    n_points = int(obs_pt.max()) + 1 if len(obs_pt) else 0
    seen = csr_matrix(
        (np.ones(len(obs_kf)), (obs_kf, obs_pt)), shape=(n_keyframes, n_points)
    )  # keyframe x landmark
    seen.data[:] = 1.0  # a keypoint observed twice in one keyframe counts once
    shared = (seen @ seen.T).tocoo()  # landmarks two keyframes observe together
    keep = shared.data >= min_shared
    graph = csr_matrix(
        (np.ones(int(keep.sum())), (shared.row[keep], shared.col[keep])),
        shape=(n_keyframes, n_keyframes),
    )
    _, labels = connected_components(graph, directed=False)
    return labels


def _hold_each_component(
    fixed: np.ndarray, labels: np.ndarray, metric: np.ndarray, positions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(fixed mask with the first keyframe of every component that has none held -- and, in a
    component without depth (``metric`` per keyframe: any usable depth), the keyframe farthest
    from it too, which holds its scale -- component per keyframe renumbered in order: the fixed
    keyframe's component first)."""
    fixed = fixed.copy()
    order = sorted(set(labels.tolist()), key=lambda c: (not fixed[labels == c].any(), c))
    for c in order:
        members = np.flatnonzero(labels == c)
        if not fixed[members].any():
            fixed[members[0]] = True
        if not metric[members].any() and len(members) > 1 and fixed[members].sum() < 2:
            first = members[fixed[members]][0]
            distance = np.linalg.norm(positions[members] - positions[first], axis=1)
            fixed[members[int(np.argmax(distance))]] = True
    renumber = {c: i for i, c in enumerate(order)}
    return fixed, np.array([renumber[c] for c in labels.tolist()], int)


def build_problem(records, T_group_cam: dict, links, fixed: set, config: GlobalBaConfig):
    """(BaProblem in the group frame, keyframe keys in problem order, number of landmarks,
    component per keyframe; see the module docstring)."""
    if not records:
        raise GlobalBaError("global BA: the group has no keyframes")
    K0 = records[0].camera.K
    for r in records:
        if not np.allclose(r.camera.K, K0, atol=1e-3):
            raise GlobalBaError(
                f"global BA needs one camera model; keyframe {r.keyframe_id} of robot {r.robot_id} "
                f"has fx={r.camera.K[0, 0]:.2f}, fy={r.camera.K[1, 1]:.2f} (first: {K0[0, 0]:.2f}, "
                f"{K0[1, 1]:.2f})"
            )
    lm = _Landmarks()
    for a, b in links:
        lm.union(tuple(a), tuple(b))
    keys = [(r.map_id, r.keyframe_id) for r in records]
    # Observations (keyframe index, landmark root, keypoint index) and a position per landmark.
    obs, seen_by, position = [], {}, {}
    for k, r in enumerate(records):
        # The keyframe's map points move with the keyframe's own (optimized) pose.
        T_group_map = T_group_cam[keys[k]] @ invert(r.T_map_cam)
        idx = np.flatnonzero(r.map_point_ids)
        points_group = transform_points(T_group_map, r.map_points_per_keypoint()[idx])
        for i, p in zip(idx.tolist(), points_group):
            root = lm.find((r.map_id, int(r.map_point_ids[i])))
            obs.append((k, root, i))
            seen_by.setdefault(root, set()).add(k)
            if np.all(np.isfinite(p)):
                position.setdefault(root, []).append(p)
    kept = sorted(
        root
        for root, ks in seen_by.items()
        if len(ks) >= config.min_observations and root in position
    )
    index = {root: j for j, root in enumerate(kept)}
    obs = [o for o in obs if o[1] in index]
    if not obs:
        raise GlobalBaError("global BA: no map point is seen by two keyframes of the group")
    obs_kf = np.array([o[0] for o in obs])
    obs_pt = np.array([index[o[1]] for o in obs])
    uv = np.array([records[k].keypoints[i, :2] for k, _, i in obs], float)
    depth = np.array([records[k].depths_m[i] for k, _, i in obs], float)
    octave = np.array([records[k].octaves[i] for k, _, i in obs], int)
    fx, fy, cx, cy = K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]
    usable = np.isfinite(depth) & (depth > config.min_depth_m) & (depth < config.max_depth_m)
    T_cams = np.array([T_group_cam[k] for k in keys])
    held, components = _hold_each_component(
        np.array([k in fixed for k in keys]),
        keyframe_components(len(keys), obs_kf, obs_pt, config.component_min_shared),
        np.bincount(obs_kf[usable], minlength=len(keys)) > 0,
        T_cams[:, :3, 3],
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        u_right = np.where(usable, uv[:, 0] - fx * config.virtual_baseline_m / depth, np.nan)
    problem = BaProblem(
        segment=0,
        kf_ids=np.arange(len(keys)),
        T_map_cam=T_cams,
        fixed=held,
        point_ids=np.arange(len(kept)),
        points_map=np.array([np.mean(position[root], axis=0) for root in kept]).reshape(-1, 3),
        obs_kf=obs_kf,
        obs_pt=obs_pt,
        obs_kp=np.array([o[2] for o in obs]),
        obs_uv=uv,
        obs_u_right=u_right,
        obs_octave=octave,
        fx=float(fx),
        fy=float(fy),
        cx=float(cx),
        cy=float(cy),
        baseline_m=config.virtual_baseline_m,
        scale_factor=config.scale_factor,
        n_levels=config.n_levels,
        iterations=config.iterations,
        disparity_sigma_px=config.disparity_sigma_px or config.max_disparity_sigma_px,
    )
    _add_odometry_priors(problem, records, components, config)
    if config.planar_motion:
        problem.planar_up_cam, problem.planar_T_map_plane = _planes(records, T_group_cam, keys)
        problem.planar_sigmas = (
            float(np.radians(config.planar_sigma_tilt_deg)),
            config.planar_sigma_height_m,
        )
    return problem, keys, len(kept), components


def _add_odometry_priors(problem: BaProblem, records, components, config: GlobalBaConfig):
    """The robots' own relative poses between neighbouring keyframes of a metric map segment,
    as weak priors (``odometry_*``), within a component only: one the images do not tie to the
    rest keeps its pose-graph placement, which a prior across would pull on."""
    if config.odometry_rot_sigma_rad <= 0 or config.odometry_trans_sigma_m <= 0:
        return
    pairs = [(i, j) for i, j in odometry_pairs(records) if components[i] == components[j]]
    if not pairs:
        return
    problem.between_pairs = np.array(pairs, int)
    problem.between_T = np.array(
        [invert(records[i].T_map_cam) @ records[j].T_map_cam for i, j in pairs]
    )
    dist_m = np.linalg.norm(problem.between_T[:, :3, 3], axis=1)
    problem.between_sigmas = np.column_stack(
        [
            config.odometry_rot_sigma_rad + config.odometry_rot_sigma_per_m * dist_m,
            config.odometry_trans_sigma_m + config.odometry_trans_sigma_per_m * dist_m,
        ]
    )


def odometry_pairs(records) -> list[tuple[int, int]]:
    """Indices (i, j) of consecutive keyframes (by id) of one metric map segment, which its
    robot's odometry relates. A monocular map's poses are in its own unit, not the group's: it
    has none (its scale drifts; see unbent_mono)."""
    last: dict[tuple[int, int], int] = {}
    pairs = []
    by_id = sorted(range(len(records)), key=lambda i: (records[i].map_id, records[i].keyframe_id))
    for j in by_id:
        rec = records[j]
        if is_mono(rec):
            continue
        seg = (rec.map_id, int(rec.map_segment))
        if seg in last:
            pairs.append((last[seg], j))
        last[seg] = j
    return pairs


def _planes(records, T_group_cam: dict, keys) -> tuple[np.ndarray, np.ndarray]:
    """Per keyframe: (floor normal in the camera frame (K, 3), its robot's camera plane in the
    group frame (K, 4, 4)). The robots share one floor, the group frame's xy plane (the root's
    map is its base at the start, z up), so a merge that tilted a map is levelled too; each robot
    keeps its own camera height on it (median of its keyframes) and its camera tilt (mean floor
    normal seen in its client's poses)."""
    up_cam, T_group_plane = np.zeros((len(keys), 3)), np.zeros((len(keys), 4, 4))
    for robot in sorted({k[0] for k in keys}):
        idx = [i for i, k in enumerate(keys) if k[0] == robot]
        up = np.mean([records[i].T_map_cam[2, :3] for i in idx], axis=0)  # R^T e_z per camera
        height = float(np.median([T_group_cam[keys[i]][2, 3] for i in idx]))
        up_cam[idx] = up / np.linalg.norm(up)
        T_group_plane[idx] = se3(np.eye(3), [0.0, 0.0, height])
    return up_cam, T_group_plane


def global_bundle_adjustment(
    records,
    T_group_cam: dict,
    links=(),
    fixed: set | None = None,
    config: GlobalBaConfig | None = None,
) -> GlobalBaResult:
    """Refine the poses of ``records`` (stored keyframes of one group, keyed by their map: initial
    poses ``T_group_cam``) and
    their map points; ``links`` are pairs of landmarks that are one physical point; ``fixed``
    keys hold the gauge (default: the first record's keyframe)."""
    config = config or GlobalBaConfig()
    config.validate()
    if not fixed and records:
        fixed = {(records[0].map_id, records[0].keyframe_id)}
    problem, keys, n_points, components = build_problem(records, T_group_cam, links, fixed, config)
    res = run_local_ba(problem)
    if not res.ok:
        raise GlobalBaError(res.message)
    time_ms, sigma = res.time_ms, problem.disparity_sigma_px
    if config.disparity_sigma_px == 0:
        spread = disparity_spread_px(problem, res.T_map_cam, res.points_map)
        if np.isfinite(spread):
            sigma = float(
                np.clip(
                    config.disparity_sigma_scale * spread,
                    config.min_disparity_sigma_px,
                    config.max_disparity_sigma_px,
                )
            )
            second = replace(
                problem,
                disparity_sigma_px=sigma,
                T_map_cam=res.T_map_cam,
                points_map=res.points_map,
            )
            res = run_local_ba(second)
            if not res.ok:
                raise GlobalBaError(res.message)
            time_ms += res.time_ms
    result = GlobalBaResult(
        poses={k: T for k, T in zip(keys, res.T_map_cam)},
        keyframes=len(keys),
        points=n_points,
        observations=len(problem.obs_kf),
        outliers=int(np.count_nonzero(res.outlier_obs)),
        disparity_sigma_px=sigma,
        rms_before=_reprojection_rms_px(problem, problem.T_map_cam, problem.points_map),
        rms_after=_reprojection_rms_px(problem, res.T_map_cam, res.points_map),
        time_ms=time_ms,
        components={k: int(c) for k, c in zip(keys, components)},
    )
    mono_maps = {rec.map_id for rec in records if is_mono(rec)}
    return unbent_mono(result, T_group_cam, mono_maps, config.mono_max_bend)


def unbent_mono(
    result: GlobalBaResult, T_group_cam: dict, mono_maps: set, share: float
) -> GlobalBaResult:
    """``result`` without the keyframes of a monocular map the BA bent: its refined positions
    fit its poses before the BA (``T_group_cam``) by a similarity no closer than ``share`` of
    their spread (RMS); such a map keeps its poses from before (the pose graph's, the client's
    odometry)."""
    poses, components = dict(result.poses), dict(result.components)
    for m in sorted(mono_maps):
        keys = [k for k in poses if k[0] == m]
        if len(keys) < 3:
            continue
        src = np.array([T_group_cam[k][:3, 3] for k in keys])
        dst = np.array([poses[k][:3, 3] for k in keys])
        try:
            T, s = umeyama(src, dst, with_scale=True)
        except RegistrationError:
            continue
        fitted = s * src @ T[:3, :3].T + T[:3, 3]
        bend = float(np.sqrt(np.mean(np.sum((fitted - dst) ** 2, axis=1))))
        spread = float(np.sqrt(np.mean(np.sum((dst - dst.mean(axis=0)) ** 2, axis=1))))
        if bend > share * spread:
            log.warning(
                "global BA bent map %s's keyframes by %.1f %% of their spread (> %.1f %%): it "
                "keeps its pose-graph poses",
                m,
                100 * bend / spread,
                100 * share,
            )
            for k in keys:
                poses.pop(k)
                components.pop(k, None)
    return replace(result, poses=poses, components=components)
