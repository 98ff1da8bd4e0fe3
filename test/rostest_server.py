#!/usr/bin/env python3
"""rostest node: two robots' keyframes into the server node; after the merge the stitched cloud,
markers, TF world -> robot_2/map, robot 2's correction and its optimized path are published and
consistent with the truth; the global BA service succeeds; the rendezvous service refuses merged
or unknown robots with a reason; a bad keyframe is rejected. Robot 2's messages are numbered
(delivery): sent out of order and twice, each is taken once and acknowledged; the team map saves
to a file, and loading one is refused once robots have sent keyframes."""
import json
import os
import sys
import threading
import time
import unittest

import numpy as np
import rospy
import rostest
import tf2_ros
from nav_msgs.msg import OccupancyGrid, Path
from rosgraph_msgs.msg import Log
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from coop_slam.geometry import invert, transform_error  # noqa: E402
from coop_slam.msg import KeyframeMessage, MapCorrection, MergeEvent  # noqa: E402
from coop_slam.ros.convert import cloud_from_msg, pose_from_msg, transform_from_msg  # noqa: E402
from coop_slam.ros.wire_bridge import to_ros  # noqa: E402
from coop_slam.wire.codec import encode  # noqa: E402
from helpers import (  # noqa: E402
    TEAM_T_WORLD_MAP,
    cylinder_depth_blob,
    cylinder_world,
    team_keyframes,
    wait_until,
)


class ServerTeamMapTest(unittest.TestCase):
    def test_team_map_after_merge(self):
        rospy.init_node("server_test")
        got, rosout = {}, []
        event = {
            k: threading.Event()
            for k in ("merge", "cloud", "markers", "corr", "path", "dense", "grid")
        }

        def keep(name, ready=lambda m: True):
            def cb(msg):
                got[name] = msg
                if ready(msg) and name in event:
                    event[name].set()

            return cb

        keep_merge = keep("merge")

        def merges_only(msg):  # links and loops inside a group come on the topic too
            if msg.type not in ("link", "loop"):
                keep_merge(msg)

        subs = [  # noqa: F841 (kept alive)
            rospy.Subscriber("/merge_events", MergeEvent, merges_only),
            rospy.Subscriber(
                "/team_map/cloud", PointCloud2, keep("cloud", lambda m: m.width * m.height > 100)
            ),
            rospy.Subscriber(
                "/team_map/markers",
                MarkerArray,
                keep("markers", lambda m: any(x.ns == "merges" for x in m.markers)),
            ),
            rospy.Subscriber(
                "/robot_2/correction", MapCorrection, keep("corr", lambda m: m.merged)
            ),
            rospy.Subscriber(
                "/team_map/robot_2/path",
                Path,
                keep("path", lambda m: m.header.frame_id == "world" and len(m.poses) == 8),
            ),
            rospy.Subscriber("/server/stats", String, keep("stats")),
            rospy.Subscriber(
                "/team_map/dense", PointCloud2, keep("dense", lambda m: m.width * m.height > 100)
            ),
            rospy.Subscriber("/team_map/grid", OccupancyGrid, keep("grid")),
        ]
        subs.append(rospy.Subscriber("/rosout", Log, lambda m: rosout.append(m.msg)))
        buf = tf2_ros.Buffer()
        tf2_ros.TransformListener(buf)
        pubs = {
            r: rospy.Publisher(f"/robot_{r}/keyframes", KeyframeMessage, queue_size=100)
            for r in (1, 2)
        }
        wait_until(
            lambda: all(p.get_num_connections() > 0 for p in pubs.values()),
            60.0,
            "the server to subscribe to /robot_1/keyframes and /robot_2/keyframes",
        )
        # The server's /rosout reaches this node before anything it logs matters: a request it
        # refuses (robot 9 is unknown) is logged and must arrive.
        from coop_slam.srv import Rendezvous

        rospy.wait_for_service("/server/rendezvous", 30.0)
        rendezvous = rospy.ServiceProxy("/server/rendezvous", Rendezvous)
        for _ in range(150):
            if any("robot_9" in m for m in rosout):
                break
            self.assertFalse(rendezvous(robot_a=1, robot_b=9, stamp=rospy.Time(0)).accepted)
            time.sleep(0.2)
        else:
            self.fail("the server's log lines never reached /rosout")
        points, desc = cylinder_world(seed=3)
        kfs = team_keyframes(1, np.linspace(0, 2 * np.pi, 36, endpoint=False), points, desc)
        kfs += team_keyframes(
            2, np.linspace(2.0, 3.0, 8), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
        )
        from coop_slam.msg import KeyframeAck

        for kf in kfs:  # each brings its depth image: the server's dense map and grid (of a
            # wall nearer than the features', within the grid's 4 m range)
            kf.depth_image = cylinder_depth_blob(kf, radius_m=3.5)
        acks = []
        subs.append(rospy.Subscriber("/robot_2/keyframe_ack", KeyframeAck, acks.append))
        msgs = []
        for kf in kfs:
            msg = to_ros(encode(kf, frame_id=f"robot_{kf.robot_id}/map"))
            if kf.robot_id == 2:  # a client's numbered messages (session 5)
                msg.session, msg.sequence = 5, len(msgs) + 1
                msgs.append(msg)
            else:
                pubs[1].publish(msg)
                time.sleep(0.05)
        # Robot 2's radio: the second message comes late, the fourth twice.
        for msg in [msgs[0], *msgs[2:4], msgs[1], msgs[3], *msgs[4:]]:
            pubs[2].publish(msg)
            time.sleep(0.05)
        bad = team_keyframes(1, [0.5], points, desc, kid0=99)[0]
        bad.robot_id = 7  # unknown robot: rejected with a log line, nothing stored changes
        pubs[1].publish(to_ros(encode(bad, frame_id="robot_7/map")))
        for name, ev in event.items():
            self.assertTrue(ev.wait(300.0), f"nothing (valid) on the {name} topic")
        truth = invert(TEAM_T_WORLD_MAP[1]) @ TEAM_T_WORLD_MAP[2]
        merge = got["merge"]
        self.assertEqual((merge.robot_a, merge.robot_b, merge.type), (1, 2, "place_recognition"))
        dt, dr = transform_error(transform_from_msg(merge.T_mapA_mapB), truth)
        self.assertLess(dt, 0.03)
        self.assertLess(dr, 1.0)
        # Correction, TF and optimized path tell the same story, and it is the true one.
        T_corr = transform_from_msg(got["corr"].T_world_map)
        self.assertLess(transform_error(T_corr, truth)[0], 0.03)
        tf = buf.lookup_transform("world", "robot_2/map", rospy.Time(0), rospy.Duration(30.0))
        t = tf.transform.translation
        self.assertLess(np.linalg.norm(np.array([t.x, t.y, t.z]) - T_corr[:3, 3]), 0.03)
        path = got["path"]
        self.assertEqual(len(path.poses), 8)
        first = pose_from_msg(path.poses[0].pose)
        true_first = truth @ kfs[36].T_map_cam
        self.assertLess(transform_error(first, true_first)[0], 0.03)
        # The stitched cloud: both robots' points of the same wall on the same cylinder.
        from coop_slam.geometry import transform_points

        xyz = transform_points(TEAM_T_WORLD_MAP[1], cloud_from_msg(got["cloud"]))
        self.assertLess(np.median(np.abs(np.linalg.norm(xyz[:, :2], axis=1) - 5.0)), 0.05)
        # The dense map lies on the cylinder too; the grid is in world (cameras at 1.2 m: the
        # floor band sees the wall below them).
        xyz = transform_points(TEAM_T_WORLD_MAP[1], cloud_from_msg(got["dense"]))
        self.assertLess(np.median(np.abs(np.linalg.norm(xyz[:, :2], axis=1) - 3.5)), 0.03)
        grid = got["grid"]
        self.assertEqual(grid.header.frame_id, "world")
        self.assertGreater(sum(1 for c in grid.data if c == 100), 100)
        # Why the server merged is logged by the core, and a user must see it (console, rqt).
        wait_until(
            lambda: any("merged robot 2 into robot 1's map" in m for m in rosout),
            30.0,
            "the core's merge message on /rosout",
        )
        labels = [m.text for m in got["markers"].markers if m.ns == "labels"]
        self.assertIn("robot_2", labels)
        # Global bundle adjustment on request.
        from coop_slam.srv import GlobalBundleAdjustment

        rospy.wait_for_service("/server/global_ba", 30.0)
        res = rospy.ServiceProxy("/server/global_ba", GlobalBundleAdjustment)(0)
        self.assertTrue(res.success, res.message)
        self.assertEqual(res.keyframes, 44)
        self.assertLessEqual(res.error_after, res.error_before + 1e-6)
        # Operator trigger (service): refused with a reason for merged or unknown robots.
        res = rendezvous(robot_a=1, robot_b=2, stamp=rospy.Time(0))
        self.assertFalse(res.accepted)
        self.assertIn("already merged", res.message)
        res = rendezvous(robot_a=1, robot_b=9, stamp=rospy.Time(0))
        self.assertFalse(res.accepted)
        self.assertIn("robot 9 is unknown", res.message)
        wait_until(
            lambda: json.loads(got["stats"].data)["rejected"] >= 1,
            30.0,
            "/server/stats to count the rejected keyframe",
        )
        stats = json.loads(got["stats"].data)
        self.assertEqual(stats["groups"], [[1, 2]])
        # Each of robot 2's messages taken once (8 keyframes), in order, and acknowledged.
        wait_until(
            lambda: acks and (acks[-1].session, acks[-1].sequence) == (5, 8),
            30.0,
            "robot 2's acknowledgement of sequence 8",
        )
        self.assertEqual(acks[-1].last_keyframe_id, 8)
        self.assertTrue(acks[-1].durable)
        # Receipts on arrival (not sent again while the server is busy), from one server run.
        received = {a.received_sequence for a in acks if a.received_session == 5}
        self.assertEqual(received, set(range(1, 9)))
        self.assertEqual({a.server_session for a in acks}, {acks[-1].server_session})
        self.assertNotEqual(acks[-1].server_session, 0)
        wait_until(
            lambda: json.loads(got["stats"].data)["duplicates"] >= 1,
            30.0,
            "/server/stats to count the duplicate",
        )
        self.assertEqual(json.loads(got["stats"].data)["keyframes_stored"], {"1": 36, "2": 8})
        from coop_slam.srv import LoadMap, SaveMap

        out = os.path.join(os.environ.get("ROS_LOG_DIR", "/tmp"), "saved.map")
        rospy.wait_for_service("/server/save_map", 30.0)
        res = rospy.ServiceProxy("/server/save_map", SaveMap)(path=out)
        self.assertTrue(res.success, res.message)
        self.assertTrue(os.path.getsize(res.path) > 0)
        res = rospy.ServiceProxy("/server/save_map", SaveMap)(path="/no/such/folder/x.map")
        self.assertFalse(res.success)
        self.assertIn("does not exist", res.message)
        res = rospy.ServiceProxy("/server/load_map", LoadMap)(path=out)
        self.assertFalse(res.success)
        self.assertIn("only before robots send keyframes", res.message)


if __name__ == "__main__":
    rostest.rosrun("coop_slam", "server_team_map", ServerTeamMapTest)
