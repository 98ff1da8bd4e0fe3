"""A client's camera on ROS: camera infos to a camera model, images paired (RGB-D: colour and
depth; stereo: left and right) and handed to the tracking thread, newest frame first
(:class:`coop_slam.frame_slot.LatestFrame`).

Inputs (``sensor``): ``rgbd`` -- ``camera/color/image_raw``, ``camera/depth/image_raw``
(registered to colour) and ``camera/color/camera_info``; ``stereo`` -- a rectified pair,
``camera/left/image_rect``, ``camera/right/image_rect``, ``camera/left/camera_info``,
``camera/right/camera_info`` (the baseline from the right camera's projection matrix); ``mono`` --
``camera/color/image_raw`` and ``camera/color/camera_info``. A stream whose partner never comes is
named on the console, and its frames are reported as not tracked so lock-step playback goes on.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable

import numpy as np
import rospy
from sensor_msgs.msg import CameraInfo, Image

from ..camera import CameraModel
from ..frame_slot import LatestFrame
from ..playback import camera_topics
from .convert import (
    MessageError,
    camera_from_info,
    depth_from_msg,
    image_from_msg,
    stereo_camera_from_infos,
)
from .validation import RejectCounter

# How long a frame that came before any camera info waits for one [s]: a camera publishes its
# info with every frame, so it is at most a frame or a loaded machine's scheduling delay behind.
CAMERA_INFO_WAIT_S = 2.0
UNPAIRED_AFTER_S = 3.0  # a main image this old, its partner stream silent as long: reported


class CameraInput:
    """``on_camera(old, new)`` runs when the camera model changes (not for the first one), with
    ``lock`` (the tracker's) held, as the new model is set; ``frame_stats(stamp, dropped)``
    reports a frame that will not be tracked."""

    def __init__(
        self,
        name: str,
        robot_id: int,
        sensor: str,
        depth_scale: float,
        rejects: RejectCounter,
        lock: threading.Lock,
        on_camera: Callable[[CameraModel, CameraModel], None],
        frame_stats: Callable[[object, bool], None],
    ):
        import message_filters

        self.name, self.sensor, self.depth_scale, self.rejects = name, sensor, depth_scale, rejects
        self.lock, self.on_camera, self.frame_stats = lock, on_camera, frame_stats
        self.camera: CameraModel | None = None
        self.slot = LatestFrame()
        self.topics = camera_topics(robot_id, sensor)
        self._camera_ready = threading.Event()
        self._camera_wait_s = CAMERA_INFO_WAIT_S
        self._infos: dict[str, CameraInfo] = {}
        self._info_keys: dict[str, tuple] = {}  # per camera info topic: the last one accepted
        self._info_lock = threading.Lock()
        self.subs = [
            rospy.Subscriber(topic, CameraInfo, self._on_info, which, queue_size=5)
            for which, topic in self.topics["infos"].items()
        ]
        # A stream whose partner never comes (no depth / right images) would stall lock-step
        # playback and leave the user guessing: watch both streams alone as well (rospy
        # deserializes a topic once for all of a node's subscribers).
        self._watch_lock = threading.Lock()
        self._unpaired: list = []  # (wall time, stamp) of main images not yet in a pair
        self._paired: collections.deque = collections.deque(maxlen=64)
        self._last_second_wall = -1e9  # wall time of the last second image [s]
        image = dict(queue_size=5, buff_size=2**24)
        if sensor == "mono":  # one image: nothing to pair
            self.subs.append(rospy.Subscriber(self.topics["image"], Image, self._on_frame, **image))
            return
        pair = [
            message_filters.Subscriber(self.topics[k], Image, **image) for k in ("image", "second")
        ]
        self.sync = message_filters.TimeSynchronizer(pair, 10)
        self.sync.registerCallback(self._on_frame)
        self.subs.append(rospy.Subscriber(self.topics["image"], Image, self._on_alone, **image))
        self.subs.append(rospy.Subscriber(self.topics["second"], Image, self._on_second, **image))
        threading.Thread(target=self._watch_pairs, daemon=True).start()

    def describe(self) -> str:
        return " and ".join(
            rospy.resolve_name(self.topics[k]) for k in ("image", "second") if k in self.topics
        )

    # --- camera infos -----------------------------------------------------------------------------
    def _on_info(self, msg: CameraInfo, which: str) -> None:
        # Every frame brings its camera info; only a change needs a new camera model.
        key = (
            msg.width,
            msg.height,
            msg.distortion_model,
            tuple(msg.D),
            tuple(msg.K),
            tuple(msg.P),
        )
        # One info at a time: stereo's left and right callbacks run in threads of their own, and
        # a camera built from one new and one old info must not be kept as the last accepted.
        with self._info_lock:
            if self.camera is not None and self._info_keys.get(which) == key:
                return
            self._infos[which] = msg
            try:
                if self.sensor == "stereo":
                    if "left" not in self._infos or "right" not in self._infos:
                        return
                    cam = stereo_camera_from_infos(self._infos["left"], self._infos["right"])
                else:  # rgbd or mono: the colour camera
                    cam = camera_from_info(msg, sensor=self.sensor, depth_scale=self.depth_scale)
            except MessageError as exc:
                self._info_keys.pop(which, None)  # the next info is checked again, in full
                self.rejects.reject(self.topics["infos"][which], str(exc))
                return
            self._info_keys[which] = key
            with self.lock:
                if self.camera is not None and cam != self.camera:
                    self.on_camera(self.camera, cam)
                self.camera = cam
                self._camera_ready.set()

    def wait_for_camera(self) -> None:
        """Images and their camera info come on topics of their own, in no order between them:
        the very first image may come before any info (a loaded machine makes that likely), and
        rejecting it would start a monocular map from a later view. It waits for the info."""
        if not self._camera_ready.wait(self._camera_wait_s):
            self._camera_wait_s = 0.0  # none came: no info is published, later frames go at once

    def decode(self, image_msg: Image, second_msg: Image | None) -> tuple[np.ndarray, object]:
        """A frame's images, checked against the camera model; raises MessageError."""
        cam = self.camera
        if cam is None:
            missing = [t for w, t in self.topics["infos"].items() if w not in self._infos]
            raise MessageError(f"no camera_info received yet on {', '.join(missing)}")
        image = image_from_msg(image_msg)
        if self.sensor == "mono":
            if image.shape[:2] != (cam.height, cam.width):
                raise MessageError(
                    f"image {image.shape[1]}x{image.shape[0]} does not match camera_info "
                    f"{cam.width}x{cam.height}"
                )
            return image, None
        if self.sensor == "stereo":
            second, what = image_from_msg(second_msg), "right image"
        else:
            second, what = depth_from_msg(second_msg, self.depth_scale), "depth"
        if image.shape[:2] != (cam.height, cam.width) or second.shape[:2] != image.shape[:2]:
            raise MessageError(
                f"image {image.shape[1]}x{image.shape[0]} / {what} "
                f"{second.shape[1]}x{second.shape[0]} do not match camera_info "
                f"{cam.width}x{cam.height}"
            )
        return image, second

    # --- images -----------------------------------------------------------------------------------
    def _on_frame(self, image_msg: Image, second_msg: Image | None = None) -> None:
        """A camera frame (pair): handed to the tracking thread; one the tracker had not taken
        yet is dropped (the newest frame wins) and said so."""
        stamp = image_msg.header.stamp
        with self._watch_lock:
            self._unpaired = [(t, s) for t, s in self._unpaired if s != stamp]
            self._paired.append(stamp)
        dropped = self.slot.put((image_msg, second_msg))
        if dropped is not None:
            self.frame_stats(dropped[0].header.stamp, True)
            rospy.logwarn_throttle(
                10.0,
                "client %s: busy, %d frame(s) dropped so far (the newest frame is tracked)",
                self.name,
                self.slot.dropped,
            )

    def _on_alone(self, msg: Image) -> None:
        with self._watch_lock:
            if msg.header.stamp not in self._paired:
                self._unpaired.append((time.monotonic(), msg.header.stamp))

    def _on_second(self, msg: Image) -> None:
        self._last_second_wall = time.monotonic()

    def _watch_pairs(self) -> None:
        """Main images older than 3 s while the second stream (depth / right) has been silent for
        3 s: say which topic is silent, and report those frames (not tracked). (Images left over
        while the second stream flows were dropped by a busy client, or are still queued.)"""
        while not rospy.is_shutdown():
            time.sleep(1.0)
            now = time.monotonic()
            with self._watch_lock:
                old = [s for t, s in self._unpaired if now - t > UNPAIRED_AFTER_S]
                if now - self._last_second_wall < UNPAIRED_AFTER_S:
                    continue
                self._unpaired = [(t, s) for t, s in self._unpaired if now - t <= UNPAIRED_AFTER_S]
            if not old:
                continue
            what = "depth" if self.sensor == "rgbd" else "right"
            self.rejects.reject(
                self.topics["image"],
                f"{len(old)} image(s) without a {what} image of the same stamp on "
                f"{rospy.resolve_name(self.topics['second'])} within 3 s: is it published?",
            )
            for stamp in old:
                self.frame_stats(stamp, False)
