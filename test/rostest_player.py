#!/usr/bin/env python3
"""rostest node: consumes both robots' streams slowly, acknowledges each frame, and checks that the
player waits for it (lock-step), stamps frames in sim time and publishes camera info and depth."""
import os
import sys
import threading
import time
import unittest

import rospy
import rostest
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Bool

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from coop_slam.msg import FrameStats  # noqa: E402
from helpers import wait_until  # noqa: E402


class PlayerLockstepTest(unittest.TestCase):
    def test_two_robots_lockstep(self):
        rospy.init_node("player_test")
        lock = threading.Lock()
        got = {1: [], 2: []}
        infos = {1: 0, 2: 0}
        depth = {1: 0, 2: 0}
        violations = []
        pending = {}
        acks = {
            k: rospy.Publisher(f"/robot_{k}/frame_stats", FrameStats, queue_size=10) for k in (1, 2)
        }

        def on_color(msg, k):
            with lock:
                if pending.get(k):
                    violations.append((k, msg.header.stamp.to_sec()))
                pending[k] = True
                got[k].append((msg.header.stamp.to_sec(), msg.width, msg.encoding))
            time.sleep(0.2)  # a slow consumer: the player must wait for the ack
            with lock:
                pending[k] = False
            ack = FrameStats(robot_id=k, tracking_ok=True)
            ack.header.stamp = msg.header.stamp
            acks[k].publish(ack)

        def on_info(msg, k):
            infos[k] += 1

        def on_depth(msg, k):
            depth[k] += 1
            self.assertEqual(msg.encoding, "32FC1")

        subs = []
        for k in (1, 2):
            subs.append(rospy.Subscriber(f"/robot_{k}/camera/color/image_raw", Image, on_color, k))
            subs.append(
                rospy.Subscriber(f"/robot_{k}/camera/color/camera_info", CameraInfo, on_info, k)
            )
            subs.append(rospy.Subscriber(f"/robot_{k}/camera/depth/image_raw", Image, on_depth, k))
        done = threading.Event()
        subs.append(rospy.Subscriber("/player/done", Bool, lambda m: m.data and done.set()))
        self.assertTrue(done.wait(90.0), "player did not finish")
        # Lock-step: every frame was acknowledged, so it reached this node; camera infos and
        # depth images travel beside it and may arrive a moment later.
        wait_until(
            lambda: min(infos.values()) >= 6 and min(depth.values()) >= 6,
            10.0,
            "6 camera infos and depth images per robot",
        )
        for k in (1, 2):
            stamps = [s for s, _, _ in got[k]]
            self.assertEqual(len(stamps), 6, f"robot_{k} frames: {stamps}")
            self.assertAlmostEqual(stamps[0], 1.0, places=3)  # robots start together at t0 = 1 s
            self.assertTrue(all(b > a for a, b in zip(stamps, stamps[1:])))
            self.assertEqual(got[k][0][1], 80)
            self.assertEqual(got[k][0][2], "bgr8")
            self.assertGreaterEqual(infos[k], 6)
            self.assertGreaterEqual(depth[k], 6)
        self.assertEqual(
            violations, [], "player published before the previous frame was acknowledged"
        )
        self.assertTrue(rospy.get_param("/use_sim_time"))


if __name__ == "__main__":
    rostest.rosrun("coop_slam", "player_lockstep", PlayerLockstepTest)
