"""The messages that cross the radio, as plain data: one class per ROS message of ``msg/``,
field for field (``coop_slam.ros.wire_bridge`` copies them to and from the generated ROS classes,
and ``test_wire`` checks that both agree), so the protocol's code runs and is tested without ROS.

A robot's keyframe stream (``/robot_k/keyframes``, :class:`KeyframeMessage`) carries one of four
kinds, each its own type: a whole keyframe (:class:`WholeKeyframe`: new, or an update sent whole),
a delta update (:class:`KeyframeDelta`: pose and the observations that changed), a place signature
(:class:`PlaceSignatureMsg`: low-bandwidth mode), or a removal (no payload). How each kind encodes
its arrays: ``docs/wire.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

KIND_KEYFRAME, KIND_DELTA, KIND_SIGNATURE, KIND_REMOVAL = 0, 1, 2, 3
KIND_NAMES = {
    KIND_KEYFRAME: "keyframe",
    KIND_DELTA: "delta",
    KIND_SIGNATURE: "signature",
    KIND_REMOVAL: "removal",
}


# --- the ROS standard types the messages embed (std_msgs, geometry_msgs), field for field ---------
@dataclass
class Stamp:
    """A ROS time (``secs``, ``nsecs``), converted to and from seconds as ROS converts it."""

    secs: int = 0
    nsecs: int = 0

    @classmethod
    def from_sec(cls, t_s: float) -> "Stamp":
        secs = int(t_s)
        nsecs = int((t_s - secs) * 1000000000)
        secs, nsecs = secs + nsecs // 1000000000, nsecs % 1000000000
        return cls(secs, nsecs)

    def to_sec(self) -> float:
        return float(self.secs) + float(self.nsecs) / 1e9

    def is_zero(self) -> bool:
        return self.secs == 0 and self.nsecs == 0


@dataclass
class Header:
    seq: int = 0
    stamp: Stamp = field(default_factory=Stamp)
    frame_id: str = ""


@dataclass
class Point:
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


@dataclass
class Quaternion:
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


@dataclass
class Pose:
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


# --- coop_slam's messages -------------------------------------------------------------------------
@dataclass
class CameraModelMsg:
    """``msg/CameraModel.msg``: the intrinsics a keyframe's keypoints come from."""

    sensor_type: int = 0  # index into coop_slam.camera.SENSORS
    width: int = 0
    height: int = 0
    fx: float = 0.0
    fy: float = 0.0
    cx: float = 0.0
    cy: float = 0.0
    baseline_m: float = 0.0


@dataclass
class WholeKeyframe:
    """``msg/WholeKeyframe.msg``: everything the server stores of a keyframe."""

    replaces: bool = False  # an update sent whole (False: a new keyframe)
    camera: CameraModelMsg = field(default_factory=CameraModelMsg)
    pose: Pose = field(default_factory=Pose)  # T_map_cam
    keypoint_step_px: float = 0.0
    descriptors: bytes = b""
    map_point_offsets_f16: bytes = b""
    map_points: list = field(default_factory=list)  # float32, 3 per point
    packed: bytes = b""
    depth_image: bytes = b""  # coop_slam.dense.depth_image blob; empty = none


@dataclass
class KeyframeDelta:
    """``msg/KeyframeDelta.msg``: an update of a keyframe the server holds."""

    pose: Pose = field(default_factory=Pose)
    map_points: list = field(default_factory=list)  # float32, 3 per patched observed keypoint
    packed: bytes = b""


@dataclass
class PlaceSignatureMsg:
    """``msg/PlaceSignature.msg``: a new keyframe as its place signature."""

    camera: CameraModelMsg = field(default_factory=CameraModelMsg)
    pose: Pose = field(default_factory=Pose)
    bow_weight_max: float = 0.0  # with weights (not counts) only
    packed: bytes = b""


@dataclass
class KeyframeMessage:
    """``msg/KeyframeMessage.msg``: one numbered message of a robot's keyframe stream."""

    header: Header = field(default_factory=Header)
    robot_id: int = 0
    keyframe_id: int = 0
    map_segment: int = 0
    session: int = 0
    sequence: int = 0
    kind: int = KIND_KEYFRAME
    keyframe: list = field(default_factory=list)  # [WholeKeyframe] for KIND_KEYFRAME
    delta: list = field(default_factory=list)  # [KeyframeDelta] for KIND_DELTA
    signature: list = field(default_factory=list)  # [PlaceSignatureMsg] for KIND_SIGNATURE
    sent: Stamp = field(default_factory=Stamp)  # made at, on the robot's clock (0: not said)

    @property
    def kind_name(self) -> str:
        return KIND_NAMES.get(self.kind, f"kind {self.kind}")


@dataclass
class KeyframeAck:
    """``msg/KeyframeAck.msg``: the server's acknowledgement of one robot's keyframe messages."""

    header: Header = field(default_factory=Header)
    robot_id: int = 0
    session: int = 0  # client session acknowledged (0: none yet)
    sequence: int = 0  # highest sequence of that session stored, in order
    last_keyframe_id: int = 0  # highest keyframe id stored for the robot, any session
    last_map_segment: int = 0
    durable: bool = False  # stored in a map file
    refused_keyframe_ids: list = field(default_factory=list)
    server_session: int = 0  # this server run
    received_session: int = 0  # a message received and queued to store (0: none named)
    received_sequence: int = 0


@dataclass
class KeyframeRequest:
    """``msg/KeyframeRequest.msg``: the server asks a robot for whole keyframes."""

    header: Header = field(default_factory=Header)
    robot_id: int = 0
    request: int = 0  # increasing per server run
    keyframe_ids: list = field(default_factory=list)


# The ROS message type of each class (``msg/`` and the ROS packages'), for the bridge and checks.
ROS_TYPES = {
    Header: "std_msgs/Header",
    Point: "geometry_msgs/Point",
    Quaternion: "geometry_msgs/Quaternion",
    Pose: "geometry_msgs/Pose",
    CameraModelMsg: "coop_slam/CameraModel",
    WholeKeyframe: "coop_slam/WholeKeyframe",
    KeyframeDelta: "coop_slam/KeyframeDelta",
    PlaceSignatureMsg: "coop_slam/PlaceSignature",
    KeyframeMessage: "coop_slam/KeyframeMessage",
    KeyframeAck: "coop_slam/KeyframeAck",
    KeyframeRequest: "coop_slam/KeyframeRequest",
}
# The element class of each message's list fields (the bridge and the checks need them).
LIST_TYPES = {
    (KeyframeMessage, "keyframe"): WholeKeyframe,
    (KeyframeMessage, "delta"): KeyframeDelta,
    (KeyframeMessage, "signature"): PlaceSignatureMsg,
}
