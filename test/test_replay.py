"""scripts/replay on a recorded run whose keyframes share descriptors (no ROS master: a bag)."""

import os

import numpy as np
import pytest

from helpers import make_keyframe

pytest.importorskip("coop_slam.msg", reason="generated messages need the catkin workspace")
rosbag = pytest.importorskip("rosbag")

REPO = os.path.normpath(os.path.join(os.path.dirname(__file__), ".."))


def test_replay_takes_keyframes_sharing_descriptors_and_keeps_their_stamps(tmp_path):
    import dataclasses

    import rospy

    from coop_slam.ros.wire_bridge import to_ros
    from coop_slam.tools.replay import replay
    from coop_slam.uplink.planner import Planner
    from coop_slam.wire.codec import encode

    a = make_keyframe(n=80, keyframe_id=1)
    b = make_keyframe(n=80, keyframe_id=2, seed=1)
    b = dataclasses.replace(b, stamp_s=13.5, descriptors=b.descriptors.copy())
    b.map_point_ids = a.map_point_ids.copy()  # b tracks a's map points, seen alike
    b.descriptors[::2] = a.descriptors[::2]
    uplink, bag_path = Planner(), str(tmp_path / "run.bag")
    with rosbag.Bag(bag_path, "w") as bag:
        for rec in (a, b):
            out = uplink.prepare(rec)
            msg = to_ros(encode(rec, out, "robot_1/map"))
            bag.write("/robot_1/keyframes", msg, rospy.Time.from_sec(rec.stamp_s))
    assert out.refs is not None  # b went without a's descriptors
    server, result, stamps = replay(
        bag_path, {"robot_ids": [1]}, os.path.join(REPO, "config", "server.yaml")
    )
    assert result["rejected"] == 0 and result["keyframes"] == 2
    assert stamps == {(1, 1): 12.5, (1, 2): 13.5}
    np.testing.assert_array_equal(server.store.record((1, 2)).descriptors, b.descriptors)


def test_replay_configures_the_server_as_the_launch_file_did():
    from coop_slam.tools.replay import _server_config

    path = os.path.join(REPO, "config", "server.yaml")
    info = {"robot_ids": [1, 2], "ground_robots": True, "low_bandwidth": True}
    cfg = _server_config(path, info, {})
    assert cfg.pull.enabled and cfg.global_ba.planar_motion and cfg.robots == [1, 2]
    assert not _server_config(path, {"robot_ids": [1, 2]}, {}).pull.enabled
