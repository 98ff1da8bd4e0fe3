#!/usr/bin/env python3
"""rostest node: with external_odom the client publishes robot_1/map -> odom over the base's
own odom -> base_footprint (never an edge of its own below odom), so that TF puts the base where
the client's pose says; it describes itself on /robot_1/description with its frames' mount."""
import os
import sys
import threading
import unittest

import numpy as np
import rospy
import rostest
import tf2_ros
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import Bool
from tf2_msgs.msg import TFMessage

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from coop_slam.geometry import se3  # noqa: E402
from coop_slam.msg import RobotDescription  # noqa: E402
from coop_slam.ros.convert import (  # noqa: E402
    description_from_msg,
    pose_from_msg,
    transform_from_msg,
    transform_stamped,
)
from helpers import wait_until  # noqa: E402


class ExternalOdomTest(unittest.TestCase):
    def test_map_to_odom_only(self):
        rospy.init_node("external_odom_test")
        wheels = tf2_ros.StaticTransformBroadcaster()  # the base's own odometry: never moved
        wheels.sendTransform(
            transform_stamped(se3(t=[0.4, -0.2, 0.0]), "odom", "base_footprint", rospy.Time(0))
        )
        got = {"pose": [], "children": set(), "description": None}
        done = threading.Event()
        subs = [  # noqa: F841 - keeps the subscribers referenced for the whole test
            rospy.Subscriber(
                "/robot_1/pose", PoseStamped, lambda m: got["pose"].append(m), queue_size=100
            ),
            rospy.Subscriber(
                "/tf",
                TFMessage,
                lambda m: got["children"].update(
                    (t.header.frame_id, t.child_frame_id) for t in m.transforms
                ),
                queue_size=100,
            ),
            rospy.Subscriber(
                "/robot_1/description",
                RobotDescription,
                lambda m: got.__setitem__("description", m),
            ),
            rospy.Subscriber("/player/done", Bool, lambda m: m.data and done.set()),
        ]
        buf = tf2_ros.Buffer()
        tf2_ros.TransformListener(buf)
        self.assertTrue(done.wait(300.0), "player did not finish")
        wait_until(
            lambda: len(got["pose"]) > 20
            and buf.can_transform("robot_1/map", "base_footprint", rospy.Time(0)),
            30.0,
            "the client's pose and TF map -> odom",
        )
        # The client's edges: map -> odom, base_footprint -> camera; nothing else below odom.
        self.assertIn(("robot_1/map", "odom"), got["children"])
        self.assertNotIn("base_footprint", {child for _, child in got["children"]})  # (/tf)
        self.assertNotIn("robot_1/odom", {child for _, child in got["children"]})
        # TF's chain puts the base where the client's pose says (its last pose's stamp).
        pose = got["pose"][-1]
        T_map_cam = pose_from_msg(pose.pose)
        tf = buf.lookup_transform("robot_1/map", "robot_1/camera_optical", pose.header.stamp)
        T_tf = transform_from_msg(tf.transform)
        self.assertLess(np.linalg.norm(T_tf[:3, 3] - T_map_cam[:3, 3]), 1e-3)
        self.assertGreater(np.linalg.norm(T_map_cam[:3, 3]), 0.3)  # the robot moved
        wait_until(lambda: got["description"] is not None, 10.0, "the robot's description")
        d = description_from_msg(got["description"])
        self.assertEqual((d.robot_id, d.sensor), (1, "rgbd"))
        self.assertGreater(d.marker_size_m, 0)


if __name__ == "__main__":
    rostest.rosrun("coop_slam", "client_external_odom", ExternalOdomTest)
