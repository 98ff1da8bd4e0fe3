"""The cameras of a bag as the drivers that recorded it named them, each mapped onto the player's
topics and a robot id."""

import pytest

from coop_slam.bag_topics import bag_cameras


def _names(cams):
    return [(c.robot_id, c.sensor, c.driver.name, c.namespace) for c in cams]


def test_a_tum_benchmark_bag_is_one_rgbd_robot():
    topics = {
        "/camera/rgb/image_color",
        "/camera/rgb/camera_info",
        "/camera/depth/image",
        "/camera/depth/camera_info",
        "/imu",
        "/tf",
    }
    (cam,) = bag_cameras(topics)
    assert _names([cam]) == [(1, "rgbd", "tum", "")]
    assert cam.remap == {
        "/camera/rgb/image_color": "/robot_1/camera/color/image_raw",
        "/camera/depth/image": "/robot_1/camera/depth/image_raw",
        "/camera/rgb/camera_info": "/robot_1/camera/color/camera_info",
    }


def test_drivers_under_robot_namespaces_keep_their_ids_others_are_numbered():
    topics = {
        # robot 3 (the player's own names)
        "/robot_3/camera/color/image_raw",
        "/robot_3/camera/depth/image_raw",
        "/robot_3/camera/color/camera_info",
        # a RealSense D435 on "/beta"
        "/beta/camera/color/image_raw",
        "/beta/camera/aligned_depth_to_color/image_raw",
        "/beta/camera/color/camera_info",
        "/beta/camera/depth/image_rect_raw",
        # a stereo pair through stereo_image_proc on "/alpha/stereo"
        "/alpha/stereo/left/image_rect",
        "/alpha/stereo/right/image_rect",
        "/alpha/stereo/left/camera_info",
        "/alpha/stereo/right/camera_info",
        # an openni2 camera on "/gamma"
        "/gamma/camera/rgb/image_raw",
        "/gamma/camera/depth_registered/image_raw",
        "/gamma/camera/rgb/camera_info",
        # a monocular camera on "/delta"
        "/delta/camera/color/image_raw",
        "/delta/camera/color/camera_info",
    }
    assert _names(bag_cameras(topics)) == [
        (1, "stereo", "stereo_image_proc", "/alpha/stereo"),
        (2, "rgbd", "realsense2", "/beta"),
        (3, "rgbd", "coop_slam", "/robot_3"),
        (4, "mono", "mono", "/delta"),
        (5, "rgbd", "openni2", "/gamma"),
    ]


def test_a_player_stereo_pair_is_one_camera_and_a_bare_image_raw_needs_its_info():
    topics = {
        "/robot_1/camera/left/image_rect",
        "/robot_1/camera/right/image_rect",
        "/robot_1/camera/left/camera_info",
        "/robot_1/camera/right/camera_info",
        "/usb_cam/image_raw",  # no camera info: too common a name to take alone
    }
    assert _names(bag_cameras(topics)) == [(1, "stereo", "stereo", "/robot_1")]
    assert _names(bag_cameras(topics | {"/usb_cam/camera_info"}))[1] == (
        2,
        "mono",
        "mono_raw",
        "/usb_cam",
    )
    assert bag_cameras(set()) == []


@pytest.mark.parametrize(
    "depth", ["/camera/depth/image_raw", "/camera/aligned_depth_to_color/image_raw"]
)
def test_colour_with_depth_is_rgbd_not_mono(depth):
    topics = {"/camera/color/image_raw", "/camera/color/camera_info", depth}
    assert [c.sensor for c in bag_cameras(topics)] == ["rgbd"]


def test_a_cameras_other_streams_are_not_taken_for_more_robots():
    """openni2 also records depth and IR images with their infos, stereo_image_proc keeps the
    raw images beside the rectified ones: one camera each, a real second camera still found."""
    openni2 = {
        "/camera/rgb/image_raw",
        "/camera/rgb/camera_info",
        "/camera/depth_registered/image_raw",
        "/camera/depth/image_raw",
        "/camera/depth/camera_info",
        "/camera/ir/image_raw",
        "/camera/ir/camera_info",
    }
    assert _names(bag_cameras(openni2)) == [(1, "rgbd", "openni2", "")]
    stereo = {
        f"/stereo/{side}/{name}"
        for side in ("left", "right")
        for name in ("image_rect", "image_raw", "camera_info")
    }
    assert _names(bag_cameras(stereo)) == [(1, "stereo", "stereo_image_proc", "/stereo")]
    usb = {"/usb_cam/image_raw", "/usb_cam/camera_info"}
    assert _names(bag_cameras(openni2 | usb))[1] == (2, "mono", "mono_raw", "/usb_cam")
