"""Parameters of the dataset player (ROS private params map 1:1 onto these fields)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..config import require
from ..playback import PlaybackError, parse_clock_offsets


@dataclass
class PlayerConfig:
    scenario: str = (
        ""  # synthetic scenario name (rendezvous, revisit, disjoint, aliasing, multi, team)
    )
    dataset: str = ""  # TUM RGB-D or KITTI odometry folder (instead of a scenario)
    bag: str = ""  # rosbag file to replay (instead of a scenario or dataset)
    split: str = ""  # frame ranges, one robot each, inclusive: "0-299,300-599"
    robots: int = 0  # number of robots (0 = the scenario's / one per split range)
    only_robots: str = ""  # play only these robots, comma-separated ids ("" = all)
    seed: int = 0  # synthetic world seed
    duration_s: float = 0.0  # synthetic world length [s]; 0 = the scenario's own
    camera_file: str = ""  # camera.yaml for a TUM folder without one
    sensors: str = (
        ""  # per robot "rgbd" / "stereo", comma-separated, or one for all; "" = the data's
    )
    keep_timing: bool = False  # play split segments at their original times instead of together
    start_offsets_s: list[float] = field(default_factory=list)  # per-robot start delay [s]
    lockstep: bool = True  # wait for each consumer's frame_stats before the next frame
    rate: float = 1.0  # real-time factor when not in lock-step (or for robots without consumer)
    ack_timeout_s: float = 60.0  # lock-step: how long to wait for a consumer [s]
    wait_for_subscribers_s: float = 15.0  # wait this long for image subscribers before playing [s]
    # Node (e.g. a rosbag recorder) that must subscribe to every robot's keyframes before playing,
    # so a recording misses none of them; "" = do not wait.
    wait_for_node: str = ""
    depth_encoding: str = "32FC1"  # 32FC1 (metres) or 16UC1 (millimetres), as in REP-118
    # Live playback (not lock-step) decodes frames ahead of time, up to this much image data [MiB]
    # (RedKitchen: ~2.1 MiB a frame with 32FC1 depth); lock-step decodes the next frames while
    # the clients work, up to 64 MiB of it; 0 = decode each frame when it is due.
    preload_mb: float = 2048.0
    progress_period_s: float = 5.0  # wall time between progress log lines [s]
    # all: play every robot and drive /clock; conductor: drive /clock and step the cameras (the
    # station of scripts/demo --hosts); camera: play ~only_robots when the conductor steps.
    role: str = "all"
    exit_when_done: bool = False  # exit after the last frame instead of spinning (latched topics)
    # Rehearsal: robots whose clock runs ahead of the master's, "ROBOT:SECONDS,...": their
    # camera's images are stamped on their clock (scripts/demo --clock-offset)
    clock_offsets: str = ""

    def validate(self) -> None:
        require(
            sum(map(bool, (self.scenario, self.dataset, self.bag))) == 1,
            "player: set exactly one of ~scenario, ~dataset or ~bag",
        )
        require(self.rate > 0, f"player: ~rate must be > 0, got {self.rate}")
        require(self.ack_timeout_s > 0, "player: ~ack_timeout_s must be > 0")
        require(
            math.isfinite(self.preload_mb) and self.preload_mb >= 0,
            f"player: ~preload_mb must be a finite number >= 0 [MiB], got {self.preload_mb}",
        )
        require(
            self.role in ("all", "conductor", "camera"),
            f"player: ~role must be all, conductor or camera, got '{self.role}'",
        )
        require(
            self.role == "all" or not self.bag,
            "player: a bag plays on one host (~role all): split it per robot to play it on hosts",
        )
        require(self.robots >= 0, "player: ~robots must be >= 0")
        try:
            parse_clock_offsets(self.clock_offsets)
        except PlaybackError as exc:
            require(False, f"player: ~clock_offsets: {exc}")
        require(self.duration_s >= 0, "player: ~duration_s must be >= 0")
        require(
            self.depth_encoding in ("32FC1", "16UC1"),
            f"player: ~depth_encoding must be 32FC1 or 16UC1, got '{self.depth_encoding}'",
        )
