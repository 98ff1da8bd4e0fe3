"""The player's look-ahead loader: order, memory budget, errors, closing."""

import threading
import time

import pytest

from coop_slam.prefetch import Prefetcher, PrefetchError


def _wait_until(cond, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def test_items_come_in_order_and_loading_stops_at_the_budget():
    loaded = []

    def load(x):
        loaded.append(x)
        return x * 10

    pf = Prefetcher(list(range(10)), load, size=lambda v: 100, max_bytes=300)
    pf.wait_filled()
    time.sleep(0.05)  # it must stay stopped, not only have been slow
    assert pf.filled() == (3, 10) and loaded == [0, 1, 2]
    assert pf.get(0) == 0
    _wait_until(lambda: pf.filled()[0] == 4)  # one taken: one more loaded
    assert [pf.get(i) for i in range(1, 10)] == [10 * i for i in range(1, 10)]
    pf.close()


def test_a_sequence_within_the_budget_is_loaded_before_playing():
    pf = Prefetcher(list(range(5)), lambda x: x, size=lambda v: 1, max_bytes=1000)
    pf.wait_filled()
    assert pf.filled() == (5, 5)
    pf.close()


def test_a_zero_budget_still_loads_one_ahead():
    pf = Prefetcher(list(range(3)), lambda x: x, size=lambda v: 8, max_bytes=0)
    pf.wait_filled()
    _wait_until(lambda: pf.filled()[0] == 1)
    time.sleep(0.05)
    assert pf.filled()[0] == 1
    assert [pf.get(i) for i in range(3)] == [0, 1, 2]
    pf.close()


def test_a_failing_item_raises_for_that_item_only():
    def load(x):
        if x == 1:
            raise ValueError("frame 1 is unreadable")
        return x

    pf = Prefetcher([0, 1, 2], load, size=lambda v: 1, max_bytes=10)
    assert pf.get(0) == 0
    with pytest.raises(ValueError, match="frame 1"):
        pf.get(1)
    assert pf.get(2) == 2
    pf.close()


def test_out_of_order_and_after_close_are_errors():
    pf = Prefetcher([0, 1], lambda x: x, size=lambda v: 1, max_bytes=10)
    with pytest.raises(PrefetchError, match="in order"):
        pf.get(1)
    pf.close()
    with pytest.raises(PrefetchError, match="closed"):
        pf.get(0)
    with pytest.raises(PrefetchError, match=">= 0"):
        Prefetcher([], lambda x: x, size=len, max_bytes=-1)


def test_close_wakes_a_consumer_waiting_for_a_slow_item():
    release = threading.Event()

    def load(x):
        release.wait(5.0)
        return x

    pf = Prefetcher([0], load, size=lambda v: 1, max_bytes=10)
    errors = []

    def consume():
        try:
            pf.get(0)
        except PrefetchError as exc:
            errors.append(exc)

    t = threading.Thread(target=consume)
    t.start()
    time.sleep(0.05)
    closer = threading.Thread(target=pf.close)  # close() waits for the loader
    closer.start()
    t.join(2.0)
    woke = not t.is_alive() and bool(errors)
    release.set()
    closer.join(5.0)
    assert woke


def test_filling_reports_progress_while_items_keep_arriving():
    """The loader wakes the waiter at every item; progress still comes once per period."""
    calls = []

    def load(x):
        time.sleep(0.02)
        return x

    pf = Prefetcher(list(range(20)), load, size=lambda v: 1, max_bytes=100)
    pf.wait_filled(lambda done, total: calls.append((done, total)), period_s=0.05)
    assert pf.filled() == (20, 20)
    assert len(calls) >= 2 and all(total == 20 for _, total in calls)
    pf.close()
