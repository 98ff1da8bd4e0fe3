"""What a run recorded (:class:`RunData`, per robot :class:`RobotRun`), filled by
:mod:`coop_slam.ros.run_recorder`, and what it is judged against (:class:`RunInput`): the two inputs
of a run's report (:mod:`.run_report`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class RobotRun:
    frames: int = 0  # frames tracked
    frames_dropped: int = 0  # frames the busy client skipped for a newer one
    # Local mapping's backlog (keyframes not finished) when frames were tracked: its maximum and
    # the frames tracked while it held more than one (mapping behind the camera)
    mapping_backlog_max: int = 0
    frames_mapping_behind: int = 0
    lost_frames: int = 0
    track_ms: list = field(default_factory=list)
    keyframes: dict = field(default_factory=dict)  # id -> (stamp_s, T_map_cam), latest version
    keyframe_points: dict = field(default_factory=dict)  # id -> points_cam (N, 3) with depth
    first_keyframe: tuple | None = None  # (stamp_s, T_map_cam) as first published
    # id -> stamp_s of every keyframe ever published, culled ones included: a merge may rest on
    # a keyframe the client culls while the merge is on its way
    keyframe_stamps: dict = field(default_factory=dict)
    kf_bytes: list = field(default_factory=list)  # (sim stamp_s, bytes) per keyframe message
    kf_kinds: dict = field(default_factory=dict)  # kind -> (messages, bytes): what they carried
    T_world_map: np.ndarray | None = None  # latest correction, when merged
    map_scale: float = 1.0  # ... and its metres per unit of the robot's map (monocular)
    # server's optimized keyframe poses in world (latest /team_map/robot_k/path, when merged):
    # id -> (stamp_s, T_world_cam)
    team_keyframes: dict = field(default_factory=dict)
    sensor: str | None = None  # rgbd, stereo or mono, as its keyframes say
    T_base_cam: np.ndarray | None = None  # its camera mount, as its description says
    clock_offset_s: float = 0.0  # its clock ran this far ahead of the master's (rehearsed) [s]
    # New keyframes its client sessions sent (a restarted client counts from 0 again), and the
    # keyframe messages not acknowledged by the server at the end
    keyframes_sent_sessions: list = field(default_factory=list)
    held_back_sessions: list = field(default_factory=list)  # ... and those its budget kept back
    unacked: int = 0
    keyframe_segments: dict = field(default_factory=dict)  # id -> map segment
    # the client's latest /robot_k/path: (keyframe id, stamp_s, T_map_base) per keyframe (id 0:
    # recorded before paths carried them)
    path: list = field(default_factory=list)

    def in_first_segment(self, keyframe_id: int) -> bool:
        """Whether a keyframe is of its first map segment (a later one is another map frame)."""
        if not self.keyframe_segments:
            return True
        first = min(self.keyframe_segments.values())
        return self.keyframe_segments.get(keyframe_id, first) == first

    def first_segment_ids(self) -> list:
        return sorted(k for k in self.keyframes if self.in_first_segment(k))

    def first_segment_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (K,), T_map_cam (K, 4, 4)) of the first map segment's keyframes, by id."""
        ids = self.first_segment_ids()
        return (
            np.array([self.keyframes[k][0] for k in ids]),
            np.array([self.keyframes[k][1] for k in ids]).reshape(-1, 4, 4),
        )


@dataclass
class RunData:
    robots: dict = field(default_factory=dict)  # robot id -> RobotRun
    merges: list = field(
        default_factory=list
    )  # dicts: type, robot_a, robot_b, stamp_s, T_mapA_mapB
    # constraints inside groups (link: two robots, loop: one): dicts type, robots,
    # keyframe_stamps, stamp_s, T_camA_camB
    links: list = field(default_factory=list)
    server_stats: dict = field(default_factory=dict)
    duration_s: float = 0.0  # sim time from first to last frame
    topic_bytes: dict = field(default_factory=dict)  # topic -> [(sim t_s, bytes)] per message
    team_cloud: tuple | None = None  # latest /team_map/cloud: (points (N, 3), rgb (N, 3) uint8)
    dense_cloud: tuple | None = None  # latest /team_map/dense, the same
    grid: object = None  # latest /team_map/grid (coop_slam.dense.occupancy.OccupancyGrid)
    grid_z_m: float = 0.0  # ... the height of its floor in the world frame [m]
    # robot id -> (sent, received) bytes on its radio interface during the run (--hosts only)
    radio_bytes: dict = field(default_factory=dict)


@dataclass
class RunInput:
    """What a run plays and is judged against, whether from a scenario/dataset or a sensor bag."""

    robot_ids: list[int]
    frames: int  # colour images of all robots
    start_s: float  # first and last frame on the playback timeline [s]
    end_s: float
    gts: dict  # robot id -> (stamps, T_world_cam); empty arrays for robots without ground truth
    overlap: dict | None = None  # synthetic overlap events (merge latency), when known
    sensors: list[str] | None = None  # each robot's camera (rgbd, stereo, mono), in robot_ids order
    # The synthetic world, when the run played one: {"layout", "seed", "hand_held"}
    world: dict | None = None
