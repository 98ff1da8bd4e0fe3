"""A client's uplink on ROS: :class:`coop_slam.uplink.engine.ClientUplink`'s messages published
on ``/robot_k/keyframes``, the server's acknowledgements (``keyframe_ack``) and requests
(``keyframe_request``, low-bandwidth mode) handed to it, and a thread that sends again what the
server has not acknowledged and sends what is held when the camera stops.

Keyframe messages are numbered (client session and sequence): the client keeps those the server
has not acknowledged (at most ``~max_unacked``; beyond, new ones are refused) and sends each again
``~resend_after_s`` after it was sent, then after twice as long, up to ``~max_resend_after_s`` (at
most ``~resend_window`` at once), so a server that restarts or a radio that drops messages loses
nothing and a lagging server is not flooded; not those the server says it has received, while
that server run stores them. They are kept on the robot's disk too (``~spool``,
:mod:`coop_slam.uplink.spool`): a restarted client sends them first, once it has heard from the
server, and continues above the keyframe ids and map segments the server and the spool hold for
its robot, in a new map segment.

A message is serialized (:class:`.wire_bridge.RosSerializer`) before it is numbered, so nothing
that cannot be published is; a publish that fails all the same is said, not raised, and leaves no
residue in the stream (:func:`.link_watch.publish_guarded`). The acknowledgement's link is
watched and subscribed again when it drops (:class:`.link_watch.LinkWatch`).
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
from typing import Callable

import rospy
from std_msgs.msg import Bool, String

from ..bow import Vocabulary
from ..uplink.config import UplinkConfig
from ..uplink.engine import ClientUplink
from ..uplink.spool import Spool, SpoolConfig
from ..wire.delivery import DeliveryConfig
from ..wire.messages import KeyframeAck, KeyframeRequest
from .link_watch import LinkWatch, publish_guarded
from .validation import RejectCounter
from .wire_bridge import RosSerializer, from_ros, to_ros

# The server's vocabulary digest (std_msgs/String, latched): a robot whose own vocabulary file has
# it loads that file instead of downloading /server/vocabulary (3 MB) across the radio.
VOCABULARY_SHA256_TOPIC = "/server/vocabulary_sha256"


def _file_sha256(path: str) -> str:
    import hashlib

    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def server_vocabulary(name: str, wait_s: float) -> Vocabulary:
    """The vocabulary the server uses (its words are what place signatures name): this
    machine's default one when it is the same file, else the one the server publishes, else the
    default one (saying so)."""
    from coop_slam.msg import Vocabulary as VocabularyMsg

    from ..default_vocabulary import default_vocabulary_path

    path = default_vocabulary_path()
    try:
        sha256 = rospy.wait_for_message(VOCABULARY_SHA256_TOPIC, String, timeout=wait_s).data
    except rospy.ROSException:
        sha256 = ""  # a server without the digest: the vocabulary itself tells
    if sha256 and os.path.isfile(path) and _file_sha256(path) == sha256:
        rospy.loginfo("client %s: place signatures in the server's vocabulary (%s)", name, path)
        return Vocabulary.load(path)
    try:
        msg = rospy.wait_for_message("/server/vocabulary", VocabularyMsg, timeout=wait_s)
        suffix = ".npz" if msg.format == "coop_slam-npz" else ".txt"
        with tempfile.NamedTemporaryFile(suffix=suffix) as fh:
            fh.write(msg.data)
            fh.flush()
            vocabulary = Vocabulary.load(fh.name)
        rospy.loginfo("client %s: place signatures in the server's vocabulary (downloaded)", name)
        return vocabulary
    except rospy.ROSException:
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
        spool: SpoolConfig | None = None,
        clock_offset_s: float = 0.0,
    ):
        from coop_slam.msg import KeyframeAck as KeyframeAckRos
        from coop_slam.msg import KeyframeMessage
        from coop_slam.msg import KeyframeRequest as KeyframeRequestRos

        self.name, self.rejects, self.odometry = name, rejects, odometry
        self.hold_for_player = hold_for_player
        self.player_done = False  # lock-step playback: the player said it played every frame
        serializer = RosSerializer()
        self.clock_offset_s = clock_offset_s  # rehearsed: this robot's clock runs ahead
        self.engine = ClientUplink(
            config=uplink,
            delivery=delivery,
            serializer=serializer,
            spool=self._open_spool(spool or SpoolConfig(), uplink_args["robot_id"], serializer),
            **uplink_args,
        )
        ns = f"/robot_{self.engine.robot_id}"
        self.pub = rospy.Publisher(f"{ns}/keyframes", KeyframeMessage, queue_size=200)
        self._publish_lock = threading.Lock()  # the tracking and resend threads both publish
        self.server_wait_s = server_wait_s
        if self.engine.signatures:
            self.engine.vocabulary = server_vocabulary(name, server_wait_s)
            self.sub_request = rospy.Subscriber(
                f"{ns}/keyframe_request", KeyframeRequestRos, self._on_request, queue_size=10
            )
        self._continue_after_server(ns, KeyframeAckRos)
        self.watch = LinkWatch(f"client {name}")
        self.watch.watch(
            f"{ns}/keyframe_ack",
            lambda: rospy.Subscriber(f"{ns}/keyframe_ack", KeyframeAckRos, self._on_ack),
            "the server's acknowledgement",
        )
        # Played data (scripts/demo, player.launch): the player says when it has played all.
        self.sub_done = rospy.Subscriber("/player/done", Bool, self._on_player_done, queue_size=1)
        self.last_frame_wall = time.monotonic()  # when the newest frame came (idle flush)
        self.flush_now: Callable[[], None] | None = None  # set by the node: flush under its lock
        threading.Thread(target=self._resend_loop, daemon=True).start()

    def _open_spool(self, cfg: SpoolConfig, robot_id: int, serializer) -> Spool | None:
        if cfg.off:
            rospy.logwarn(
                "client %s: ~spool off: keyframe messages not acknowledged are lost if the client "
                "is killed",
                self.name,
            )
            return None
        spool = Spool(cfg.file(robot_id), robot_id, serializer.format_id, int(cfg.max_mb * 1e6))
        for aside, why in spool.set_aside_as:
            rospy.logwarn(
                "client %s: spool %s set aside as %s: %s", self.name, spool.path, aside, why
            )
        kept = spool.count
        rospy.loginfo(
            "client %s: keyframe messages kept in %s until acknowledged%s",
            self.name,
            spool.path,
            f" ({kept} from before the restart)" if kept else "",
        )
        return spool

    def _continue_after_server(self, ns: str, ack_type) -> None:
        """A restarted client must not reuse the keyframe ids the server stored or the spool
        kept, and sends what the spool kept first: the server's latched acknowledgement says
        what it holds (see ClientUplink.server_found)."""
        try:
            ack = rospy.wait_for_message(f"{ns}/keyframe_ack", ack_type, timeout=self.server_wait_s)
        except rospy.ROSException:
            ack = None
        if ack is None:
            kept = self.engine.unacked
            rospy.loginfo(
                "client %s: no server acknowledgement within %.0f s: starting at keyframe %d%s",
                self.name,
                self.server_wait_s,
                self.engine.kf_id_base + 1,
                f"; the {kept} messages kept from before go once it answers" if kept else "",
            )
            return
        self.send(self.engine.server_found(from_ros(ack, KeyframeAck), self._server_map_id()))
        if self.engine.kf_id_base > 0:
            rospy.logwarn(
                "client %s: the server holds keyframes of this robot from before: continuing "
                "from keyframe %d in new map segment %d",
                self.name,
                self.engine.kf_id_base + 1,
                self.engine.segment_base,
            )

    @staticmethod
    def _server_map_id() -> str:
        """The team map the server holds (``/team_map/map_id``; "" when it does not say)."""
        try:
            return str(rospy.get_param("/team_map/map_id", ""))
        except (OSError, rospy.ROSException):
            return ""

    def send(self, messages) -> None:
        """Publish; a message that fails is said and sent again later (never raised: the
        tracking and resend threads must live on)."""
        for msg in messages:
            try:
                ros = to_ros(msg)
                # When it went, on this robot's clock: its server measures the clock with it.
                ros.sent = rospy.Time.from_sec(rospy.get_time() + self.clock_offset_s)
            except Exception as exc:
                why = f"{type(exc).__name__}: {exc}"
            else:
                with self._publish_lock:
                    why = publish_guarded(self.pub, ros)
            if why:
                rospy.logerr(
                    "client %s: keyframe %d (message %d) not published: %s",
                    self.name,
                    msg.keyframe_id,
                    msg.sequence,
                    why,
                )

    def _on_ack(self, msg) -> None:
        if msg.robot_id != self.engine.robot_id:
            self.rejects.reject("keyframe_ack", f"acknowledgement for robot {msg.robot_id}")
            return
        ack = from_ros(msg, KeyframeAck)
        if self.engine.started:
            self.engine.acknowledged(ack)
        else:  # the first acknowledgement after a start without one
            self.send(self.engine.server_found(ack, self._server_map_id()))

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
        self.player_done = bool(msg.data)
        if msg.data and self.flush_now is not None:
            self.flush_now()

    def _resend_loop(self) -> None:
        while not rospy.is_shutdown():
            time.sleep(0.5)
            try:
                self._resend()
            except Exception as exc:  # this thread is what sends again: it must not end
                rospy.logerr_throttle(10.0, "client %s: sending again: %s", self.name, exc)

    def _resend(self) -> None:
        # No frame for a while: the camera stopped, what is held goes now (not in lock-step
        # playback: it goes when the player is done, so the messages stay the same however
        # loaded the machine is), and the counters follow the acknowledgements.
        idle = time.monotonic() - self.last_frame_wall > self.engine.planner.idle_flush_s
        playing = (
            self.hold_for_player and not self.player_done and self.sub_done.get_num_connections()
        )
        if idle and not playing and self.flush_now is not None:
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

    def close(self) -> None:
        """Say what is kept and what was refused, and close the spool (after the last send)."""
        e = self.engine
        where = e.spool.path if e.spool is not None else "memory (lost now: ~spool off)"
        rospy.loginfo(
            "client %s: %d keyframe messages not acknowledged, kept in %s; %d sent from the spool "
            "of the run before; %d refused (max_unacked / spool_max_mb reached)",
            self.name,
            e.unacked,
            where,
            e.resent_from_spool,
            e.refused_full,
        )
        e.close()
