"""A tracked frame's outputs -- pose, TF, the path and cloud when due, marker sightings -- and its
FrameStats, published in frame order from a thread of their own.

Made by the tracking thread they took 5-8 ms of a live RedKitchen frame (rospy's publishing, under
the interpreter lock that local mapping wants too): long enough for a frame coming meanwhile to
replace the one waiting (1-3 of 600 dropped a run). Here they are made while the tracker waits for
its next frame, with the tracker's lock held (they read the odometry and the path's state).
Lock-step playback makes them at once, before its frame is finished.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import rospy

from ..errors import CoopSlamError


@dataclass
class TrackedFrame:
    """What a frame's outputs are made of, as it was when tracked."""

    stamp: Any  # rospy.Time of the image
    result: Any  # the odometry's TrackResult
    vo: Any  # the odometry that tracked it
    kf_id_base: int  # its keyframes' message ids start here
    frames: int  # frames tracked so far, this one included
    image: np.ndarray
    K: np.ndarray  # the camera's intrinsics


class FrameOutputs:
    def __init__(
        self,
        name: str,
        lock: threading.Lock,
        pose,
        cues,
        publish_stats: Callable[[Any], None],
        counters: Callable[[Any], None],
        reject: Callable[[str], None],
        beside: bool,
    ):
        """``pose``: the PoseOutput; ``cues``: the TeamCues; ``counters(stats)`` fills the
        delivery counters in; ``reject(text)`` reports a frame the outputs refused; ``beside``:
        in their own thread (else at once)."""
        self.name = name
        self.lock = lock
        self.pose, self.cues = pose, cues
        self.publish_stats, self.counters, self.reject = publish_stats, counters, reject
        self._jobs: queue.Queue | None = None
        if beside:
            self._jobs = queue.Queue()
            threading.Thread(target=self._loop, name="frame_outputs", daemon=True).start()

    def put(self, frame: TrackedFrame | None, stats) -> None:
        """A frame's outputs (``frame`` None: a rejected frame, only its stats)."""
        if self._jobs is None:
            self._publish(frame, stats)
        else:
            self._jobs.put((frame, stats))

    def drain(self, timeout_s: float) -> None:
        """Wait (at most ``timeout_s``) until the frames' outputs so far went."""
        t_end = time.monotonic() + timeout_s
        while self._jobs is not None and self._jobs.unfinished_tasks and time.monotonic() < t_end:
            time.sleep(0.01)

    def _loop(self) -> None:
        while True:
            frame, stats = self._jobs.get()
            try:
                self._publish(frame, stats)
            except Exception as exc:  # this thread publishes every frame's outputs: it goes on
                rospy.logerr("client %s: outputs: %s: %s", self.name, type(exc).__name__, exc)
            finally:
                self._jobs.task_done()

    def _publish(self, frame: TrackedFrame | None, stats) -> None:
        try:
            with self.lock:
                if frame is not None:
                    stamp, res, vo = frame.stamp, frame.result, frame.vo
                    self.pose.frame(stamp, res, vo, frame.kf_id_base)
                    self.cues.sightings(frame.frames, stamp, frame.image, res, vo, frame.K)
                # Counters on every frame's stats, a rejected one's too: the recorder takes a
                # drop in keyframes_sent for a restarted client. Live, the uplink's thread may
                # still be on this frame's events: the counters can be a frame behind (they only
                # grow).
                self.counters(stats)
        except CoopSlamError as exc:
            self.reject(str(exc))
        finally:
            self.publish_stats(stats)
