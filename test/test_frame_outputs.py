"""A client's frame outputs (pose, path, cloud, sightings, stats) from their own thread: in frame
order, with the tracker's lock held, a refused frame's stats too, and going on after an error."""

import threading
import types

import numpy as np

from coop_slam.errors import CoopSlamError
from coop_slam.ros.frame_outputs import FrameOutputs, TrackedFrame


class _Recorder:
    def __init__(self, lock, fail_on=()):
        self.lock, self.fail_on, self.calls = lock, set(fail_on), []

    def frame(self, stamp, res, vo, kf_id_base):
        assert self.lock.locked(), "the pose output reads the odometry: the tracker's lock held"
        if stamp in self.fail_on:
            raise (CoopSlamError if stamp % 2 else RuntimeError)(f"bad frame {stamp}")
        self.calls.append(("pose", stamp))

    def sightings(self, frames, stamp, image, res, vo, K):
        self.calls.append(("sightings", stamp))


def _outputs(beside, fail_on=()):
    lock = threading.Lock()
    rec = _Recorder(lock, fail_on)
    published, rejected = [], []
    out = FrameOutputs(
        "robot_1",
        lock,
        rec,
        rec,
        lambda stats: (published.append(stats.stamp), rec.calls.append(("stats", stats.stamp))),
        lambda stats: setattr(stats, "counted", True),
        rejected.append,
        beside=beside,
    )
    return out, rec, published, rejected


def _frame(stamp):
    return TrackedFrame(stamp, None, None, 0, stamp, np.zeros((2, 2), np.uint8), np.eye(3))


def test_outputs_go_in_frame_order_from_their_thread_and_errors_do_not_stop_them():
    out, rec, published, rejected = _outputs(beside=True, fail_on={3, 4})
    for stamp in range(1, 7):
        out.put(None if stamp == 5 else _frame(stamp), types.SimpleNamespace(stamp=stamp))
    out.drain(5.0)
    assert published == [1, 2, 3, 4, 5, 6], "every frame's stats, in order, failed ones too"
    poses = [s for kind, s in rec.calls if kind == "pose"]
    assert poses == [1, 2, 6], "no outputs of a refused frame (5) or of the failing ones (3, 4)"
    assert rec.calls.index(("pose", 2)) < rec.calls.index(("stats", 2))  # the pose before stats
    assert rejected == ["bad frame 3"], "a frame the outputs refuse is reported"


def test_lock_step_playback_makes_the_outputs_before_the_frame_is_finished():
    out, rec, published, _ = _outputs(beside=False)
    stats = types.SimpleNamespace(stamp=1)
    out.put(_frame(1), stats)
    assert rec.calls == [("pose", 1), ("sightings", 1), ("stats", 1)] and published == [1]
    assert stats.counted, "the delivery counters are filled in"
