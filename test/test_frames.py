"""A robot's frames: configurable names, and map -> odom over a base's own odometry."""

import numpy as np
import pytest

from coop_slam.errors import ConfigError
from coop_slam.frames import FrameConfig, T_map_odom_over
from coop_slam.geometry import se3
from coop_slam.ros.params import client_params


def _yaw(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def test_map_odom_over_a_drifting_wheel_odometry_puts_the_base_where_the_map_says():
    """Wheel odometry drifts (its odom -> base_link is off by 0.3 m and 5 degrees); TF's chain
    map -> odom -> base_link still gives the visual pose."""
    T_map_base = se3(_yaw(40.0), [2.0, 1.0, 0.0])
    T_odom_base = se3(_yaw(45.0), [2.3, 0.8, 0.0])
    T_map_odom = T_map_odom_over(T_map_base, T_odom_base)
    np.testing.assert_allclose(T_map_odom @ T_odom_base, T_map_base, atol=1e-12)
    assert not np.allclose(T_map_odom, np.eye(4))


def test_frame_names_default_to_the_robots_and_can_be_the_bases_own():
    names = FrameConfig().names(2)
    assert (names.map, names.odom, names.base, names.camera) == (
        "robot_2/map",
        "robot_2/odom",
        "robot_2/base_link",
        "robot_2/camera_optical",
    )
    own = FrameConfig(odom_frame="odom", base_frame="base_footprint").names(2)
    assert (own.map, own.odom, own.base) == ("robot_2/map", "odom", "base_footprint")


def test_bad_frame_parameters_are_refused_by_name():
    with pytest.raises(ConfigError, match="odom_frame"):
        client_params({"robot_id": 1, "odom_frame": "/odom"})
    with pytest.raises(ConfigError, match="must differ"):
        client_params({"robot_id": 1, "base_frame": "robot_1/odom"})
    p = client_params({"robot_id": 1, "external_odom": True, "publish_camera_tf": False})
    assert p.frame_config.external_odom and not p.frame_config.publish_camera_tf
