"""Loading a sequence's items ahead of their use, within a memory budget.

A player at the camera's own rate that decodes each frame when it is due spends that time on the
cores the robots' clients need at that very moment (and publishes late by it). Here one thread
loads items in order ahead of the consumer, up to ``max_bytes`` of loaded items not yet taken,
so a sequence that fits is decoded before playing starts and a longer one stays that far ahead.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Sequence


class PrefetchError(RuntimeError):
    """Items were asked for out of order, or after the prefetcher was closed."""


class Prefetcher:
    """``get(i)`` returns ``load(items[i])``, loaded ahead by a background thread.

    Items must be taken in order (each index once). ``size(value)`` gives a loaded value's bytes;
    the thread stops loading while the values not yet taken hold ``max_bytes`` or more (at least
    one item is always loaded ahead). An exception from ``load`` is raised by ``get`` of that
    item, and loading goes on with the next.
    """

    def __init__(
        self,
        items: Sequence,
        load: Callable[[Any], Any],
        size: Callable[[Any], int],
        max_bytes: int,
    ):
        if max_bytes < 0:
            raise PrefetchError(f"prefetch budget must be >= 0 bytes, got {max_bytes}")
        self._items = items
        self._load = load
        self._size = size
        self._max_bytes = max_bytes
        self._cond = threading.Condition()
        self._ready: dict[int, tuple[bool, Any, int]] = {}  # index -> (ok, value or error, bytes)
        self._held_bytes = 0
        self._next_load = 0
        self._next_get = 0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="prefetch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            with self._cond:
                while (
                    not self._closed
                    and self._next_load < len(self._items)
                    and self._ready
                    and self._held_bytes >= self._max_bytes
                ):
                    self._cond.wait()
                if self._closed or self._next_load >= len(self._items):
                    return
                index = self._next_load
            try:
                value = self._load(self._items[index])
                entry = (True, value, int(self._size(value)))
            except Exception as exc:  # handed to the consumer of this item
                entry = (False, exc, 0)
            with self._cond:
                if self._closed:
                    return
                self._ready[index] = entry
                self._held_bytes += entry[2]
                self._next_load = index + 1
                self._cond.notify_all()

    def filled(self) -> tuple[int, int]:
        """(items loaded so far, items in all)."""
        with self._cond:
            return self._next_load, len(self._items)

    def wait_filled(self, progress: Callable[[int, int], None] | None = None, period_s=1.0):
        """Block until the budget is full or everything is loaded; ``progress(loaded, total)``
        every ``period_s`` meanwhile."""
        next_report = time.monotonic() + period_s
        with self._cond:
            while (
                not self._closed
                and self._next_load < len(self._items)
                and self._held_bytes < self._max_bytes
            ):
                self._cond.wait(max(0.0, next_report - time.monotonic()))
                if progress is not None and time.monotonic() >= next_report:
                    next_report += period_s
                    progress(self._next_load, len(self._items))

    def get(self, index: int) -> Any:
        """The loaded item ``index`` (the next in order), waiting for the loader if need be;
        raises what loading it raised, or PrefetchError once closed."""
        with self._cond:
            if index != self._next_get:
                raise PrefetchError(
                    f"items are taken in order: asked for {index}, next is {self._next_get}"
                )
            while index not in self._ready:
                if self._closed:
                    raise PrefetchError("prefetcher is closed")
                self._cond.wait()
            ok, value, nbytes = self._ready.pop(index)
            self._held_bytes -= nbytes
            self._next_get += 1
            self._cond.notify_all()
        if not ok:
            raise value
        return value

    def close(self) -> None:
        """Stop loading and drop what is loaded; a waiting get() raises PrefetchError."""
        with self._cond:
            self._closed = True
            self._ready.clear()
            self._held_bytes = 0
            self._cond.notify_all()
        self._thread.join(timeout=5.0)
