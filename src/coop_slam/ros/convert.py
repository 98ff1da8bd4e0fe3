"""Conversion between ROS messages and the pure core's numpy types.

Images are converted without cv_bridge (numpy views of the message buffer). Every ``*_from_msg``
function validates what it reads and raises :class:`MessageError` with a message naming the field.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Pose, Transform
from sensor_msgs.msg import CameraInfo, Image

from ..camera import CameraError, CameraModel
from ..dense.occupancy import OccupancyGrid
from ..errors import CoopSlamError
from ..geometry import GeometryError, quat_from_se3, se3_from_quat
from ..wire.record import MAX_POSITION_M


class MessageError(CoopSlamError):
    """An incoming ROS message is malformed (wrong sizes, NaN, unknown encoding, ...)."""


# --- poses ----------------------------------------------------------------------------------------
def pose_to_msg(T: np.ndarray) -> Pose:
    t, q = quat_from_se3(T)
    msg = Pose()
    msg.position.x, msg.position.y, msg.position.z = map(float, t)
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = map(float, q)
    return msg


def pose_from_msg(msg: Pose, name: str = "pose") -> np.ndarray:
    p, o = msg.position, msg.orientation
    try:
        T = se3_from_quat([p.x, p.y, p.z], [o.x, o.y, o.z, o.w])
    except GeometryError as exc:
        raise MessageError(f"{name}: {exc}") from None
    return _finite_pose(T, name)


def _finite_pose(T: np.ndarray, name: str) -> np.ndarray:
    if not np.all(np.isfinite(T)):
        raise MessageError(f"{name} contains NaN or inf")
    # Finite yet absurd (a correction placing a keyframe 1e300 m away would move the client's
    # published pose there): every pose and transform between map frames lies within a map.
    far = float(np.abs(T[:3, 3]).max())
    if far > MAX_POSITION_M:
        raise MessageError(
            f"{name} position {far:.3g} m is beyond the {MAX_POSITION_M:g} m any map spans"
        )
    return T


def transform_to_msg(T: np.ndarray) -> Transform:
    t, q = quat_from_se3(T)
    msg = Transform()
    msg.translation.x, msg.translation.y, msg.translation.z = map(float, t)
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = map(float, q)
    return msg


def transform_from_msg(msg: Transform, name: str = "transform") -> np.ndarray:
    t, r = msg.translation, msg.rotation
    try:
        return _finite_pose(se3_from_quat([t.x, t.y, t.z], [r.x, r.y, r.z, r.w]), name)
    except GeometryError as exc:
        raise MessageError(f"{name}: {exc}") from None


# --- images ---------------------------------------------------------------------------------------
_ENCODINGS = {
    "bgr8": (np.uint8, 3),
    "rgb8": (np.uint8, 3),
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "16UC1": (np.uint16, 1),
    "mono16": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}


def image_to_msg(img: np.ndarray, encoding: str, stamp=None, frame_id: str = "") -> Image:
    dtype, channels = _ENCODINGS[encoding]
    img = np.ascontiguousarray(img, dtype=dtype)
    msg = Image()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = img.shape[:2]
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = msg.width * channels * np.dtype(dtype).itemsize
    msg.data = img.tobytes()
    return msg


def image_from_msg(msg: Image) -> np.ndarray:
    """numpy view of an image message (BGR for colour); raises MessageError when malformed."""
    if msg.encoding not in _ENCODINGS:
        raise MessageError(
            f"image encoding '{msg.encoding}' unsupported; use one of {sorted(_ENCODINGS)}"
        )
    if msg.width == 0 or msg.height == 0:
        raise MessageError(f"image is empty ({msg.width}x{msg.height})")
    dtype, channels = _ENCODINGS[msg.encoding]
    itemsize = np.dtype(dtype).itemsize
    row = msg.width * channels * itemsize
    if msg.step < row or len(msg.data) < msg.step * msg.height:
        raise MessageError(
            f"image data holds {len(msg.data)} bytes, expected {msg.step * msg.height} "
            f"({msg.width}x{msg.height} {msg.encoding}, step {msg.step})"
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8, count=msg.step * msg.height).reshape(
        msg.height, msg.step
    )
    img = buf[:, :row].copy().view(dtype)
    if msg.is_bigendian and itemsize > 1:
        img = img.byteswap()
    img = (
        img.reshape(msg.height, msg.width, channels)
        if channels > 1
        else img.reshape(msg.height, msg.width)
    )
    if msg.encoding == "rgb8":
        img = img[:, :, ::-1].copy()
    return img


def depth_from_msg(msg: Image, depth_scale: float = 1000.0) -> np.ndarray:
    """Depth in metres (float32, 0 = none) from a 16UC1 (``depth_scale`` units per metre, REP-118:
    millimetres) or 32FC1 (metres) image."""
    img = image_from_msg(msg)
    if img.dtype == np.uint16:
        return img.astype(np.float32) / np.float32(depth_scale)
    if img.dtype != np.float32:
        raise MessageError(f"depth image encoding '{msg.encoding}' is not 16UC1 or 32FC1")
    depth = img.astype(np.float32, copy=True)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


# --- camera ---------------------------------------------------------------------------------------
def camera_info_to_msg(
    camera: CameraModel, stamp=None, frame_id: str = "", right: bool = False
) -> CameraInfo:
    """The rectified camera; ``right``: the right camera of a stereo pair (P[3] = -fx * b)."""
    msg = CameraInfo()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = camera.width, camera.height
    msg.distortion_model = "plumb_bob"
    msg.D = [0.0] * 5
    msg.K = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    msg.R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    Tx = -camera.fx * camera.baseline_m if right else 0.0  # ROS convention for the right camera
    msg.P = [camera.fx, 0.0, camera.cx, Tx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def stereo_camera_from_infos(left: CameraInfo, right: CameraInfo) -> CameraModel:
    """The stereo camera of a rectified pair's camera infos: the left camera's intrinsics, the
    baseline from the right camera's projection matrix (P[3] = -fx * baseline)."""
    P = list(right.P)
    if len(P) != 12 or not np.all(np.isfinite(P)) or P[0] <= 0:
        raise MessageError("right camera_info P must hold 12 finite numbers with fx > 0")
    if (left.width, left.height) != (right.width, right.height):
        raise MessageError(
            f"left and right camera_info differ in size: {left.width}x{left.height} and "
            f"{right.width}x{right.height}"
        )
    baseline_m = -P[3] / P[0]
    if baseline_m <= 0:
        raise MessageError(
            f"right camera_info gives baseline {baseline_m:.4f} m (P[3] = {P[3]:.3f}); a "
            "rectified right camera has P[3] = -fx * baseline < 0: are left and right swapped, "
            "or is it the left camera's info?"
        )
    return camera_from_info(left, sensor="stereo", baseline_m=baseline_m)


def camera_from_info(
    msg: CameraInfo, sensor: str = "rgbd", depth_scale: float = 1000.0, baseline_m: float = 0.0
) -> CameraModel:
    K = list(msg.K)
    if len(K) != 9 or not np.all(np.isfinite(K)):
        raise MessageError("camera_info K must hold 9 finite numbers")
    try:
        return CameraModel(
            width=msg.width,
            height=msg.height,
            fx=K[0],
            fy=K[4],
            cx=K[2],
            cy=K[5],
            sensor=sensor,
            depth_scale=depth_scale,
            baseline_m=baseline_m,
        )
    except CameraError as exc:
        raise MessageError(f"camera_info: {exc}") from None


# --- point clouds ---------------------------------------------------------------------------------
def cloud_to_msg(points: np.ndarray, frame_id: str, stamp=None, rgb: np.ndarray | None = None):
    """PointCloud2 (x, y, z float32 [+ rgb packed float32]) built with numpy, no per-point loop."""
    from sensor_msgs.msg import PointCloud2, PointField

    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [
        PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
        for i, n in enumerate("xyz")
    ]
    if rgb is not None:
        rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
        packed = (
            (rgb[:, 0].astype(np.uint32) << 16)
            | (rgb[:, 1].astype(np.uint32) << 8)
            | rgb[:, 2].astype(np.uint32)
        )
        data = np.empty((len(points), 4), np.float32)
        data[:, :3] = points
        data[:, 3] = packed.view(np.float32)
        fields.append(PointField(name="rgb", offset=12, datatype=PointField.FLOAT32, count=1))
    else:
        data = points
    msg = PointCloud2()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, len(points)
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = 4 * data.shape[1] if len(points) else 4 * len(fields)
    msg.row_step = msg.point_step * len(points)
    msg.is_dense = True
    msg.data = np.ascontiguousarray(data).tobytes()
    return msg


def cloud_from_msg(msg) -> np.ndarray:
    """(N, 3) xyz of a PointCloud2 with float32 x, y, z fields."""
    offsets = {f.name: f.offset for f in msg.fields}
    if not all(k in offsets for k in "xyz") or msg.point_step == 0:
        raise MessageError("point cloud lacks float32 x, y, z fields")
    n = msg.width * msg.height
    if len(msg.data) < n * msg.point_step:
        raise MessageError(f"point cloud data holds {len(msg.data)} bytes for {n} points")
    raw = np.frombuffer(msg.data, np.uint8, count=n * msg.point_step).reshape(n, msg.point_step)
    return np.stack(
        [raw[:, offsets[k] : offsets[k] + 4].copy().view(np.float32)[:, 0] for k in "xyz"], axis=1
    )


def cloud_colours_from_msg(msg) -> np.ndarray:
    """(N, 3) uint8 red, green, blue of a PointCloud2's packed ``rgb`` field (zeros without one)."""
    n = msg.width * msg.height
    offsets = {f.name: f.offset for f in msg.fields}
    if "rgb" not in offsets or n == 0 or len(msg.data) < n * msg.point_step:
        return np.zeros((n, 3), np.uint8)
    raw = np.frombuffer(msg.data, np.uint8, count=n * msg.point_step).reshape(n, msg.point_step)
    packed = raw[:, offsets["rgb"] : offsets["rgb"] + 4].copy().view(np.uint32)[:, 0]
    return np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], 1).astype(np.uint8)


def transform_stamped(T: np.ndarray, parent: str, child: str, stamp):
    from geometry_msgs.msg import TransformStamped

    msg = TransformStamped(transform=transform_to_msg(T))
    msg.header.stamp = stamp
    msg.header.frame_id = parent
    msg.child_frame_id = child
    return msg


def description_to_msg(d):
    """A :class:`coop_slam.robot_description.RobotDescription` as ``coop_slam/RobotDescription``."""
    from coop_slam.msg import RobotDescription as RobotDescriptionMsg

    return RobotDescriptionMsg(
        robot_id=d.robot_id,
        sensor=d.sensor,
        camera=d.camera,
        T_base_cam=pose_to_msg(d.T_base_cam),
        marker_dictionary=d.marker_dictionary,
        marker_size_m=d.marker_size_m,
        T_base_marker=pose_to_msg(d.T_base_marker),
        body_size_m=list(d.body_size_m),
    )


def description_from_msg(msg):
    """A ``coop_slam/RobotDescription`` message -> a validated
    :class:`coop_slam.robot_description.RobotDescription` (:class:`MessageError` if unusable)."""
    from ..robot_description import RobotDescription, RobotDescriptionError

    try:
        return RobotDescription(
            robot_id=int(msg.robot_id),
            sensor=msg.sensor,
            T_base_cam=pose_from_msg(msg.T_base_cam, "T_base_cam"),
            marker_dictionary=msg.marker_dictionary,
            marker_size_m=float(msg.marker_size_m),
            T_base_marker=pose_from_msg(msg.T_base_marker, "T_base_marker"),
            body_size_m=tuple(float(v) for v in msg.body_size_m),
            camera=msg.camera,
        )
    except RobotDescriptionError as exc:
        raise MessageError(str(exc)) from None


def marker_seen_from_msg(msg):
    """A ``coop_slam/RobotSighting`` -> :class:`coop_slam.robot_description.MarkerSeen`. One
    recorded before sightings carried the marker (its observed body, ``T_cam_body``, placed with
    the default marker) is read back to the marker it saw."""
    from ..markers import MarkerConfig
    from ..robot_description import MarkerSeen

    if not hasattr(msg, "T_cam_marker"):
        default = MarkerConfig()
        T_cam_body = pose_from_msg(msg.T_cam_body, "T_cam_body")
        return MarkerSeen(T_cam_body @ default.base_marker(), default.marker_size_m)
    size = float(msg.marker_size_m)
    if not np.isfinite(size) or size <= 0:
        raise MessageError(f"sighting's marker_size_m {size} is not > 0 [m]")
    return MarkerSeen(pose_from_msg(msg.T_cam_marker, "T_cam_marker"), size)


# --- occupancy grids ------------------------------------------------------------------------------
def grid_to_msg(grid: OccupancyGrid, frame_id: str, stamp=None, z_m: float = 0.0):
    """nav_msgs/OccupancyGrid of a grid whose cell (0, 0) corner is at its origin, at height z."""
    from nav_msgs.msg import OccupancyGrid as GridMsg

    msg = GridMsg()
    if stamp is not None:
        msg.header.stamp = msg.info.map_load_time = stamp
    msg.header.frame_id = frame_id
    msg.info.resolution = float(grid.cell_m)
    msg.info.height, msg.info.width = (int(n) for n in grid.cells.shape)
    msg.info.origin.position.x, msg.info.origin.position.y = grid.origin_xy_m
    msg.info.origin.position.z = float(z_m)
    msg.info.origin.orientation.w = 1.0
    msg.data = np.asarray(grid.cells, np.int8).ravel().tolist()  # int8[]: rospy takes no bytes
    return msg


def grid_from_msg(msg) -> OccupancyGrid:
    """The grid of a nav_msgs/OccupancyGrid (its origin's orientation must be the identity)."""
    info = msg.info
    data = msg.data
    cells = np.frombuffer(data, np.int8) if isinstance(data, bytes) else np.asarray(data, np.int8)
    if len(cells) != info.width * info.height:
        raise MessageError(
            f"occupancy grid holds {len(cells)} cells for {info.width} x {info.height}"
        )
    return OccupancyGrid(
        cells.reshape(info.height, info.width).copy(),
        float(info.resolution),
        (float(info.origin.position.x), float(info.origin.position.y)),
    )
