#!/usr/bin/env python3
"""rostest node: a client's camera model changes (new intrinsics) mid-run; it starts a new map,
whose keyframes and map segment continue after those of the first one: reused ids would make the
server take a new keyframe for an old one. The very first frame comes before any camera info
(separate topics, no order between them): it waits for the info and is tracked, not rejected."""
import dataclasses
import os
import sys
import time
import unittest

import rospy
import rostest
from sensor_msgs.msg import CameraInfo, Image

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import helpers_vo  # noqa: E402
from coop_slam.msg import FrameStats, KeyframeMessage  # noqa: E402
from coop_slam.ros.convert import camera_info_to_msg, image_to_msg  # noqa: E402
from helpers import wait_until  # noqa: E402


def _new(m) -> bool:
    """A new keyframe: sent whole for the first time, or as its place signature (what the
    radio budget holds back)."""
    if m.kind == m.KIND_SIGNATURE:
        return True
    return m.kind == m.KIND_KEYFRAME and not m.keyframe[0].replaces


class CameraChangeTest(unittest.TestCase):
    def test_new_map_continues_the_ids(self):
        rospy.init_node("camera_change_test")
        got, stats = [], []
        subs = [  # noqa: F841 - keeps the subscribers referenced for the whole test
            rospy.Subscriber("/robot_1/keyframes", KeyframeMessage, got.append, queue_size=100),
            rospy.Subscriber("/robot_1/frame_stats", FrameStats, stats.append, queue_size=100),
        ]
        cam = "/robot_1/camera"
        pub_info = rospy.Publisher(f"{cam}/color/camera_info", CameraInfo, queue_size=5)
        pub_depth = rospy.Publisher(f"{cam}/depth/image_raw", Image, queue_size=5)
        pub_color = rospy.Publisher(f"{cam}/color/image_raw", Image, queue_size=5)
        wait_until(
            lambda: pub_color.get_num_connections() and pub_depth.get_num_connections(),
            60.0,
            "the client's subscriptions",
        )
        stamps, frames, _ = helpers_vo.sequence(n_frames=12)
        other = dataclasses.replace(helpers_vo.CAMERA, fx=helpers_vo.CAMERA.fx * 1.1)

        def play(camera, first_s: float, n: int, info_late: bool = False) -> None:
            for i in range(n):
                stamp = rospy.Time.from_sec(first_s + i / 30.0)
                bgr, depth = frames[i]
                info = camera_info_to_msg(camera, stamp, "robot_1/camera_optical")
                if not (info_late and i == 0):
                    pub_info.publish(info)
                pub_depth.publish(image_to_msg(depth, "32FC1", stamp, "robot_1/camera_optical"))
                pub_color.publish(image_to_msg(bgr, "bgr8", stamp, "robot_1/camera_optical"))
                if info_late and i == 0:
                    time.sleep(0.5)
                    pub_info.publish(info)
                time.sleep(0.3)  # a slow camera: the client tracks every frame

        def new_keyframes():  # (without a server to acknowledge them, messages go again)
            first_sends = {(m.session, m.sequence): m for m in got}.values()
            return sorted((m.keyframe_id, m.map_segment) for m in first_sends if _new(m))

        play(helpers_vo.CAMERA, 100.0, 6, info_late=True)
        wait_until(lambda: new_keyframes(), 30.0, "a keyframe of the first map")
        first_frame = [s for s in stats if abs(s.header.stamp.to_sec() - 100.0) < 1e-6]
        self.assertTrue(first_frame, "no frame statistics of the first frame")
        self.assertTrue(first_frame[0].tracking_ok, "the frame before its camera info was lost")
        first = new_keyframes()
        self.assertTrue(all(seg == 0 for _, seg in first), first)
        play(other, 110.0, 6)
        wait_until(
            lambda: any(seg == 1 for _, seg in new_keyframes()), 30.0, "a keyframe of the next map"
        )
        # (the first map's last keyframes may go after the change: new ones are held a while)
        sent = new_keyframes()
        self.assertTrue(all(seg in (0, 1) for _, seg in sent), sent)
        first = [k for k, seg in sent if seg == 0]
        later = [k for k, seg in sent if seg == 1]
        self.assertGreater(min(later), max(first), f"the next map reuses the first's ids: {sent}")


if __name__ == "__main__":
    rostest.rosrun("coop_slam", "client_camera_change", CameraChangeTest)
