"""Building the stitched team cloud beside the server's worker, not in it.

Fusing eight robots' map points takes a second or more (``scripts/bench --only server_scale``):
built in the worker, every keyframe message that arrived meanwhile waited, and a merge decided
just after waited with them. The worker now only fixes what the cloud is made of (a snapshot of
the keyframes and their poses, milliseconds: :meth:`.server.TeamServer.team_cloud_job`) and hands
it to the one builder thread here, which builds it and hands the result to ``on_built`` (the node
publishes it). The builder takes one job at a time and none while it works: a worker that finds it
busy keeps the map due and hands over a newer snapshot later, so the cloud shown is never older
than one build and no queue of stale clouds forms. How often it builds stays with the cadence
(:mod:`.publish_cadence`), to which the builder reports each build's cost: the builder's share of
the machine stays bounded as before.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

from .publish_cadence import PublishCadence

log = logging.getLogger(__name__)


class TeamMapBuilder:
    def __init__(self, on_built: Callable[[Any, float], None], cadence: PublishCadence):
        """``on_built(cloud, stamp_s)`` receives each built cloud, in the builder thread."""
        self.on_built = on_built
        self.cadence = cadence
        self.built = 0  # clouds built
        self.failed = 0  # builds that raised (logged; the builder carries on)
        self._cv = threading.Condition()
        self._job: tuple[Callable[[], Any], float] | None = None
        self._working = False
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="team map builder", daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        """Whether a build is waiting or running (then :meth:`submit` refuses)."""
        with self._cv:
            return self._working or self._job is not None

    def submit(self, job: Callable[[], Any], stamp_s: float) -> bool:
        """Build ``job()`` (the cloud of data time ``stamp_s``) unless busy; whether taken."""
        with self._cv:
            if self._closed or self._working or self._job is not None:
                return False
            self._job = (job, stamp_s)
            self._cv.notify_all()
            return True

    def wait_idle(self, timeout_s: float | None = None) -> bool:
        """Wait until no build waits or runs; False on timeout."""
        with self._cv:
            return self._cv.wait_for(lambda: not (self._working or self._job), timeout_s)

    def close(self, timeout_s: float | None = 5.0) -> None:
        """Stop the builder after the build in progress, if any."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._job is not None or self._closed)
                if self._closed:
                    return
                (job, stamp_s), self._job = self._job, None
                self._working = True
            started = time.monotonic()
            try:
                self.on_built(job(), stamp_s)
                self.built += 1
            except Exception as exc:  # noqa: BLE001 -- one bad build must not end the builder
                self.failed += 1
                log.error("team map: building the cloud failed (%s: %s)", type(exc).__name__, exc)
            finally:
                self.cadence.published(stamp_s, started, time.monotonic())
                with self._cv:
                    self._working = False
                    self._cv.notify_all()
