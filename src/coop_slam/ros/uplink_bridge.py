"""A client's uplink on ROS: :class:`coop_slam.uplink.engine.ClientUplink`'s messages published
on ``/robot_k/keyframes``, the server's acknowledgements (``keyframe_ack``) and requests
(``keyframe_request``, low-bandwidth mode) handed to it, and a thread that sends again what the
server has not acknowledged and sends what is held when the camera stops.

Keyframe messages are numbered (client session and sequence): the client keeps those the server
has not acknowledged (at most ``~max_unacked``) and sends each again ``~resend_after_s`` after it
was sent, then after twice as long, up to ``~max_resend_after_s`` (at most ``~resend_window`` at
once), so a server that restarts or a radio that drops messages loses nothing and a lagging
server is not flooded; not those the server says it has received, while that server run stores
them. A restarted client continues above the keyframe ids and map segments the server has stored
for its robot, in a new map segment.
"""

from __future__ import annotations

import tempfile
import threading
import time
from typing import Callable

import rospy
from std_msgs.msg import Bool

from ..bow import Vocabulary
from ..uplink.config import UplinkConfig
from ..uplink.engine import ClientUplink
from ..wire.delivery import DeliveryConfig
from ..wire.messages import KeyframeAck, KeyframeRequest
from .validation import RejectCounter
from .wire_bridge import from_ros, to_ros


def server_vocabulary(name: str, wait_s: float) -> Vocabulary:
    """The vocabulary the server publishes (its words are what place signatures name), else
    the default one this machine has."""
    from coop_slam.msg import Vocabulary as VocabularyMsg

    from ..default_vocabulary import default_vocabulary_path

    try:
        msg = rospy.wait_for_message("/server/vocabulary", VocabularyMsg, timeout=wait_s)
        suffix = ".npz" if msg.format == "coop_slam-npz" else ".txt"
        with tempfile.NamedTemporaryFile(suffix=suffix) as fh:
            fh.write(msg.data)
            fh.flush()
            vocabulary = Vocabulary.load(fh.name)
        rospy.loginfo("client %s: place signatures in the server's vocabulary", name)
        return vocabulary
    except rospy.ROSException:
        path = default_vocabulary_path()
        rospy.logwarn(
            "client %s: no /server/vocabulary within %.0f s: place signatures in %s (the server "
            "must use the same vocabulary)",
            name,
            wait_s,
            path,
        )
        return Vocabulary.load(path)


class UplinkBridge:
    """``odometry(fn)`` runs ``fn(vo)`` with the tracker's lock held and returns its result (None
    without an odometry); ``hold_for_player``: lock-step playback, where a pause in the frames
    says nothing and what is held goes when the player is done."""

    def __init__(
        self,
        name: str,
        uplink: UplinkConfig,
        delivery: DeliveryConfig,
        server_wait_s: float,
        rejects: RejectCounter,
        odometry: Callable,
        hold_for_player: bool,
        uplink_args: dict,
    ):
        from coop_slam.msg import KeyframeAck as KeyframeAckRos
        from coop_slam.msg import KeyframeMessage
        from coop_slam.msg import KeyframeRequest as KeyframeRequestRos

        self.name, self.rejects, self.odometry = name, rejects, odometry
        self.hold_for_player = hold_for_player
        self.engine = ClientUplink(config=uplink, delivery=delivery, **uplink_args)
        ns = f"/robot_{self.engine.robot_id}"
        self.pub = rospy.Publisher(f"{ns}/keyframes", KeyframeMessage, queue_size=200)
        self.server_wait_s = server_wait_s
        if self.engine.pull:
            self.engine.vocabulary = server_vocabulary(name, server_wait_s)
            self.sub_request = rospy.Subscriber(
                f"{ns}/keyframe_request", KeyframeRequestRos, self._on_request, queue_size=10
            )
        self._continue_after_server(ns, KeyframeAckRos)
        self.sub_ack = rospy.Subscriber(f"{ns}/keyframe_ack", KeyframeAckRos, self._on_ack)
        # Played data (scripts/demo, player.launch): the player says when it has played all.
        self.sub_done = rospy.Subscriber("/player/done", Bool, self._on_player_done, queue_size=1)
        self.last_frame_wall = time.monotonic()  # when the newest frame came (idle flush)
        self.flush_now: Callable[[], None] | None = None  # set by the node: flush under its lock
        threading.Thread(target=self._resend_loop, daemon=True).start()

    def _continue_after_server(self, ns: str, ack_type) -> None:
        """A restarted client must not reuse the keyframe ids the server stored before: the
        server's latched acknowledgement says how far they went."""
        try:
            ack = rospy.wait_for_message(f"{ns}/keyframe_ack", ack_type, timeout=self.server_wait_s)
        except rospy.ROSException:
            rospy.loginfo(
                "client %s: no server acknowledgement within %.0f s: starting at keyframe 1",
                self.name,
                self.server_wait_s,
            )
            return
        if ack.last_keyframe_id > 0:
            self.engine.continue_after(ack.last_keyframe_id, ack.last_map_segment)
            rospy.logwarn(
                "client %s: the server holds %d keyframes of this robot from before: continuing "
                "from keyframe %d in new map segment %d",
                self.name,
                ack.last_keyframe_id,
                self.engine.kf_id_base + 1,
                self.engine.segment_base,
            )

    def send(self, messages) -> None:
        for msg in messages:
            self.pub.publish(to_ros(msg))

    def _on_ack(self, msg) -> None:
        if msg.robot_id != self.engine.robot_id:
            self.rejects.reject("keyframe_ack", f"acknowledgement for robot {msg.robot_id}")
            return
        self.engine.acknowledged(from_ros(msg, KeyframeAck))

    def _on_request(self, msg) -> None:
        """The server asks for whole keyframes (low-bandwidth mode)."""
        if msg.robot_id != self.engine.robot_id:
            self.rejects.reject("keyframe_request", f"request for robot {msg.robot_id}")
            return
        request = from_ros(msg, KeyframeRequest)
        # The uplink's state (what the server holds) is the tracking thread's too.
        sent = self.odometry(lambda vo: self.engine.answer(request, vo.keyframe))
        self.send(sent or [])

    def _on_player_done(self, msg) -> None:
        if msg.data and self.flush_now is not None:
            self.flush_now()

    def _resend_loop(self) -> None:
        while not rospy.is_shutdown():
            time.sleep(0.5)
            # No frame for a while: the camera stopped, what is held goes now (not in lock-step
            # playback: it goes when the player is done, so the messages stay the same however
            # loaded the machine is).
            idle = time.monotonic() - self.last_frame_wall > self.engine.planner.idle_flush_s
            playing = self.hold_for_player and self.sub_done.get_num_connections()
            if self.engine.held and idle and not playing and self.flush_now is not None:
                self.flush_now(blocking=False)
            due = self.engine.due_again()
            if due and self.pub.get_num_connections() > 0:
                rospy.loginfo_throttle(
                    10.0,
                    "client %s: sending %d unacknowledged keyframe messages again",
                    self.name,
                    len(due),
                )
                self.send(due)
