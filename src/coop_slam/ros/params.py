"""The nodes' own parameters (private ROS parameters, set by ``client.launch`` / ``server.launch``),
typed like every other configuration and loaded by the same loader: a misspelt or mistyped
parameter is refused by name. The modules' configurations (``vo``, ``uplink``, ``markers``; the
server's sections) come as parameters of the same node too: what is not a node parameter below
goes to them (docs/configuration.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from ..config import load_config, require
from ..frames import FrameConfig
from ..ids import MAX_ROBOT_ID
from ..uplink.spool import SpoolConfig
from ..wire.delivery import DeliveryConfig

CLIENT_SECTIONS = ("vo", "uplink", "markers")  # the client's module configurations


@dataclass
class ClientNodeParams:
    """``client_node``'s parameters (client.launch)."""

    robot_id: int = 0  # robot id k >= 1: topics /robot_k/..., frames robot_k/...
    sensor: str = "rgbd"  # the camera: rgbd, stereo or mono
    config: str = ""  # YAML file of the sections vo, uplink, markers ("" = the defaults)
    # Camera preset layered over it (config/cameras/NAME.yaml, or a path; "" = none)
    camera: str = ""
    T_base_cam: list = field(default_factory=list)  # camera in base_link [x y z qx qy qz qw]
    # TF frame names ('' = robot_k/odom, robot_k/base_link, robot_k/camera_optical) and who
    # publishes which edge (see coop_slam.frames)
    odom_frame: str = ""
    base_frame: str = ""
    camera_frame: str = ""
    external_odom: bool = False  # the base publishes odom -> base_link; the client map -> odom
    publish_camera_tf: bool = True  # base_link -> camera from ~T_base_cam (false: URDF does)
    # 16UC1 depth units per metre (REP-118: millimetres); 0 = the camera preset's, else 1000
    depth_scale: float = 0.0
    cloud_period_s: float = 2.0  # the local cloud goes out at most this often [s of data]
    path_period_s: float = 1.0  # the keyframe path goes out at most this often [s of data]
    marker_every_frames: int = 5  # look for other robots' markers every N frames; 0 = never
    # Rehearsal only (scripts/demo --clock-offset): this robot's clock runs this far ahead of
    # the master's; the player stamps its camera's images so, and the client its messages [s]
    clock_offset_s: float = 0.0
    # Lock-step playback: a frame is finished when local mapping has caught up (results do not
    # depend on the machine's speed); live cameras: false.
    wait_for_mapping: bool = False
    mapping_backlog_warn: int = 3  # warn when local mapping is this many keyframes behind
    server_wait_s: float = 3.0  # wait this long for the server's acknowledgement at start [s]
    max_unacked: int = 1000  # keyframe messages kept for the server; beyond, new ones are refused
    # Keyframe messages not acknowledged are kept on disk, and sent first after a restart: the
    # file ("" = $ROS_HOME/coop_slam/robot_<k>/spool.db; off = in memory only, lost with the node)
    spool: str = ""
    spool_max_mb: float = 200.0  # beyond this, new keyframe messages are refused [MB]
    resend_after_s: float = 2.0  # first wait before a message goes again [s]
    resend_window: int = 100  # at most this many go again at once
    max_resend_after_s: float = 30.0  # the longest wait between sends of one message [s]
    vo: dict = field(default_factory=dict)  # overrides of section vo (see config/client.yaml)
    uplink: dict = field(default_factory=dict)  # overrides of section uplink
    markers: dict = field(default_factory=dict)  # overrides of section markers

    def validate(self) -> None:
        require(
            1 <= self.robot_id <= MAX_ROBOT_ID,
            f"~robot_id must be in [1, {MAX_ROBOT_ID}] (the server keys maps by one byte), got "
            f"{self.robot_id}",
        )
        self.spool_config.validate()
        require(
            len(self.T_base_cam) in (0, 7),
            "~T_base_cam must be [x, y, z, qx, qy, qz, qw] (or [] for a level camera)",
        )
        self.frame_config.validate()
        self.frame_config.names(self.robot_id)
        require(self.depth_scale >= 0, "~depth_scale must be >= 0 [units per metre]")
        require(self.marker_every_frames >= 0, "~marker_every_frames must be >= 0")

    @property
    def frame_config(self) -> FrameConfig:
        return FrameConfig(
            self.odom_frame,
            self.base_frame,
            self.camera_frame,
            self.external_odom,
            self.publish_camera_tf,
        )

    @property
    def spool_config(self) -> SpoolConfig:
        return SpoolConfig(self.spool, self.spool_max_mb)

    @property
    def delivery(self) -> DeliveryConfig:
        return DeliveryConfig(
            self.max_unacked, self.resend_after_s, self.resend_window, self.max_resend_after_s
        )


@dataclass
class ServerNodeParams:
    """``server_node``'s parameters (server.launch); every other private parameter is a key of
    the server's configuration (section ``server``)."""

    config: str = ""  # YAML file of section server ("" = the defaults)
    vocabulary: str = ""  # the shared vocabulary ("" = the default one setup builds)
    cloud_period_s: float = 2.0  # the team cloud goes out at most this often [s of data]
    cloud_max_busy_share: float = 0.2  # building it takes at most this share of the wall time
    map: str = ""  # the team map file ("" = a new one per run in $ROS_HOME/coop_slam; off = none)
    resume: bool = False  # rebuild the team map from the map file (after a crash or restart)
    load_map: str = ""  # start from a map saved in an earlier session

    def validate(self) -> None:
        require(self.cloud_period_s > 0, "~cloud_period_s must be > 0 [s]")
        require(0 < self.cloud_max_busy_share <= 1, "~cloud_max_busy_share must be in (0, 1]")


def client_params(values: Mapping[str, Any]) -> ClientNodeParams:
    """The client node's parameters from its private namespace (``rospy.get_param("~")``)."""
    return load_config(ClientNodeParams, values, prefix="~")


def server_params(values: Mapping[str, Any]) -> tuple[ServerNodeParams, dict]:
    """The server node's parameters and the rest (overrides of its configuration) from its
    private namespace."""
    names = set(ServerNodeParams.__dataclass_fields__)
    node = load_config(ServerNodeParams, {k: v for k, v in values.items() if k in names}, "~")
    return node, {k: v for k, v in values.items() if k not in names}
