#!/usr/bin/env python3
"""rostest node: the client publishes keyframes, pose, TF (map -> odom -> base_link -> camera),
path and local cloud with the right frames while the player plays a short synthetic sequence; a
correction from the server moves its path and cloud onto the poses it carries."""
import os
import sys
import threading
import time
import unittest

import numpy as np
import rospy
import rostest
import tf2_ros
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Bool

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from coop_slam.geometry import se3  # noqa: E402
from coop_slam.msg import FrameStats, KeyframeMessage, MapCorrection  # noqa: E402
from coop_slam.ros.convert import (  # noqa: E402
    cloud_from_msg,
    pose_from_msg,
    pose_to_msg,
    transform_to_msg,
)
from coop_slam.ros.wire_bridge import from_ros  # noqa: E402
from coop_slam.wire import messages as wm  # noqa: E402
from coop_slam.wire.codec import Incomplete, decode  # noqa: E402
from helpers import wait_until  # noqa: E402


class ClientOutputsTest(unittest.TestCase):
    def test_outputs(self):
        rospy.init_node("client_test")
        got = {"kf": [], "pose": [], "path": None, "cloud": None, "stats": []}
        done = threading.Event()
        subs = [  # noqa: F841 - keeps the subscribers referenced for the whole test
            rospy.Subscriber(
                "/robot_1/keyframes",
                KeyframeMessage,
                lambda m: got["kf"].append(m),
                queue_size=100,
            ),
            rospy.Subscriber(
                "/robot_1/pose", PoseStamped, lambda m: got["pose"].append(m), queue_size=100
            ),
            rospy.Subscriber("/robot_1/path", Path, lambda m: got.__setitem__("path", m)),
            rospy.Subscriber(
                "/robot_1/local_map", PointCloud2, lambda m: got.__setitem__("cloud", m)
            ),
            rospy.Subscriber(
                "/robot_1/frame_stats", FrameStats, lambda m: got["stats"].append(m), queue_size=100
            ),
            rospy.Subscriber("/player/done", Bool, lambda m: m.data and done.set()),
        ]
        buf = tf2_ros.Buffer()
        tf2_ros.TransformListener(buf)
        self.assertTrue(done.wait(500.0), "player did not finish")
        # In lock-step every frame was acknowledged before the player finished; the last
        # messages may still be on their way to this node.
        wait_until(
            lambda: got["path"] is not None
            and got["cloud"] is not None
            and buf.can_transform("robot_1/map", "robot_1/camera_optical", rospy.Time(0)),
            30.0,
            "the client's path, cloud and TF",
        )
        self.assertGreaterEqual(len(got["stats"]), 100, "the client acknowledged too few frames")
        self.assertTrue(all(s.robot_id == 1 for s in got["stats"]))
        self.assertGreaterEqual(sum(s.tracking_ok for s in got["stats"]), 0.9 * len(got["stats"]))
        self.assertGreaterEqual(len(got["kf"]), 2)
        # Taken as the server takes them: each once, in sequence order (no server acknowledges
        # here, so the client sends them again and again), completed from the keyframes held.
        # The keyframes held back until the player was done go last: wait until no new message
        # came for 3 s (messages sent again carry the sequence they had).
        newest, since = 0, time.monotonic()
        while time.monotonic() - since < 3.0:
            top = max(m.sequence for m in got["kf"])
            if top != newest:
                newest, since = top, time.monotonic()
            time.sleep(0.2)  # (sim time stopped with the player)
        by_sequence = {m.sequence: m for m in got["kf"]}
        missing = sorted(set(range(1, max(by_sequence) + 1)) - set(by_sequence))
        self.assertFalse(missing, f"keyframe messages never received: {missing}")
        seen = {}  # keyframe id -> as held (delta updates and shared descriptors come from it)
        for _, m in sorted(by_sequence.items()):
            self.assertEqual(m.header.frame_id, "robot_1/map")
            kf = decode(from_ros(m, wm.KeyframeMessage), known_robots={1})
            if isinstance(kf, Incomplete):
                kf = kf.complete(seen.get)
            self.assertTrue(m.sequence > 0 and m.session > 0)  # numbered for delivery
            if m.kind == m.KIND_REMOVAL:
                seen.pop(m.keyframe_id, None)
            else:
                seen[m.keyframe_id] = kf
                self.assertGreater(kf.num_keypoints, 100)
                self.assertGreater(np.count_nonzero(kf.map_point_ids), 50)
        self.assertGreater(len(got["pose"]), 100)
        self.assertEqual(got["pose"][-1].header.frame_id, "robot_1/map")
        self.assertIsNotNone(got["path"])
        self.assertEqual(got["path"].header.frame_id, "robot_1/map")
        self.assertGreaterEqual(len(got["path"].poses), 2)
        self.assertIsNotNone(got["cloud"])
        self.assertEqual(got["cloud"].header.frame_id, "robot_1/map")
        self.assertGreater(len(cloud_from_msg(got["cloud"])), 100)
        for parent, child in (
            ("robot_1/map", "robot_1/odom"),
            ("robot_1/odom", "robot_1/base_link"),
            ("robot_1/base_link", "robot_1/camera_optical"),
            ("robot_1/map", "robot_1/camera_optical"),
        ):
            self.assertTrue(
                buf.can_transform(parent, child, rospy.Time(0)), f"no TF {parent} -> {child}"
            )
        # The pose stream and TF agree on where the camera is.
        T = buf.lookup_transform("robot_1/map", "robot_1/camera_optical", rospy.Time(0))
        p = got["pose"][-1].pose.position
        t = T.transform.translation
        self.assertLess(np.linalg.norm([p.x - t.x, p.y - t.y, p.z - t.z]), 0.2)

        # Pose-graph sharing: the server sends corrected poses of the client's keyframes; the
        # client shows its path and cloud there (map -> odom too, with its next frame's pose).
        kept = {k: kf for k, kf in seen.items() if kf.action != 2}
        pub = rospy.Publisher("/robot_1/correction", MapCorrection, queue_size=1, latch=True)

        newest = max(kept)

        def corrected_by(S, stamp):  # every keyframe but the newest moved by S
            corr = MapCorrection(robot_id=1, merged=False, T_world_map=transform_to_msg(np.eye(4)))
            corr.header.stamp = stamp  # the cloud it makes carries it (no earlier one counts)
            corr.keyframe_ids = sorted(kept)
            corr.keyframe_poses = [
                pose_to_msg((np.eye(4) if k == newest else S) @ kept[k].T_map_cam)
                for k in corr.keyframe_ids
            ]
            got["path"] = got["cloud"] = None
            pub.publish(corr)
            wait_until(
                lambda: got["path"] is not None
                and got["cloud"] is not None
                and got["cloud"].header.stamp == stamp,
                30.0,
                "the path and cloud after a correction",
            )
            path = {ps.header.seq: pose_from_msg(ps.pose) for ps in got["path"].poses}
            return path, cloud_from_msg(got["cloud"])

        # The poses the client sent, then the older keyframes moved by S: they and their points
        # move, the newest keyframe and its points stay (one map -> odom offset could not).
        path_sent, cloud_sent = corrected_by(np.eye(4), rospy.Time(10000))
        self.assertEqual(sorted(path_sent), sorted(kept))
        S = se3(t=[0.3, 0.0, 0.0])
        path_moved, cloud_moved = corrected_by(S, rospy.Time(10001))
        for k, T in path_sent.items():
            T_expected = T if k == newest else S @ T
            self.assertLess(np.linalg.norm(path_moved[k][:3, 3] - T_expected[:3, 3]), 1e-3, k)
        self.assertEqual(cloud_moved.shape, cloud_sent.shape)
        shift = cloud_moved - cloud_sent
        moved = np.linalg.norm(shift - [0.3, 0.0, 0.0], axis=1) < 1e-3
        still = np.linalg.norm(shift, axis=1) < 1e-3
        self.assertTrue((moved | still).all())
        self.assertTrue(moved.any() and still.any(), (moved.sum(), still.sum()))


if __name__ == "__main__":
    rostest.rosrun("coop_slam", "client_outputs", ClientOutputsTest)
