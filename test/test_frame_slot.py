"""The drop-newest hand-over: a slow tracker gets the latest frame, never a backlog."""

import threading

from coop_slam.frame_slot import LatestFrame


def test_a_busy_tracker_gets_the_newest_frame_and_drops_are_counted():
    slot = LatestFrame()
    got, busy, taken = [], threading.Event(), threading.Event()

    def tracker():
        while (frame := slot.take(timeout_s=5.0)) is not None:
            got.append(frame)
            taken.set()
            busy.wait(5.0)  # tracking this frame takes until the camera sent more
            busy.clear()

    worker = threading.Thread(target=tracker)
    worker.start()
    slot.put(0)
    assert taken.wait(5.0)
    for k in range(1, 10):  # the camera goes on while the tracker is busy
        slot.put(k)
    taken.clear()
    busy.set()
    assert taken.wait(5.0)
    slot.close()
    busy.set()
    worker.join(5.0)
    assert got == [0, 9]  # the newest, never the backlog
    assert slot.dropped == 8


def test_put_returns_what_it_replaced():
    slot = LatestFrame()
    assert slot.put("a") is None
    assert slot.put("b") == "a" and slot.dropped == 1
    assert slot.take(0.1) == "b" and slot.take(0.01) is None
