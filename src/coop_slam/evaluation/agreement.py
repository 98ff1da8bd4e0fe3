"""How well robots' maps agree where they overlap, without ground truth.

Once a team map is stitched, every keyframe carries its optimized pose in the merged group's frame
and its 3D points (from RGB-D or stereo depth) in its camera frame. Where two robots mapped the same
surface, a good stitch puts their points on one surface; a stitch off by a few centimetres or
degrees doubles it. This module measures that gap and compares it with the best one can expect from
the same sensors and the same SLAM: the gap between a robot's map and itself where it came back to
a place (its self-agreement).

Definitions (all in :class:`AgreementConfig`):

* **Point-to-plane distance** of a point p against a reference cloud: the reference points within
  ``radius_m`` (5 cm) of p -- the nearest 32 of them, at least ``min_neighbours`` (6) -- define a
  local plane by PCA (centroid; normal = eigenvector of the smallest eigenvalue of their
  covariance). The plane is used only when the neighbourhood is planar: smallest eigenvalue <=
  ``max_planarity`` (0.25) x the middle one. On a 3-5 cm patch that keeps walls with 5 mm depth
  noise (ratio ~0.05-0.1) and most with 1 cm (~0.2-0.35), and drops patches straddling an edge or
  corner (~0.3-0.5) and clutter, where a plane is no model of the surface; noisier depth needs a
  larger radius. Planarity is judged on the reference points only, so a misaligned query point is
  never dropped for being misaligned. The distance is ``|normal . (p - centroid)|``. Points
  without such a neighbourhood are not in the overlap and are left out.
* **inter** (robots a, b): distances of a's points against b's cloud and of b's points against a's,
  pooled.
* **intra / self-agreement** (robot r): distances of r's points against r's own cloud, using only
  reference points observed at least ``min_revisit_s`` before or after the query point -- never its
  own temporal neighbours, which agree trivially. For a pair, the distances of those of a and b
  that revisit enough (see ``min_points``) are pooled.
* **Statistic**: a trimmed RMS -- the RMS of the distances after dropping the largest
  ``trim_fraction`` (10 %) of them. Dropping the tail makes it robust to what no plane explains
  (mixed pixels at silhouettes, people walking by, a non-planar neighbourhood that slips through
  the planarity test); every distance is below ``radius_m`` anyway, so the tail is bounded. It is
  preferred to the median because a misalignment usually shows on part of the overlap only -- a
  shift moves only the surfaces it crosses, a yaw error mostly the far ones -- and the median does
  not move until more than half of the points do: in the tests' room, a 3 cm shift along x (seen
  by the x walls only) takes the median from ~3.4 to ~6.5 mm, the trimmed RMS from ~4 to ~16 mm.
  The trimmed RMS still ignores a misalignment seen by fewer than ~10 % of the points. With
  Gaussian noise of sigma per point it reads ~0.8 sigma when aligned (5 mm noise -> ~3.9 mm). A
  figure needs ``min_points`` distances; fewer gives None ("no overlap" / "no revisits").

Both inter and intra compare a noisy point with a plane fitted to the other side's noisy points,
with the same neighbourhoods, so sensor noise enters both alike: a perfect stitch gives inter ~
intra, a misaligned one inter > intra. Limits worth knowing when reading the figures:

* A point-to-plane distance cannot see one map sliding *along* a surface (a corridor shifted along
  its axis); only shifts across some of the overlapping surfaces show.
* Distances are bounded by ``radius_m``: a misalignment much larger than the radius does not raise
  inter, it empties the overlap (``inter_points`` drops, eventually to None), so read the counts
  along with the figure.
* The result is only meaningful for robots in one frame: call it once per merged group.

Speed: each robot's points are thinned on a ``voxel_m`` grid to the earliest and the latest
observation of each voxel (so every revisit of a surface keeps a point with its own time, and
reference density is bounded whatever the number of keyframes), at most ``max_queries`` of them
(fixed-seed sample: deterministic) are used as query points, and neighbourhoods are k-nearest
queries in a cKDTree with batched 3x3 eigen-decompositions: 3 robots x 300 keyframes x 1000
points take ~0.6 s of one core. Pure numpy/scipy, no ROS.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..errors import CoopSlamError, GeometryError
from ..geometry import check_se3

# Neighbours looked at per query point (the nearest within radius_m): fewer than a thinned
# surface ball holds, for speed at a small cost in the figures (docs/tuning.md).
_MAX_NEIGHBOURS = 32
_QUERY_SEED = 0  # fixed: the query sample (and so every figure) is the same on every call


class AgreementError(CoopSlamError):
    """Invalid agreement configuration or keyframe clouds (shapes, non-finite poses, ...)."""


@dataclass(eq=False)
class KeyframeCloud:
    """One keyframe as placed in the team map: its stamp, its optimized pose in the merged group's
    frame and its 3D points (N, 3) in its camera frame (NaN rows = no depth, ignored)."""

    stamp_s: float
    T_group_cam: np.ndarray
    points_cam: np.ndarray


@dataclass
class AgreementConfig:
    radius_m: float = 0.05  # neighbourhood of a point on the other side's surface
    min_neighbours: int = 6  # reference points needed in the neighbourhood to fit a plane
    voxel_m: float = 0.02  # thinning grid (earliest + latest observation kept per voxel)
    min_revisit_s: float = 3.0  # self-agreement: reference observed at least this long apart
    min_points: int = 200  # distances needed for a figure (else None)
    max_planarity: float = 0.25  # plane accepted when eig_min <= this x eig_mid
    max_queries: int = 5000  # query points per robot (fixed-seed sample beyond)
    trim_fraction: float = 0.1  # largest distances left out of the RMS

    def validate(self) -> "AgreementConfig":
        def require(ok: bool, message: str) -> None:
            if not ok:
                raise AgreementError(f"agreement config: {message}")

        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            require(
                isinstance(value, (int, float, np.integer, np.floating))
                and not isinstance(value, bool),
                f"{name} must be a number, got {value!r}",
            )
        require(
            math.isfinite(self.radius_m) and self.radius_m > 0,
            f"radius_m must be a finite length > 0 [m], got {self.radius_m}",
        )
        require(
            math.isfinite(self.voxel_m) and 0 < self.voxel_m <= self.radius_m / 2,
            f"voxel_m must be > 0 and at most radius_m / 2 = {self.radius_m / 2} so a "
            f"neighbourhood spans several voxels, got {self.voxel_m}",
        )
        require(
            int(self.min_neighbours) == self.min_neighbours
            and 3 <= self.min_neighbours <= _MAX_NEIGHBOURS,
            f"min_neighbours must be an integer in [3, {_MAX_NEIGHBOURS}] (a plane needs 3 "
            f"points), got {self.min_neighbours}",
        )
        require(
            math.isfinite(self.min_revisit_s) and self.min_revisit_s >= 0,
            f"min_revisit_s must be >= 0 [s], got {self.min_revisit_s}",
        )
        require(
            int(self.min_points) == self.min_points and self.min_points >= 1,
            f"min_points must be an integer >= 1, got {self.min_points}",
        )
        require(
            math.isfinite(self.max_planarity) and 0 < self.max_planarity < 1,
            f"max_planarity must be in (0, 1) (eig_min / eig_mid of a planar neighbourhood), got "
            f"{self.max_planarity}",
        )
        require(
            int(self.max_queries) == self.max_queries and self.max_queries >= self.min_points,
            f"max_queries must be an integer >= min_points = {self.min_points}, got "
            f"{self.max_queries}",
        )
        require(
            math.isfinite(self.trim_fraction) and 0 <= self.trim_fraction <= 0.5,
            f"trim_fraction must be in [0, 0.5] (share of the largest distances dropped), got "
            f"{self.trim_fraction}",
        )
        return self


@dataclass
class TeamAgreement:
    """Everything :func:`team_agreement` measured: the pairs (see :func:`overlap_agreement`) and
    each robot's self-agreement [m] (None: too few revisited points)."""

    pairs: list[dict] = field(default_factory=list)
    self_m: dict[int, float | None] = field(default_factory=dict)
    self_points: dict[int, int] = field(default_factory=dict)


@dataclass
class _RobotCloud:
    """A robot's thinned cloud in the group frame, its stamps, its query subset and its tree."""

    points_group: np.ndarray  # (M, 3)
    stamps_s: np.ndarray  # (M,)
    query: np.ndarray  # indices into points_group
    tree: cKDTree | None  # None when the robot has no points
    lo_group: np.ndarray | None = None  # bounding box of points_group
    hi_group: np.ndarray | None = None


def as_keyframe_clouds(robot_id, keyframes) -> list[KeyframeCloud]:
    """Checked :class:`KeyframeCloud` list from KeyframeClouds or (stamp_s, T_group_cam,
    points_cam) tuples; raises AgreementError naming the robot and keyframe at fault."""
    if isinstance(keyframes, (str, bytes)) or not hasattr(keyframes, "__iter__"):
        raise AgreementError(
            f"robot {robot_id}: expected a list of keyframe clouds, got {type(keyframes).__name__}"
        )
    out = []
    for k, kf in enumerate(keyframes):
        where = f"robot {robot_id}, keyframe {k}"
        if not isinstance(kf, KeyframeCloud):
            if not isinstance(kf, (tuple, list)) or len(kf) != 3:
                raise AgreementError(
                    f"{where}: expected a KeyframeCloud or a (stamp_s, T_group_cam, points_cam) "
                    f"tuple, got {type(kf).__name__}"
                )
            kf = KeyframeCloud(*kf)
        try:
            stamp_s = float(kf.stamp_s)
        except (TypeError, ValueError):
            raise AgreementError(f"{where}: stamp_s {kf.stamp_s!r} is not a number") from None
        if not math.isfinite(stamp_s):
            raise AgreementError(f"{where}: stamp_s is {stamp_s}, expected a finite time [s]")
        try:
            T = check_se3(np.asarray(kf.T_group_cam, dtype=float), f"{where}: T_group_cam")
        except (GeometryError, TypeError, ValueError) as exc:
            raise AgreementError(str(exc)) from None
        points_cam = np.asarray(kf.points_cam, dtype=float)
        if points_cam.ndim != 2 or points_cam.shape[1] != 3:
            raise AgreementError(
                f"{where}: points_cam has shape {points_cam.shape}, expected (N, 3) camera-frame "
                "points"
            )
        out.append(KeyframeCloud(stamp_s, T, points_cam))
    return out


def _robot_cloud(keyframes: list[KeyframeCloud], config: AgreementConfig) -> _RobotCloud:
    """Points in the group frame thinned to the earliest and latest observation per voxel."""
    keyframes = sorted(keyframes, key=lambda kf: kf.stamp_s)  # stable: ties keep input order
    chunks, stamps = [], []
    for kf in keyframes:
        pts = kf.points_cam[np.all(np.isfinite(kf.points_cam), axis=1)]
        chunks.append(pts @ kf.T_group_cam[:3, :3].T + kf.T_group_cam[:3, 3])
        stamps.append(np.full(len(pts), kf.stamp_s))
    if not chunks or sum(len(c) for c in chunks) == 0:
        return _RobotCloud(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), None)
    points_group = np.concatenate(chunks)
    stamps_s = np.concatenate(stamps)  # non-decreasing: keyframes were sorted by time
    cells = np.floor(points_group / config.voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if np.prod(dims.astype(float)) < 2**62:
        key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    else:  # a huge extent at a fine grid: rank the cells instead of packing them
        key = np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)
    # Stable sort: within a voxel the points stay in time order, so a group's first and last
    # members are its earliest and latest observations.
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    ends = np.r_[starts[1:], len(order)] - 1
    keep = np.unique(np.concatenate([order[starts], order[ends]]))
    points_group, stamps_s = points_group[keep], stamps_s[keep]
    query = np.arange(len(points_group))
    if len(query) > config.max_queries:
        rng = np.random.default_rng(_QUERY_SEED)
        query = np.sort(rng.choice(len(query), config.max_queries, replace=False))
    # Unbalanced, 32-point leaves: faster to build than the default, and faster k=32 queries.
    tree = cKDTree(points_group, leafsize=32, balanced_tree=False, compact_nodes=False)
    return _RobotCloud(
        points_group, stamps_s, query, tree, points_group.min(axis=0), points_group.max(axis=0)
    )


def _point_to_plane(
    query_group: np.ndarray,
    reference: _RobotCloud,
    config: AgreementConfig,
    query_stamps_s: np.ndarray | None = None,
) -> np.ndarray:
    """|point-to-plane| distances [m] of the query points that have a planar neighbourhood in the
    reference; with ``query_stamps_s``, reference points observed less than ``min_revisit_s``
    from the query point are not neighbours."""
    if reference.tree is None or len(query_group) == 0:
        return np.zeros(0)
    # Only query points near the reference's extent can have neighbours: skip the rest cheaply.
    lo, hi = reference.lo_group - config.radius_m, reference.hi_group + config.radius_m
    near = np.all((query_group >= lo) & (query_group <= hi), axis=1)
    query_group = query_group[near]
    if query_stamps_s is not None:
        query_stamps_s = query_stamps_s[near]
    if len(query_group) == 0:
        return np.zeros(0)
    k = min(_MAX_NEIGHBOURS, len(reference.points_group))
    dist, idx = reference.tree.query(
        query_group, k=k, distance_upper_bound=config.radius_m, workers=1
    )
    dist, idx = dist.reshape(len(query_group), k), idx.reshape(len(query_group), k)
    valid = np.isfinite(dist)
    idx = np.where(valid, idx, 0)  # missing neighbours come back as index n: park them on 0
    if query_stamps_s is not None:
        dt = np.abs(reference.stamps_s[idx] - query_stamps_s[:, None])
        valid &= dt >= config.min_revisit_s
    count = valid.sum(axis=1)
    enough = count >= config.min_neighbours
    if not np.any(enough):
        return np.zeros(0)
    q, idx, valid, count = query_group[enough], idx[enough], valid[enough], count[enough]
    # Neighbours relative to their query point (within radius_m): first and second moments stay
    # accurate in float64 and batched matmuls are much faster than a three-operand einsum.
    local = reference.points_group[idx] - q[:, None, :]  # (n, k, 3)
    local *= valid[:, :, None]
    mean = local.sum(axis=1) / count[:, None]
    cov = np.matmul(local.transpose(0, 2, 1), local) / count[:, None, None]
    cov -= mean[:, :, None] * mean[:, None, :]
    eigval, eigvec = np.linalg.eigh(cov)  # ascending
    planar = eigval[:, 0] <= config.max_planarity * eigval[:, 1]
    normal = eigvec[planar][:, :, 0]
    # The query point sits at the local origin: its distance to the plane through the mean.
    return np.abs(np.einsum("nc,nc->n", mean[planar], normal))


def _summary(distances: np.ndarray, config: AgreementConfig) -> float | None:
    """Trimmed RMS [m] (see the module docstring), None below ``min_points`` distances."""
    if len(distances) < config.min_points:
        return None
    n_keep = max(1, int(round((1.0 - config.trim_fraction) * len(distances))))
    kept = np.partition(distances, n_keep - 1)[:n_keep]
    return float(np.sqrt(np.mean(kept**2)))


def _self_distances(cloud: _RobotCloud, config: AgreementConfig) -> np.ndarray:
    q = cloud.query
    return _point_to_plane(cloud.points_group[q], cloud, config, cloud.stamps_s[q])


def _robot_clouds(clouds_by_robot, config: AgreementConfig) -> dict[int, _RobotCloud]:
    if not isinstance(clouds_by_robot, dict):
        raise AgreementError(
            "expected a dict robot id -> list of keyframe clouds, got "
            f"{type(clouds_by_robot).__name__}"
        )
    out = {}
    for rid, keyframes in clouds_by_robot.items():
        if isinstance(rid, bool) or not isinstance(rid, (int, np.integer)):
            raise AgreementError(f"robot ids must be integers, got {rid!r}")
        out[int(rid)] = _robot_cloud(as_keyframe_clouds(rid, keyframes), config)
    return dict(sorted(out.items()))


def team_agreement(clouds_by_robot: dict, config: AgreementConfig | None = None) -> TeamAgreement:
    """Inter- and intra-robot agreement of every robot pair of one merged group, and each robot's
    self-agreement. ``clouds_by_robot``: robot id -> list of :class:`KeyframeCloud` (or
    ``(stamp_s, T_group_cam, points_cam)`` tuples), all in the same group frame."""
    config = (config or AgreementConfig()).validate()
    clouds = _robot_clouds(clouds_by_robot, config)
    result = TeamAgreement()
    self_distances = {}
    for rid, cloud in clouds.items():
        self_distances[rid] = _self_distances(cloud, config)
        result.self_m[rid] = _summary(self_distances[rid], config)
        result.self_points[rid] = len(self_distances[rid])
    for a, b in itertools.combinations(clouds, 2):
        ca, cb = clouds[a], clouds[b]
        inter = np.concatenate(
            [
                _point_to_plane(ca.points_group[ca.query], cb, config),
                _point_to_plane(cb.points_group[cb.query], ca, config),
            ]
        )
        # Only robots whose own figure stands (enough revisited points) speak for the pair.
        intra_parts = [self_distances[r] for r in (a, b) if result.self_m[r] is not None]
        intra = np.concatenate(intra_parts) if intra_parts else np.zeros(0)
        result.pairs.append(
            {
                "robots": [a, b],
                "inter_m": _summary(inter, config),
                "intra_m": _summary(intra, config),
                "inter_points": int(len(inter)),
                "intra_points": int(len(intra)),
            }
        )
    return result


def overlap_agreement(clouds_by_robot: dict, config: AgreementConfig | None = None) -> list[dict]:
    """Per robot pair a < b: ``{"robots": [a, b], "inter_m", "intra_m", "inter_points",
    "intra_points"}`` -- the trimmed-RMS point-to-plane gap [m] between the two robots' maps
    where they overlap (None: fewer than ``min_points`` points in the overlap), the same figure
    for each robot against itself where it revisits, pooled over a and b (None: neither revisits
    enough), and how many distances each figure rests on. See the module docstring."""
    return team_agreement(clouds_by_robot, config).pairs


def self_agreement(keyframes, config: AgreementConfig | None = None) -> float | None:
    """Trimmed-RMS point-to-plane gap [m] between one robot's map and itself where it revisits
    (reference points at least ``min_revisit_s`` apart in time); None when fewer than
    ``min_points`` points are revisited. ``keyframes``: a list of :class:`KeyframeCloud` or
    ``(stamp_s, T_group_cam, points_cam)`` tuples."""
    config = (config or AgreementConfig()).validate()
    cloud = _robot_cloud(as_keyframe_clouds("given", keyframes), config)
    return _summary(_self_distances(cloud, config), config)
