"""Progress lines for long user commands, at most one every few seconds."""

from __future__ import annotations

import time
from collections.abc import Callable


def throttled(
    report: Callable[[int, int], None], period_s: float = 2.0
) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that passes a call on to ``report`` at most once per
    ``period_s`` (and always the last one, ``done == total``), so a log is not flooded."""
    last = [float("-inf")]

    def progress(done: int, total: int) -> None:
        now = time.monotonic()
        if done == total or now - last[0] > period_s:
            last[0] = now
            report(done, total)

    return progress
