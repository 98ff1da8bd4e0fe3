"""The hand-over between a camera and a tracker that may be slower than it: one slot, newest
frame wins.

A camera does not wait. A queue in front of a slow tracker grows stale (ROS drops its oldest
frames only once the queue is full, so the tracker works on frames up to a queue length old);
here the tracker always gets the newest frame, and a frame replaced before the tracker took it is
dropped at once and counted, so the delay never exceeds one frame.
"""

from __future__ import annotations

import threading
from typing import Any


class LatestFrame:
    def __init__(self):
        self._cond = threading.Condition()
        self._item: Any = None
        self._full = False
        self._closed = False
        self.dropped = 0  # frames replaced before they were taken

    def put(self, item: Any) -> Any | None:
        """Offer a new frame; returns the frame it replaced (dropped), or None."""
        with self._cond:
            old = self._item if self._full else None
            if self._full:
                self.dropped += 1
            self._item, self._full = item, True
            self._cond.notify()
            return old

    def take(self, timeout_s: float | None = None) -> Any | None:
        """The newest frame, waiting up to ``timeout_s`` for one; None on timeout or close."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._full or self._closed, timeout_s):
                return None
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
