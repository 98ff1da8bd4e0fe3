"""Camera and ground-truth messages of a dataset frame, as a robot's camera driver would publish
them: what the dataset player sends and ``scripts/export_bag`` writes."""

from __future__ import annotations

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped

from ..playback import RobotStream, camera_topics
from .convert import camera_info_to_msg, image_to_msg, pose_to_msg


def frame_messages(
    stream: RobotStream,
    frame,
    play_s: float,
    depth_encoding: str = "32FC1",
    T_world_cam: np.ndarray | None = None,
):
    """The messages of one robot's frame at ``play_s``, in publishing order: [(topic, msg)].

    Camera info, depth (or the right image), then colour (left): clients keep the camera info and
    synchronise the images; ground truth ``T_world_cam`` (camera optical frame in ``gt_world``),
    when given and finite, last.
    """
    seq = stream.sequence
    ns = f"/{stream.name}"
    optical_frame = f"{stream.name}/camera_optical"
    stamp = rospy.Time.from_sec(play_s)
    color = seq.load_color(frame)
    enc = "bgr8" if color.ndim == 3 else "mono8"
    topics = camera_topics(stream.robot_id, seq.camera.sensor)
    if seq.camera.sensor == "stereo":
        right = seq.load_right(frame)
        right_frame = f"{stream.name}/camera_right_optical"
        out = [
            (topics["infos"]["left"], camera_info_to_msg(seq.camera, stamp, optical_frame)),
            (
                topics["infos"]["right"],
                camera_info_to_msg(seq.camera, stamp, right_frame, right=True),
            ),
            (topics["second"], image_to_msg(right, enc, stamp, right_frame)),
            (topics["image"], image_to_msg(color, enc, stamp, optical_frame)),
        ]
        return out + _ground_truth(ns, stamp, T_world_cam)
    out = [(topics["infos"]["color"], camera_info_to_msg(seq.camera, stamp, optical_frame))]
    if seq.camera.sensor == "rgbd":
        depth_m = seq.load_depth_m(frame)
        if depth_encoding == "16UC1":
            depth_img = np.clip(np.rint(depth_m * 1000.0), 0, 65535).astype(np.uint16)
        else:
            depth_img = depth_m
        out.append(
            (topics["second"], image_to_msg(depth_img, depth_encoding, stamp, optical_frame))
        )
    out.append((topics["image"], image_to_msg(color, enc, stamp, optical_frame)))
    return out + _ground_truth(ns, stamp, T_world_cam)


def messages_bytes(group_messages: dict) -> int:
    """Bytes of image data in a frame group's messages (what the prefetch budget counts)."""
    return sum(
        len(getattr(msg, "data", b""))
        for messages in group_messages.values()
        if isinstance(messages, list)
        for _, msg in messages
    )


def _ground_truth(ns: str, stamp, T_world_cam) -> list:
    if T_world_cam is None or not np.all(np.isfinite(T_world_cam)):
        return []
    msg = PoseStamped(pose=pose_to_msg(T_world_cam))
    msg.header.stamp, msg.header.frame_id = stamp, "gt_world"
    return [(f"{ns}/ground_truth/pose", msg)]
