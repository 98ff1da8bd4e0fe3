"""A lossy radio between a client and the server, for fault injection (``scripts/demo --faults
drop:P``): relays one robot's keyframe messages from ``~input`` to ``~output``, dropping each with
probability ``~drop`` (seeded by ``~seed``, so a run is repeatable). The client's delivery
(acknowledgements and sending again, see :mod:`coop_slam.wire.delivery`) must make up for it.
"""

from __future__ import annotations

import numpy as np
import rospy

from ..errors import CoopSlamError


class RadioRelay:
    def __init__(self):
        from coop_slam.msg import KeyframeMessage

        self.drop = float(rospy.get_param("~drop", 0.0))
        if not 0.0 <= self.drop < 1.0:
            raise CoopSlamError(f"~drop must be in [0, 1), got {self.drop}")
        self.rng = np.random.default_rng(int(rospy.get_param("~seed", 0)))
        self.relayed = self.dropped = 0
        self.pub = rospy.Publisher(rospy.get_param("~output"), KeyframeMessage, queue_size=200)
        self.sub = rospy.Subscriber(
            rospy.get_param("~input"),
            KeyframeMessage,
            self._on_msg,
            queue_size=200,
            buff_size=2**24,
        )

    def _on_msg(self, msg) -> None:
        if self.rng.random() < self.drop:
            self.dropped += 1
            return
        self.relayed += 1
        self.pub.publish(msg)

    def shutdown(self) -> None:
        rospy.loginfo(
            "radio %s: %d keyframe messages relayed, %d dropped",
            rospy.get_name(),
            self.relayed,
            self.dropped,
        )


def main() -> None:
    rospy.init_node("radio")
    try:
        node = RadioRelay()
    except (CoopSlamError, KeyError) as exc:
        rospy.logfatal("radio: %s", exc)
        raise SystemExit(1) from exc
    rospy.on_shutdown(node.shutdown)
    rospy.spin()
