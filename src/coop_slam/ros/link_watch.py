"""Keeping a ROS 1 topic link alive, from both of its ends.

A rospy publisher whose message fails to serialize part-way leaves the bytes written so far in its
buffer, and the next message goes out after them: every subscriber then reads a misaligned stream,
drops the connection, fails the reconnect handshake (its read buffer still holds the rest) and
never connects again, since the publisher stays registered and the master has nothing to tell it.

- :func:`publish_guarded`, the publisher's side: a failed publish is said, never raised (no
  thread dies of it), and the residue is cleared so the stream stays aligned.
- :class:`LinkWatch`, the subscriber's side: a wall-clock thread (the sim clock pauses in
  lock-step playback) compares, every ``period_s``, the publishers the master lists for each
  watched topic with the subscriber's connections; short on two checks in a row, it unregisters
  and subscribes again (a new subscriber has a fresh buffer and connects to every publisher
  listed), backing off to ``max_backoff_s`` while that does not help (a publisher killed with
  kill -9 stays listed until its node starts again).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

import rosgraph
import rospy


def publish_guarded(pub: rospy.Publisher, msg) -> str:
    """Publish ``msg``; returns "" or why it failed (the publisher's buffer is cleared then)."""
    try:
        pub.publish(msg)
        return ""
    except Exception as exc:  # whatever genpy raised: said by the caller, the thread lives on
        impl = getattr(pub, "impl", None)
        buff = getattr(impl, "buff", None)
        if buff is not None:
            impl.acquire()
            try:
                buff.seek(0)
                buff.truncate(0)
            finally:
                impl.release()
        return f"{type(exc).__name__}: {exc}"


@dataclass
class _Watched:
    make: Callable[[], rospy.Subscriber]
    what: str  # for the log line, e.g. "robot 2's keyframe"
    sub: rospy.Subscriber
    short: int = 0  # checks in a row with fewer connections than publishers
    backoff_s: float = 0.0
    next_try: float = 0.0


class LinkWatch:
    """Subscribers that subscribe again when their link dropped. ``who`` starts the log line
    (``server``, ``client robot_2``); ``say`` logs it (rospy.logwarn: console and /rosout)."""

    def __init__(
        self,
        who: str,
        period_s: float = 2.0,
        max_backoff_s: float = 60.0,
        say: Callable[..., None] = rospy.logwarn,
    ):
        self.who, self.period_s, self.max_backoff_s, self.say = who, period_s, max_backoff_s, say
        self._watched: dict[str, _Watched] = {}
        self._lock = threading.Lock()
        self.resubscribed = 0
        threading.Thread(target=self._loop, daemon=True).start()

    def watch(self, topic: str, make: Callable[[], rospy.Subscriber], what: str) -> None:
        """Subscribe (``make()``) and keep the link alive; ``topic`` as resolved."""
        with self._lock:
            self._watched[topic] = _Watched(make, what, make(), backoff_s=self.period_s)

    def subscriber(self, topic: str) -> rospy.Subscriber:
        return self._watched[topic].sub

    def _loop(self) -> None:
        while not rospy.is_shutdown():
            time.sleep(self.period_s)
            try:
                self.check(time.monotonic())
            except Exception as exc:  # the master away for a moment: try again next time
                rospy.logdebug("%s: link watch: %s", self.who, exc)

    def check(self, now: float) -> None:
        """One comparison of the master's publishers with each subscriber's connections."""
        me = rospy.get_name()
        publishers, _, _ = rosgraph.Master(me).getSystemState()
        listed = {topic: [n for n in nodes if n != me] for topic, nodes in publishers}
        with self._lock:
            for topic, w in self._watched.items():
                if len(listed.get(topic, [])) <= w.sub.get_num_connections():
                    w.short, w.backoff_s = 0, self.period_s
                    continue
                w.short += 1
                if w.short < 2 or now < w.next_try:
                    continue
                self.say(
                    "%s: %s link on %s dropped (a message it could not read?): subscribing again",
                    self.who,
                    w.what,
                    topic,
                )
                w.sub.unregister()
                w.sub = w.make()
                self.resubscribed += 1
                w.short, w.next_try = 0, now + w.backoff_s
                w.backoff_s = min(2.0 * w.backoff_s, self.max_backoff_s)
