"""Global bundle adjustment of a merged group: every keyframe pose and map point of the group's
robots, in the group frame, refined together (GTSAM, through the client's BA solver).

Landmarks are the robots' map points, keyed ``(robot_id, map_point_id)``. Points that the server
matched across keyframes (merge and loop inliers) are *linked* and become one landmark, so the
maps are tied together by shared points, not only by the pose-graph constraints. Observations and
factors are those of :func:`coop_slam.vo.local_ba.run_local_ba` (stereo-like factor from depth,
projection factor without, Huber, sigma = scale**octave px); the gauge is the group's first
keyframe, held fixed. One camera model per problem: robots with different intrinsics are refused.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import require
from ..errors import CoopSlamError
from ..geometry import invert, transform_points
from ..vo.local_ba import BaProblem, run_local_ba

Key = tuple[int, int]  # (robot_id, keyframe_id)
Landmark = tuple[int, int]  # (robot_id, map_point_id)


class GlobalBaError(CoopSlamError):
    """A group the global bundle adjustment cannot take (no keyframes, mixed cameras, ...)."""


@dataclass
class GlobalBaConfig:
    iterations: int = 10  # Levenberg-Marquardt iterations
    min_observations: int = 2  # landmarks seen by fewer keyframes are left out
    virtual_baseline_m: float = 0.08  # of the stereo-like depth factor, as the client's [m]
    # depth noise sigma_z = depth_sigma_per_m2 * z^2 (Kinect-class) and a floor on the disparity
    # sigma: 1 px as ORB-SLAM, since real depth is not exactly registered to colour (measured on
    # RedKitchen: 0.05 px made the team map worse, 1-2 px better); exact synthetic depth: 0.05
    depth_sigma_per_m2: float = 1.425e-3
    min_disparity_sigma_px: float = 1.0
    min_depth_m: float = 0.3  # depth range used by that factor [m]
    max_depth_m: float = 6.0
    scale_factor: float = 1.2  # ORB pyramid of the clients
    n_levels: int = 8
    after_merge: bool = True  # run automatically after a merge when the problem is small enough
    auto_max_observations: int = 60000  # ... i.e. has at most this many observations

    def validate(self) -> None:
        require(self.iterations >= 1, "global_ba.iterations must be >= 1")
        require(self.min_observations >= 2, "global_ba.min_observations must be >= 2")
        require(self.virtual_baseline_m > 0, "global_ba.virtual_baseline_m must be > 0")
        require(
            0 < self.min_depth_m < self.max_depth_m, "global_ba: need 0 < min_depth_m < max_depth_m"
        )
        require(self.depth_sigma_per_m2 >= 0, "global_ba.depth_sigma_per_m2 must be >= 0")
        require(self.min_disparity_sigma_px > 0, "global_ba.min_disparity_sigma_px must be > 0")
        require(self.scale_factor > 1, "global_ba.scale_factor must be > 1")
        require(self.n_levels >= 1, "global_ba.n_levels must be >= 1")
        require(self.auto_max_observations >= 0, "global_ba.auto_max_observations must be >= 0")


@dataclass
class GlobalBaResult:
    poses: dict  # Key -> refined T_group_cam
    keyframes: int
    points: int
    observations: int
    outliers: int  # observations beyond the chi-square gate after optimization
    rms_before: float  # RMS reprojection error [px] of the inlier observations, before
    rms_after: float  # ... and after (robust: the 95 % best observations)
    time_ms: float


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


def _reprojection_rms_px(problem: BaProblem, T_map_cam: np.ndarray, points: np.ndarray) -> float:
    """RMS image reprojection error [px] over the best 95 % of the observations (outliers would
    dominate a plain RMS)."""
    T_cam_map = np.linalg.inv(T_map_cam)[problem.obs_kf]
    pc = np.einsum("nij,nj->ni", T_cam_map[:, :3, :3], points[problem.obs_pt]) + T_cam_map[:, :3, 3]
    z = np.maximum(pc[:, 2], 1e-6)
    du = problem.fx * pc[:, 0] / z + problem.cx - problem.obs_uv[:, 0]
    dv = problem.fy * pc[:, 1] / z + problem.cy - problem.obs_uv[:, 1]
    e2 = np.sort(du**2 + dv**2)
    return float(np.sqrt(np.mean(e2[: max(1, int(0.95 * len(e2)))])))


def count_observations(records) -> int:
    """Upper bound of a problem's size: keypoints with a map point over all keyframes."""
    return int(sum(np.count_nonzero(r.map_point_ids) for r in records))


def build_problem(records, T_group_cam: dict, links, fixed: set, config: GlobalBaConfig):
    """(BaProblem in the group frame, keyframe keys in problem order, number of landmarks)."""
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
    keys = [(r.robot_id, r.keyframe_id) for r in records]
    # Observations (keyframe index, landmark root, keypoint index) and a position per landmark.
    obs, seen_by, position = [], {}, {}
    for k, r in enumerate(records):
        # The keyframe's map points move with the keyframe's own (optimized) pose.
        T_group_map = T_group_cam[keys[k]] @ invert(r.T_map_cam)
        idx = np.flatnonzero(r.map_point_ids)
        points_group = transform_points(T_group_map, r.map_points_per_keypoint()[idx])
        for i, p in zip(idx.tolist(), points_group):
            root = lm.find((r.robot_id, int(r.map_point_ids[i])))
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
    with np.errstate(divide="ignore", invalid="ignore"):
        u_right = np.where(usable, uv[:, 0] - fx * config.virtual_baseline_m / depth, np.nan)
    problem = BaProblem(
        segment=0,
        kf_ids=np.arange(len(keys)),
        T_map_cam=np.array([T_group_cam[k] for k in keys]),
        fixed=np.array([k in fixed for k in keys]),
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
        disparity_sigma_px=max(
            config.min_disparity_sigma_px,
            fx * config.virtual_baseline_m * config.depth_sigma_per_m2,
        ),
    )
    return problem, keys, len(kept)


def global_bundle_adjustment(
    records,
    T_group_cam: dict,
    links=(),
    fixed: set | None = None,
    config: GlobalBaConfig | None = None,
) -> GlobalBaResult:
    """Refine the poses of ``records`` (keyframes of one group, initial poses ``T_group_cam``) and
    their map points; ``links`` are pairs of landmarks that are one physical point; ``fixed``
    keys hold the gauge (default: the first record's keyframe)."""
    config = config or GlobalBaConfig()
    config.validate()
    if not fixed and records:
        fixed = {(records[0].robot_id, records[0].keyframe_id)}
    problem, keys, n_points = build_problem(records, T_group_cam, links, fixed, config)
    res = run_local_ba(problem)
    if not res.ok:
        raise GlobalBaError(res.message)
    return GlobalBaResult(
        poses={k: T for k, T in zip(keys, res.T_map_cam)},
        keyframes=len(keys),
        points=n_points,
        observations=len(problem.obs_kf),
        outliers=int(np.count_nonzero(res.outlier_obs)),
        rms_before=_reprojection_rms_px(problem, problem.T_map_cam, problem.points_map),
        rms_after=_reprojection_rms_px(problem, res.T_map_cam, res.points_map),
        time_ms=res.time_ms,
    )
