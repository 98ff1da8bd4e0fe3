"""ROS message conversion and validation (no master needed): images, poses, camera infos.
Keyframe messages: test_wire."""

import numpy as np
import pytest

msg_mod = pytest.importorskip(
    "coop_slam.msg", reason="generated messages need the catkin workspace"
)
from coop_slam.ros.convert import (  # noqa: E402
    MessageError,
    depth_from_msg,
    image_from_msg,
    image_to_msg,
    pose_from_msg,
    pose_to_msg,
    transform_from_msg,
    transform_to_msg,
)
from coop_slam.ros.validation import RejectCounter  # noqa: E402


def _wire(msg):
    """Serialize and deserialize, as a message crossing a topic."""
    import io

    buf = io.BytesIO()
    msg.serialize(buf)
    out = type(msg)()
    out.deserialize(buf.getvalue())
    return out


def test_images_and_depth():
    img = np.random.default_rng(0).integers(0, 255, (4, 5, 3), dtype=np.uint8)
    assert np.array_equal(image_from_msg(_wire(image_to_msg(img, "bgr8"))), img)
    rgb = image_to_msg(img[:, :, ::-1], "rgb8")
    assert np.array_equal(image_from_msg(rgb), img)
    d16 = image_to_msg(np.full((3, 3), 1500, np.uint16), "16UC1")
    assert np.allclose(depth_from_msg(d16), 1.5)
    d32 = np.full((3, 3), 2.0, np.float32)
    d32[0, 0] = np.nan
    out = depth_from_msg(image_to_msg(d32, "32FC1"))
    assert out[0, 0] == 0.0 and out[1, 1] == 2.0
    bad = image_to_msg(img, "bgr8")
    bad.data = bad.data[:-1]
    with pytest.raises(MessageError, match="bytes"):
        image_from_msg(bad)
    empty = image_to_msg(np.zeros((0, 0, 3), np.uint8), "bgr8")
    with pytest.raises(MessageError, match="empty"):
        image_from_msg(empty)
    bad.encoding = "yuv422"
    with pytest.raises(MessageError, match="unsupported"):
        image_from_msg(bad)


def test_pose_conversion_and_reject_counter():
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    assert np.allclose(pose_from_msg(pose_to_msg(T)), T)
    T[1, 3] = 1e300  # a map correction placing a keyframe there would move the client's pose
    with pytest.raises(MessageError, match="keyframe pose position 1e.300 m is beyond"):
        pose_from_msg(pose_to_msg(T), "keyframe pose")
    with pytest.raises(MessageError, match="T_world_map position"):
        transform_from_msg(transform_to_msg(T), "T_world_map")
    counter = RejectCounter("test", log_period_s=100.0)
    counter.reject("/a", "bad")
    counter.reject("/a", "bad")
    counter.reject("/b", "worse")
    assert counter.counts["/a"] == 2 and counter.total == 3


def test_stereo_camera_from_the_ros_stereo_camera_infos():
    """The baseline comes from the right camera's projection matrix (P[3] = -fx * b); a swapped
    pair, a left info on the right topic or sizes that disagree are named."""
    import dataclasses

    from coop_slam.ros.convert import camera_info_to_msg, stereo_camera_from_infos
    from helpers import camera

    stereo = dataclasses.replace(camera(), sensor="stereo", baseline_m=0.12)
    left = _wire(camera_info_to_msg(stereo))
    right = _wire(camera_info_to_msg(stereo, right=True))
    got = stereo_camera_from_infos(left, right)
    assert got.sensor == "stereo" and got.baseline_m == pytest.approx(0.12)
    assert (got.width, got.height, got.fx, got.cx) == (640, 480, stereo.fx, stereo.cx)
    with pytest.raises(MessageError, match="left and right swapped"):
        stereo_camera_from_infos(right, left)  # the "right" info is the left camera's
    flipped = _wire(camera_info_to_msg(stereo, right=True))
    flipped.P = list(flipped.P[:3]) + [-flipped.P[3]] + list(flipped.P[4:])
    with pytest.raises(MessageError, match="baseline -0.1200 m"):
        stereo_camera_from_infos(left, flipped)
    small = _wire(
        camera_info_to_msg(dataclasses.replace(stereo, width=320, height=240), right=True)
    )
    with pytest.raises(MessageError, match="differ in size"):
        stereo_camera_from_infos(left, small)


def test_an_occupancy_grid_crosses_a_topic_and_comes_back_the_same():
    from coop_slam.dense.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyGrid
    from coop_slam.ros.convert import grid_from_msg, grid_to_msg

    cells = np.full((3, 4), UNKNOWN, np.int8)
    cells[0, :2], cells[2, 3] = FREE, OCCUPIED
    grid = OccupancyGrid(cells, 0.05, (-1.0, 2.5))
    msg = _wire(grid_to_msg(grid, "world", z_m=0.1))
    assert (msg.info.width, msg.info.height, msg.header.frame_id) == (4, 3, "world")
    assert msg.info.origin.position.z == pytest.approx(0.1)
    back = grid_from_msg(msg)
    assert np.array_equal(back.cells, cells) and back.origin_xy_m == (-1.0, 2.5)
    msg.data = msg.data[:-1]
    with pytest.raises(MessageError, match="11 cells for 4 x 3"):
        grid_from_msg(msg)
