"""The server's dense team map: the depth images RGB-D and stereo keyframes brought, placed by
the keyframes' current poses -- a voxel cloud of every group (shown as the sparse cloud is, other
groups beside the world group) and the occupancy grid of the world group's floor band.

Built in the map builder's thread from a snapshot the worker takes in milliseconds
(:meth:`coop_slam.team.server.TeamServer.dense_map_job`); each keyframe's depth image is decoded
and thinned once (:class:`DenseMapBuilder` keeps them), so a rebuild after the graph moved costs
placing and voxelizing points, not decoding."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field

import numpy as np

from ..camera import CameraModel
from ..config import require
from ..dense import depth_image
from ..dense.dense_cloud import place, voxel_centroids, voxel_filter
from ..dense.keyframe_points import points_cam
from ..dense.occupancy import OccupancyConfig, OccupancyGrid, PlacedViews, grid_of_placed
from ..dense.teammates import BodyTrack, outside_bodies
from ..errors import CoopSlamError

log = logging.getLogger(__name__)


@dataclass
class DenseMapConfig:
    """Section ``server.dense``: the dense team map and its occupancy grid."""

    enabled: bool = True  # build and publish them from the keyframes' depth images
    voxel_m: float = 0.05  # voxel size of the dense cloud [m]
    min_depth_m: float = 0.1  # depth used from the keyframes' images [m] ...
    # ... up to this: a cap; each camera's own range is its client's (vo.dense.max_depth_m)
    max_depth_m: float = 30.0
    # The floor's height in the world frame [m]: robot 1's map frame is its base_link at start,
    # on the floor for a ground robot (REP-105); a hand-held camera's map is at its start height.
    floor_z_m: float = 0.0
    # A keyframe's points inside a teammate's body (its description's box, grown by this) at the
    # keyframe's time are left out: robots are not obstacles (coop_slam.dense.teammates) [m] ...
    teammate_margin_m: float = 0.1
    # ... where the teammate has a keyframe within this long of it [s]
    teammate_max_gap_s: float = 1.5
    # ... and after its last keyframe, also this far ahead of it (it stops up to a keyframe's
    # distance on) [m]
    teammate_reach_m: float = 0.5
    # Also each merged robot's grid in its own map frame (/robot_k/team_grid, in robot_k/map),
    # for a planner that works there: one more grid per robot to build
    robot_grids: bool = False
    grid: OccupancyConfig = field(default_factory=OccupancyConfig)

    def validate(self) -> None:
        require(self.voxel_m > 0, "dense.voxel_m must be > 0 [m]")
        require(
            0 <= self.min_depth_m < self.max_depth_m, "dense: need 0 <= min_depth_m < max_depth_m"
        )
        require(np.isfinite(self.floor_z_m), "dense.floor_z_m must be a finite height [m]")
        require(self.teammate_margin_m >= 0, "dense.teammate_margin_m must be >= 0 [m]")
        require(self.teammate_max_gap_s >= 0, "dense.teammate_max_gap_s must be >= 0 [s]")
        require(self.teammate_reach_m >= 0, "dense.teammate_reach_m must be >= 0 [m]")
        self.grid.validate()


@dataclass
class DenseKeyframe:
    """One keyframe of a snapshot: its key, robot, stamp, depth blob (the record's array, not
    copied), camera, pose in the view frame, its group's root and whether that is the world
    group."""

    key: tuple
    robot_id: int
    stamp_s: float
    blob: np.ndarray
    camera: CameraModel
    T_view_cam: np.ndarray
    group: int
    in_world: bool


@dataclass
class DenseMap:
    """What one build made: voxel centroids in the view frame with each voxel's robot, the world
    group's occupancy grid (None: no keyframe with depth in it) and the frame it is in."""

    points: np.ndarray  # (N, 3) float32
    robot_ids: np.ndarray  # (N,)
    grid: OccupancyGrid | None
    floor_z_m: float
    keyframes: int  # keyframes with a depth image in the build
    # robot id -> the grid in its map frame (DenseMapConfig.robot_grids; z = 0 its floor)
    robot_grids: dict = field(default_factory=dict)


@dataclass
class _Decoded:
    blob: np.ndarray
    points_cam: np.ndarray


class DenseMapBuilder:
    """Keeps every keyframe's points decoded and thinned between builds (one lock: the worker
    may drop keys while the builder builds)."""

    def __init__(self, config: DenseMapConfig):
        self.config = config
        self._decoded: dict[tuple, _Decoded] = {}
        self._lock = threading.Lock()

    def _points(self, kf: DenseKeyframe) -> np.ndarray | None:
        got = self._decoded.get(kf.key)
        if got is not None and (got.blob is kf.blob or np.array_equal(got.blob, kf.blob)):
            return got.points_cam
        try:
            image = depth_image.decode(kf.blob.tobytes())
            pts = points_cam(image, kf.camera, self.config.min_depth_m, self.config.max_depth_m)
        except CoopSlamError as exc:  # one robot's bad image must not stop the team's map
            log.warning("dense map: robot %d keyframe %s left out: %s", kf.robot_id, kf.key, exc)
            pts = np.zeros((0, 3), np.float32)
        # Thinned at half the voxel size in the camera frame: what a voxel of the team map gets
        # from one keyframe, for a tenth of the points at 2 m.
        pts = voxel_filter(pts, self.config.voxel_m / 2)
        self._decoded[kf.key] = _Decoded(kf.blob, pts)
        return pts

    def _placed(self, kf: DenseKeyframe, pts: np.ndarray, bodies) -> np.ndarray:
        """A keyframe's points in the view frame, without those in a teammate's body."""
        cfg = self.config
        placed = place([(kf.T_view_cam, pts)])
        boxes = [
            body.box_at(
                kf.stamp_s, cfg.teammate_max_gap_s, cfg.teammate_margin_m, cfg.teammate_reach_m
            )
            for body in bodies
            if body.group == kf.group and body.robot_id != kf.robot_id
        ]
        boxes = [box for box in boxes if box is not None]
        if not boxes or not len(pts):
            return placed
        return placed[outside_bodies(placed, boxes)]

    def build(
        self,
        snapshot: list[DenseKeyframe],
        bodies: list[BodyTrack] = (),
        T_world_maps: dict | None = None,
    ) -> DenseMap:
        """The dense map of a snapshot; ``bodies``: the robots' bodies along their paths, left out
        of their teammates' keyframes; ``T_world_maps``: robot id -> its map frame in the world
        group's, for the robots that want the grid in it."""
        cfg = self.config
        with self._lock:
            views = [(kf, self._points(kf)) for kf in snapshot]
            for key in set(self._decoded) - {kf.key for kf in snapshot}:
                del self._decoded[key]  # removed keyframes
        kept = [(kf, self._placed(kf, pts, bodies)) for kf, pts in views]
        placed = np.concatenate([p for _, p in kept] or [np.zeros((0, 3), np.float32)])
        robots = np.concatenate(
            [np.full(len(p), kf.robot_id, np.int64) for kf, p in kept] or [np.zeros(0, int)]
        )
        centroids, first, _ = voxel_centroids(placed, cfg.voxel_m)
        world = [(kf, p) for kf, p in kept if kf.in_world]
        grid, robot_grids = None, {}
        if world:
            # The grid takes the points as placed here: in the world group's frame.
            placed_world = PlacedViews.of(
                [kf.T_view_cam[:3, 3] for kf, _ in world], [p for _, p in world]
            )
            grid = grid_of_placed(placed_world, cfg.grid, cfg.floor_z_m)
            for robot_id, T_world_map in (T_world_maps or {}).items():
                in_map = placed_world.moved(np.linalg.inv(T_world_map))
                robot_grids[robot_id] = grid_of_placed(in_map, cfg.grid)
        return DenseMap(centroids, robots[first], grid, cfg.floor_z_m, len(views), robot_grids)


def body_tracks(tracks: dict, bodies: dict) -> list[BodyTrack]:
    """BodyTracks from (robot, group) -> [(stamp_s, T_view_cam)] and robot -> (T_base_cam, size)."""
    out = []
    for (robot_id, group), poses in tracks.items():
        T_base_cam, size = bodies[robot_id]
        poses.sort(key=lambda p: p[0])
        T_cam_base = np.linalg.inv(T_base_cam)
        out.append(
            BodyTrack(
                robot_id,
                group,
                np.array([s for s, _ in poses]),
                np.array([T @ T_cam_base for _, T in poses]),
                tuple(size),
            )
        )
    return out
