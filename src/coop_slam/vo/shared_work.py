"""Work shared between threads: OpenCV runs without Python's lock, so an image's pyramid levels
go to whichever thread is free first -- the caller, the process's one worker thread, or a thread
that would otherwise wait for the result. When the other core is busy (local mapping, the other
image of a stereo pair) the caller simply does every level itself rather than wait."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

# Shared by all odometries of a process, made on first use.
_WORKER: list = []
_WORKER_LOCK = threading.Lock()


def shared_worker() -> ThreadPoolExecutor:
    """The process's one worker thread for shared jobs."""
    with _WORKER_LOCK:
        if not _WORKER:
            _WORKER.append(ThreadPoolExecutor(1, thread_name_prefix="shared_work"))
        return _WORKER[0]


class SharedJob:
    """``work(i)`` for i in 0..n-1 (an image's pyramid levels, largest first), each item handed
    out to whichever thread asks first (:meth:`drain`); the owner's :meth:`join` returns
    {i: result} once every item is done, raising the first error any thread met."""

    def __init__(self, work, n_items: int):
        self._work = work
        self._n = n_items
        self._next = 0
        self._busy = 0
        self._cond = threading.Condition()
        self._done: dict = {}
        self._error: BaseException | None = None

    @property
    def exhausted(self) -> bool:
        return self._next == self._n

    def drain(self) -> None:
        while True:
            with self._cond:
                if self._next == self._n:
                    return
                item = self._next
                self._next += 1
                self._busy += 1
            try:
                self._done[item] = self._work(item)
            except BaseException as exc:  # noqa: B036  (re-raised in the owner's join)
                self._error = self._error or exc
            finally:
                with self._cond:
                    self._busy -= 1
                    self._cond.notify_all()

    def join(self) -> dict:
        self.drain()
        with self._cond:
            self._cond.wait_for(lambda: self._busy == 0)
        if self._error is not None:
            raise self._error
        return self._done
