"""``scripts/export_bag``: write a synthetic scenario or a dataset folder as a rosbag with the
player's topics (per robot ``robot_k/camera/...`` and ``robot_k/ground_truth/pose``), or with
the TUM RGB-D benchmark's own (``--topics tum``: one camera, ``/camera/rgb/image_color``,
``/camera/depth/image``, ``/camera/rgb/camera_info``, ground truth as ``/tf world -> kinect``).

Such a bag is what a team of real robots would record; ``scripts/demo --bag`` runs the system on
it, and evaluates against the ground-truth topic when the bag has one.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from ..errors import CoopSlamError
from ..playback import build_schedule, ground_truth_by_frame, load_run_source
from .progress import throttled
from .sequence_args import add_duration_argument, check_duration


class ExportError(CoopSlamError):
    """The bag cannot be written (bad output path, unreadable frames)."""


def export_bag(
    source,
    out_path: str,
    keep_timing: bool = False,
    depth_encoding: str = "16UC1",
    progress=None,
    topics: str = "coop_slam",
) -> int:
    """Write every robot's frames of ``source`` (see :func:`coop_slam.playback.load_streams`) in
    playback order to ``out_path`` (LZ4-compressed); returns the number of frames written.
    ``topics``: the player's (``coop_slam``) or the TUM benchmark's (``tum``, one RGB-D camera)."""
    import rosbag
    import rospy

    from ..datasets import DatasetError
    from ..ros.camera_messages import frame_messages

    schedule = build_schedule(source.streams, keep_timing=keep_timing)
    if not schedule:
        raise ExportError("nothing to export: the source has no frames")
    rename = _tum_names(source) if topics == "tum" else None
    streams = {s.robot_id: s for s in source.streams}
    gt = {s.robot_id: ground_truth_by_frame(s) for s in source.streams}
    parent = os.path.dirname(os.path.abspath(out_path))
    if not os.path.isdir(parent):
        raise ExportError(f"output folder {parent} does not exist")
    tmp = out_path + ".active"  # a half-written bag never carries the final name
    try:
        with rosbag.Bag(tmp, "w", compression="lz4") as bag:
            for n, item in enumerate(schedule, 1):
                T_world_cam = gt[item.robot_id][item.frame.index]
                stamp = rospy.Time.from_sec(item.play_s)
                for topic, msg in frame_messages(
                    streams[item.robot_id], item.frame, item.play_s, depth_encoding, T_world_cam
                ):
                    if rename is not None:
                        topic, msg = rename(topic, msg)
                        if topic is None:
                            continue
                    bag.write(topic, msg, stamp)
                if progress is not None:
                    progress(n, len(schedule))
    except DatasetError as exc:
        os.remove(tmp)
        raise ExportError(str(exc)) from None
    os.replace(tmp, out_path)
    return len(schedule)


def _tum_names(source):
    """(player topic, message) -> (the TUM benchmark bag's topic, message) of a one-camera RGB-D
    source; the ground truth as /tf world -> kinect."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    from ..bag_topics import DRIVERS
    from ..playback import camera_topics

    if len(source.streams) != 1 or source.streams[0].sequence.camera.sensor != "rgbd":
        raise ExportError("--topics tum: a TUM RGB-D bag holds one RGB-D camera")
    rid = source.streams[0].robot_id
    tum = next(d for d in DRIVERS if d.name == "tum")
    own = camera_topics(rid, "rgbd")
    names = {own["image"]: "/" + tum.image, own["second"]: "/" + tum.second}
    names.update({own["infos"][role]: "/" + t for role, t in tum.infos.items()})

    def rename(topic, msg):
        if topic in names:
            msg.header.frame_id = "openni_rgb_optical_frame"
            return names[topic], msg
        if topic.endswith("/ground_truth/pose"):
            tf = TransformStamped()
            tf.header.stamp, tf.header.frame_id, tf.child_frame_id = (
                msg.header.stamp,
                "/world",
                "/kinect",
            )
            p, o = msg.pose.position, msg.pose.orientation
            tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = (
                p.x,
                p.y,
                p.z,
            )
            tf.transform.rotation = o
            return "/tf", TFMessage([tf])
        return None, None

    return rename


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/export_bag", description=__doc__.split("\n\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", help="synthetic scenario")
    src.add_argument("--dataset", help="TUM RGB-D or KITTI odometry folder")
    p.add_argument("--robots", type=int, default=None, help="number of robots")
    p.add_argument(
        "--sensors",
        help="each robot's camera, comma-separated, or one for all: rgbd, stereo, mono "
        "(default: RGB-D for synthetic worlds, what a dataset has)",
    )
    p.add_argument("--split", help="inclusive frame ranges, one robot each: 0-299,300-599")
    p.add_argument("--keep-timing", action="store_true", help="keep split segments' own times")
    p.add_argument("--seed", type=int, default=0, help="synthetic world seed")
    add_duration_argument(p)
    p.add_argument("--camera", help="camera.yaml for a dataset folder without one")
    p.add_argument(
        "--depth-encoding", choices=("16UC1", "32FC1"), default="16UC1", help="depth image type"
    )
    p.add_argument(
        "--topics",
        choices=("coop_slam", "tum"),
        default="coop_slam",
        help="topic names: the player's (per robot) or the TUM RGB-D benchmark's (one camera, "
        "ground truth on /tf world -> kinect; with --depth-encoding 32FC1 as theirs)",
    )
    p.add_argument("--out", required=True, help="bag file to write")
    args = p.parse_args(argv)
    check_duration(p, args)
    t0 = time.monotonic()
    progress = throttled(
        lambda done, total: print(
            f"[export_bag] {done}/{total} frames ({100 * done / total:.0f} %)", flush=True
        )
    )

    try:
        source = load_run_source(vars(args))
        n = export_bag(
            source, args.out, args.keep_timing, args.depth_encoding, progress, args.topics
        )
    except CoopSlamError as exc:
        print(f"[export_bag] ERROR: {exc}", file=sys.stderr)
        return 2
    size_mb = os.path.getsize(args.out) / 1e6
    print(
        f"[export_bag] {args.out}: {len(source.streams)} robots, {n} frames, {size_mb:.0f} MB "
        f"in {time.monotonic() - t0:.0f} s",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
