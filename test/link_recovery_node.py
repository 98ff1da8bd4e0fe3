#!/usr/bin/env python3
"""The nodes of test_link_recovery: ``sub watch|plain`` subscribes /robot_1/keyframes (as the
server does, with or without the link watch) and prints each message's sequence; ``pub
raw|guarded`` publishes good messages, one that cannot be serialized (raw: rospy's publish as is;
guarded: the client's publish_guarded), then good ones again."""

import sys
import time

import rospy

from coop_slam.ros.link_watch import LinkWatch, publish_guarded
from coop_slam.ros.wire_bridge import to_ros
from coop_slam.wire.codec import encode
from helpers import make_keyframe

TOPIC = "/robot_1/keyframes"


def say(*args) -> None:
    print(args[0] % args[1:], flush=True)


def sub(mode: str) -> None:
    from coop_slam.msg import KeyframeMessage

    rospy.init_node(f"link_sub_{mode}")

    def got(msg) -> None:
        print(f"got {msg.sequence}", flush=True)

    def make():
        return rospy.Subscriber(TOPIC, KeyframeMessage, got, queue_size=500, buff_size=2**24)

    if mode == "watch":
        LinkWatch("test", period_s=0.5, say=say).watch(TOPIC, make, "robot 1's keyframe")
    else:
        make()
    print("ready", flush=True)
    rospy.spin()


def pub(mode: str) -> None:
    from coop_slam.msg import KeyframeMessage

    rospy.init_node("link_pub")
    out = rospy.Publisher(TOPIC, KeyframeMessage, queue_size=100)
    deadline = time.monotonic() + 20.0
    while out.get_num_connections() < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(0.5)
    msg = encode(make_keyframe(n=30, keyframe_id=1), frame_id="robot_1/map")
    for seq in range(1, 41):
        msg.sequence = seq
        ros = to_ros(msg)
        if seq == 5:
            ros.keyframe[0].keypoint_step_px = 1e300  # does not fit a float32
            if mode == "guarded":
                print(f"refused: {publish_guarded(out, ros)}", flush=True)
            else:
                try:
                    out.publish(ros)
                except Exception as exc:
                    print(f"raised: {type(exc).__name__}", flush=True)
        else:
            out.publish(ros)
        time.sleep(0.25)
    print("done", flush=True)


if __name__ == "__main__":
    {"sub": sub, "pub": pub}[sys.argv[1]](sys.argv[2])
