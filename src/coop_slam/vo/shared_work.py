"""The process's one worker thread for tracking's side jobs: work that runs without Python's lock
(scipy's KD tree) is done there while the tracking thread goes on in Python."""

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
