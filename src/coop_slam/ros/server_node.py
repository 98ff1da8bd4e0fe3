"""Server node: receives every robot's keyframes, stitches the maps, publishes merges and TF.

Subscribes ``/robot_k/keyframes`` for each configured robot; publishes ``/merge_events``
(``coop_slam/MergeEvent``), TF ``world -> robot_k/map`` for every robot in the master's group,
``/robot_k/correction`` (``coop_slam/MapCorrection``), the team map (``/team_map/cloud``,
``/team_map/markers``, ``/team_map/robot_k/path``: optimized keyframe poses, in ``world`` once
merged, else in the robot's group root map) and ``/server/stats``. Keyframes are processed
in one worker thread in arrival order, so callbacks never block and the graph has one writer.

The team map is durable (:mod:`coop_slam.team.durable`): every input the server takes is
committed to the map file (``~map``; default a new file per run under ``$ROS_HOME/coop_slam``,
``off`` for none) before ``/robot_k/keyframe_ack`` acknowledges it; ``~resume`` rebuilds the team
map from that file after a crash or restart, ``~load_map`` starts from a map saved in an earlier
session. Services ``~save_map`` and ``~load_map``.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import json
import os
import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String

from ..bow import Vocabulary
from ..config import load_yaml_config
from ..delivery import new_session
from ..errors import CoopSlamError
from ..geometry import invert, se3_from_quat
from ..keyframe_record import KeyframeRecord
from ..team.config import ServerConfig
from ..team.durable import PendingKeyframe
from ..team.results import TYPE_LINK, TYPE_LOOP, TYPE_OVERLAP
from ..team.server import TeamServer
from ..team.view import marker_scale
from .convert import (
    MessageError,
    cloud_to_msg,
    keyframe_from_msg,
    needs_stored,
    pose_from_msg,
    pose_to_msg,
    transform_stamped,
    transform_to_msg,
    unpacked,
)
from .log_bridge import forward_core_logs
from .validation import RejectCounter

# Work for the worker thread, which alone changes the team map. A request that waits for its
# answer (a service call) carries a Future the worker completes.


@dataclass
class _KeyframeJob:
    record: KeyframeRecord | PendingKeyframe  # pending: a delta update, completed when taken
    stamp_s: float
    session: int = 0  # delivery (see coop_slam.delivery); 0 = unsequenced
    sequence: int = 0


@dataclass
class _RendezvousJob:
    robot_a: int
    robot_b: int
    stamp_s: float | None  # None: now (the robots' latest keyframes)
    T_camA_bodyB: np.ndarray | None = None  # marker sighting: robot b's body in a's camera
    sighting: bool = False  # a marker sighting (rate-limited) rather than an operator request
    reply: Future | None = None  # (merge or None, message)


@dataclass
class _GlobalBaJob:
    robot_id: int | None
    reply: Future  # (GlobalBaResult or None, message)


@dataclass
class _RelocalizeJob:
    robot_id: int
    map_segment: int
    bow: object  # BowVector of the lost robot's view
    reply: Future  # (LocalMap or None, message)


@dataclass
class _MapFileJob:
    path: str
    load: bool  # load (else save)
    reply: Future  # (success, message, path)


def default_map_path() -> str:
    """A new map file per run in ``$ROS_HOME/coop_slam`` (``~/.ros`` by default)."""
    import time

    home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    folder = os.path.join(home, "coop_slam")
    os.makedirs(folder, exist_ok=True)
    return os.path.join(folder, time.strftime("team_map_%Y%m%d-%H%M%S.db"))


class ServerNode:
    def __init__(self):
        import tf2_ros

        from coop_slam.msg import KeyFrame, MapCorrection, MergeEvent

        node_params = (
            "config",
            "vocabulary",
            "T_base_cam",
            "cloud_period_s",
            "cloud_max_busy_share",
            "map",
            "resume",
            "load_map",
        )
        overrides = {k: v for k, v in rospy.get_param("~", {}).items() if k not in node_params}
        self.cfg = load_yaml_config(
            ServerConfig, rospy.get_param("~config", ""), "server", overrides
        )
        vocab_path = rospy.get_param("~vocabulary", "")
        if not vocab_path:
            from ..bow.training import default_vocabulary_path

            vocab_path = default_vocabulary_path()
        if not os.path.isfile(vocab_path):
            raise CoopSlamError(
                f"vocabulary file not found: {vocab_path} (run scripts/setup, which "
                "builds the default vocabulary, or set ~vocabulary)"
            )
        rospy.loginfo("server: loading vocabulary %s", vocab_path)
        self.vocab_path = vocab_path
        with open(vocab_path, "rb") as fh:
            vocab_data = fh.read()
        self.vocabulary = Vocabulary.load(vocab_path)
        self.vocab_sha256 = hashlib.sha256(vocab_data).hexdigest()
        map_path = str(rospy.get_param("~map", "")).strip()
        self.map_path = None if map_path == "off" else (map_path or default_map_path())
        self.durable = self._open_map(
            bool(rospy.get_param("~resume", False)), str(rospy.get_param("~load_map", "")).strip()
        )
        self.server = self.durable.server
        self.rejects = RejectCounter("server")
        self.duplicates = 0  # keyframe messages received again (a client re-sending)
        self._constraints_published = 0  # server.constraints already sent as merge events
        self.queue: queue.Queue = queue.Queue()
        self.tf = tf2_ros.StaticTransformBroadcaster()
        self.pub_merge = rospy.Publisher("/merge_events", MergeEvent, queue_size=20, latch=True)
        self.pub_stats = rospy.Publisher("/server/stats", String, queue_size=5, latch=True)
        from coop_slam.msg import Vocabulary as VocabularyMsg

        self.pub_vocab = rospy.Publisher(
            "/server/vocabulary", VocabularyMsg, queue_size=1, latch=True
        )
        self.pub_vocab.publish(
            VocabularyMsg(
                format="coop_slam-npz" if vocab_data[:2] == b"PK" else "dbow2-text",
                sha256=self.vocab_sha256,
                k=self.server.vocabulary.k,
                levels=self.server.vocabulary.levels,
                data=vocab_data,
            )
        )
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        from ..team.map_builder import TeamMapBuilder
        from ..team.publish_cadence import PublishCadence, PublishCadenceConfig

        self.cadence = PublishCadence(
            PublishCadenceConfig(
                period_s=float(rospy.get_param("~cloud_period_s", 2.0)),
                max_busy_share=float(rospy.get_param("~cloud_max_busy_share", 0.2)),
            )
        )
        # The stitched cloud is built beside the worker (see team/map_builder.py).
        self.map_builder = TeamMapBuilder(self._publish_cloud, self.cadence)
        self._merge_unshown = False  # a merge the team map has not shown yet
        self.pub_cloud = rospy.Publisher("/team_map/cloud", PointCloud2, queue_size=1, latch=True)
        self.pub_markers = rospy.Publisher(
            "/team_map/markers", MarkerArray, queue_size=1, latch=True
        )
        from nav_msgs.msg import Path

        self._Path, self._KeyFrame = Path, KeyFrame
        self._MergeEvent, self._MapCorrection = MergeEvent, MapCorrection
        from coop_slam.msg import KeyframeRequest

        self._KeyframeRequest, self.pub_request, self._request_count = KeyframeRequest, {}, 0
        self.pub_path, self.pub_corr, self.pub_ack, self.subs = {}, {}, {}, []
        # Acknowledgements: what the worker stored, the newest per robot (a receipt repeats it),
        # and this run's id (a restarted server lost what it had received and not stored).
        self._acks: dict = {}
        self._ack_lock = threading.Lock()
        self.server_session = new_session()
        self._robot_topics()
        from coop_slam.msg import RobotSighting
        from coop_slam.srv import Rendezvous

        base_cam = rospy.get_param("~T_base_cam", [])  # the robots' camera mounting, 7 numbers
        self.T_base_cam = se3_from_quat(base_cam[:3], base_cam[3:]) if base_cam else None
        self.subs.append(
            rospy.Subscriber("/robot_sightings", RobotSighting, self._on_sighting, queue_size=20)
        )
        self.srv = rospy.Service("~rendezvous", Rendezvous, self._on_rendezvous)
        from coop_slam.srv import GlobalBundleAdjustment

        self.srv_gba = rospy.Service("~global_ba", GlobalBundleAdjustment, self._on_global_ba)
        from coop_slam.srv import LoadMap, SaveMap

        self.srv_save = rospy.Service("~save_map", SaveMap, self._on_save_map)
        self.srv_load = rospy.Service("~load_map", LoadMap, self._on_load_map)
        from coop_slam.srv import Relocalize

        # Answered before the keyframes waiting in the queue: a lost robot waits for it.
        self.urgent: queue.Queue = queue.Queue()
        self.srv_reloc = rospy.Service("~relocalize", Relocalize, self._on_relocalize)
        self._map_dirty, self._last_stamp_s = False, 0.0
        self._said_idle = False  # stats said idle since the last job
        self.worker = threading.Thread(target=self._work, daemon=True)
        self.worker.start()
        self._publish_tf(rospy.Time.now())
        if self.durable.rebuilt is not None or self.durable.loaded is not None:
            self._publish_map(rospy.Time.now())
        rospy.loginfo("server: robots %s, waiting for keyframes", self.cfg.robots)

    def _open_map(self, resume: bool, load_path: str):
        """The durable team map: a new map file, the one resumed, or a saved map loaded."""
        from ..team.durable import DurableServer

        where = self.map_path or "memory only (map:=off)"
        what = "resuming" if resume else ("loading " + load_path if load_path else "new map")
        rospy.loginfo("server: team map file %s (%s)", where, what)

        def progress(done, total):
            rospy.loginfo("server: rebuilding the team map: %d/%d inputs", done, total)

        durable = DurableServer(
            self.cfg,
            lambda cfg: TeamServer(cfg, self.vocabulary),
            self.map_path,
            resume=resume,
            load_path=load_path or None,
            vocabulary_sha256=self.vocab_sha256,
            progress=progress,
            defer_global_ba=True,  # after a merge: when no keyframe message waits (_work)
        )
        for name, rep in (("resumed", durable.rebuilt), ("loaded", durable.loaded)):
            if rep is not None:
                rospy.loginfo(
                    "server: %s %d keyframes (%d inputs) in %.1f s; robots %s",
                    name,
                    rep.keyframes,
                    rep.inputs,
                    rep.time_s,
                    durable.robots,
                )
        return durable

    def _robot_topics(self) -> None:
        """Publishers and subscribers of every robot the server knows (loaded maps add some)."""
        from coop_slam.msg import KeyframeAck

        for r in self.durable.robots:
            if r in self.pub_path:
                continue
            self.pub_path[r] = rospy.Publisher(
                f"/team_map/robot_{r}/path", self._Path, queue_size=1, latch=True
            )
            self.pub_corr[r] = rospy.Publisher(
                f"/robot_{r}/correction", self._MapCorrection, queue_size=5, latch=True
            )
            self.pub_ack[r] = rospy.Publisher(
                f"/robot_{r}/keyframe_ack", KeyframeAck, queue_size=5, latch=True
            )
            if self.durable.pull is not None:
                self.pub_request[r] = rospy.Publisher(
                    f"/robot_{r}/keyframe_request", self._KeyframeRequest, queue_size=10, latch=True
                )
            self.subs.append(
                rospy.Subscriber(
                    f"/robot_{r}/keyframes",
                    self._KeyFrame,
                    self._on_keyframe,
                    callback_args=r,
                    queue_size=500,
                    buff_size=2**24,
                )
            )
            self._publish_ack(r)

    def _publish_ack(self, robot_id: int) -> None:
        from coop_slam.msg import KeyframeAck

        session, sequence = self.durable.acknowledged(robot_id)
        last_kf, last_seg = self.durable.last_ids().get(robot_id, (0, 0))
        msg = KeyframeAck(
            robot_id=robot_id,
            session=session,
            sequence=sequence,
            last_keyframe_id=last_kf,
            last_map_segment=last_seg,
            durable=self.durable.store is not None,
            refused_keyframe_ids=self.durable.refused(robot_id),
            server_session=self.server_session,
        )
        msg.header.stamp = rospy.Time.now()
        with self._ack_lock:
            self._acks[robot_id] = msg
            self.pub_ack[robot_id].publish(msg)

    def _publish_receipt(self, robot_id: int, session: int, sequence: int) -> None:
        """A numbered message arrived and waits in the queue to be stored: the client need not
        send it again while this server is busy with what came before (from the callback
        thread: the newest acknowledgement of what is stored, with the receipt added)."""
        with self._ack_lock:
            stored = self._acks.get(robot_id)  # (set only by _publish_ack, with its publisher)
            if stored is None:
                return
            msg = copy.copy(stored)
            msg.header = copy.copy(stored.header)
            msg.header.stamp = rospy.Time.now()
            msg.received_session, msg.received_sequence = session, sequence
            self.pub_ack[robot_id].publish(msg)

    def _on_keyframe(self, msg, topic_robot: int) -> None:
        topic = f"/robot_{topic_robot}/keyframes"
        if msg.robot_id != topic_robot:
            self.rejects.reject(
                topic, f"keyframe of robot {msg.robot_id} on robot {topic_robot}'s topic"
            )
            return
        try:
            msg = unpacked(msg)  # (once: needs_stored and keyframe_from_msg take it as it is)
            if needs_stored(msg):  # needs keyframes as the server holds them when its turn comes
                rec = PendingKeyframe(
                    msg.robot_id, lambda: self._stored_record(msg), msg.keyframe_id
                )
            else:
                rec = keyframe_from_msg(
                    msg,
                    known_robots=self.server.known_robots,
                    word_idf=self.vocabulary.word_weights,
                )
        except MessageError as exc:
            self.rejects.reject(topic, str(exc))
            return
        self.queue.put(_KeyframeJob(rec, msg.header.stamp.to_sec(), msg.session, msg.sequence))
        if msg.session:
            self._publish_receipt(topic_robot, msg.session, msg.sequence)

    def _stored_record(self, msg) -> KeyframeRecord:
        """A message completed from the keyframes the server holds (in the worker thread)."""
        return keyframe_from_msg(
            msg,
            known_robots=self.server.known_robots,
            stored=functools.partial(self.server.stored_record, msg.robot_id, msg.map_segment),
            word_idf=self.vocabulary.word_weights,
        )

    def _on_sighting(self, msg) -> None:
        """A marker sighting asks for a rendezvous check (at most once per pair and period)."""
        if (
            msg.observer_id not in self.server.known_robots
            or msg.observed_id not in self.server.known_robots
        ):
            self.rejects.reject(
                "/robot_sightings",
                f"sighting between unknown robots " f"{msg.observer_id} and {msg.observed_id}",
            )
            return
        try:
            T_cam_body = pose_from_msg(msg.T_cam_body, "T_cam_body")
        except MessageError as exc:
            self.rejects.reject("/robot_sightings", str(exc))
            return
        self.queue.put(
            _RendezvousJob(
                msg.observer_id, msg.observed_id, msg.header.stamp.to_sec(), T_cam_body, True
            )
        )

    def _on_rendezvous(self, req):
        from coop_slam.srv import RendezvousResponse

        reply: Future = Future()
        stamp = req.stamp.to_sec() or None
        self.queue.put(_RendezvousJob(req.robot_a, req.robot_b, stamp, reply=reply))
        try:
            merge, message = reply.result(timeout=60.0)
        except TimeoutError:
            return RendezvousResponse(accepted=False, message="server busy: request timed out")
        return RendezvousResponse(accepted=merge is not None, message=message)

    def _on_global_ba(self, req):
        """Runs in the worker thread like keyframes, so the team map has one writer."""
        from coop_slam.srv import GlobalBundleAdjustmentResponse

        reply: Future = Future()
        self.queue.put(_GlobalBaJob(req.robot_id or None, reply))
        try:
            r, message = reply.result(timeout=600.0)
        except TimeoutError:
            return GlobalBundleAdjustmentResponse(success=False, message="server busy: timed out")
        if r is None:
            return GlobalBundleAdjustmentResponse(success=False, message=message)
        return GlobalBundleAdjustmentResponse(
            success=True,
            message=message,
            keyframes=r.keyframes,
            points=r.points,
            observations=r.observations,
            error_before=r.rms_before,
            error_after=r.rms_after,
            time_s=r.time_ms / 1e3,
        )

    def _on_save_map(self, req):
        from coop_slam.srv import SaveMapResponse

        ok, message, path = self._map_file_request(req.path, load=False)
        return SaveMapResponse(success=ok, message=message, path=path)

    def _on_load_map(self, req):
        from coop_slam.srv import LoadMapResponse

        ok, message, _ = self._map_file_request(req.path, load=True)
        return LoadMapResponse(success=ok, message=message)

    def _map_file_request(self, path: str, load: bool):
        if not path.strip():
            return False, "give the map file's path", ""
        reply: Future = Future()
        self.queue.put(_MapFileJob(os.path.expanduser(path.strip()), load, reply))
        try:
            return reply.result(timeout=600.0)
        except TimeoutError:
            return False, "server busy: timed out", ""

    def _map_file(self, job: _MapFileJob) -> None:
        """Save the team map, or load a saved one as the starting map (in the worker thread)."""
        from ..team.map_store import MapStoreError, remove_map_file

        try:
            if not job.load:
                path = self.durable.save(job.path)
                result = True, f"team map saved to {path}", path
            elif any(self.durable.keyframes_stored().values()):
                result = (
                    False,
                    "a map loads only before robots send keyframes (start the server with "
                    "load_map:=FILE instead)",
                    "",
                )
            else:
                self.durable.close()
                if self.map_path:
                    remove_map_file(self.map_path)  # nothing taken yet: the file starts again
                self.durable = self._open_map(False, job.path)
                self.server = self.durable.server
                # A new run for the clients: what the old one received and had not stored (held
                # out of order) is gone, so their receipts no longer count.
                self.server_session = new_session()
                self._robot_topics()
                for r in self.durable.robots:
                    self._publish_ack(r)
                stamp = rospy.Time.from_sec(self._last_stamp_s)
                self._publish_tf(stamp)
                self._publish_map(stamp)
                result = True, f"loaded {job.path}: robots {self.durable.robots}", job.path
        except MapStoreError as exc:
            result = False, str(exc), ""
        if result[0]:
            rospy.loginfo("server: %s", result[1])
        else:
            rospy.logwarn("server: %s", result[1])
        job.reply.set_result(result)

    def _on_relocalize(self, req):
        """A lost robot's view -> the team's local map there (see
        :mod:`coop_slam.team.assisted_relocalization`); runs in the worker thread."""
        from coop_slam.srv import RelocalizeResponse

        from ..bow.signature import SignatureError, decode_signature

        try:
            bow = decode_signature(
                bytes(req.bow_word_gaps), bytes(req.bow_weights), float(req.bow_weight_max)
            )
        except SignatureError as exc:
            self.rejects.reject("~relocalize", str(exc))
            return RelocalizeResponse(found=False, message=str(exc))
        if req.robot_id not in self.server.known_robots:
            msg = f"robot {req.robot_id} is unknown to the server"
            self.rejects.reject("~relocalize", msg)
            return RelocalizeResponse(found=False, message=msg)
        reply: Future = Future()
        self.urgent.put(_RelocalizeJob(req.robot_id, req.map_segment, bow, reply))
        self.queue.put(None)  # wakes the worker if it waits for keyframes
        try:
            local, message, pending = reply.result(timeout=10.0)
        except TimeoutError:
            return RelocalizeResponse(found=False, message="server busy: timed out")
        if local is None:
            return RelocalizeResponse(found=False, pending=pending, message=message)
        return RelocalizeResponse(
            found=True,
            message=message,
            points=local.points_map.ravel().tolist(),
            descriptors=local.descriptors.tobytes(),
        )

    def _relocalize(self, job: _RelocalizeJob) -> None:
        from ..team.assisted_relocalization import local_map_for

        cfg = self.cfg.assisted_relocalization
        server = self.server
        local, message = None, "assisted relocalization is off (assisted_relocalization.enabled)"
        pending = None
        if cfg.enabled:
            segment = server.segments.segment_of(server.current_map(job.robot_id))
            pull = self.durable.pull
            if segment != job.map_segment:
                message = (
                    f"robot {job.robot_id} asks in map segment {job.map_segment}, the server "
                    f"holds segment {segment} as its newest"
                )
            elif pull is not None and (  # the place's keyframe may be a signature only
                pending := pull.ask_for_view(job.robot_id, job.bow, time.monotonic())
            ):
                message = (
                    f"asked robot {pending[0]} for keyframe {pending[1]}, the best match of its "
                    "view (low-bandwidth mode): ask again"
                )
                self._publish_requests()
            else:
                local = local_map_for(server, job.robot_id, job.bow, cfg)
                message = (
                    "no place of its group matches its view"
                    if local is None
                    else f"{len(local.points_map)} points of keyframes {local.keyframes} "
                    f"(BoW score {local.score:.3f})"
                )
        rospy.loginfo("server: relocalization for robot %d: %s", job.robot_id, message)
        job.reply.set_result((local, message, pending is not None))

    def _global_ba(self, job: _GlobalBaJob) -> None:
        from ..team.global_ba import GlobalBaError

        try:
            r = self.durable.global_bundle_adjustment(job.robot_id)
            result = r, (
                f"{r.keyframes} keyframes, {r.points} points: "
                f"reprojection RMS {r.rms_before:.2f} -> {r.rms_after:.2f} px"
            )
        except GlobalBaError as exc:  # the core logged a run; a refusal is logged here
            result = None, str(exc)
            rospy.logwarn("server: global BA: %s", exc)
        job.reply.set_result(result)

    def _rendezvous(self, job: _RendezvousJob) -> list | None:
        """The merges a request made; None for a sighting that is not a request."""
        T_body_cam = None if self.T_base_cam is None else invert(self.T_base_cam)
        T_camA_bodyB = job.T_camA_bodyB if T_body_cam is not None else None
        if job.sighting:
            outcome = self.durable.sighting(
                job.robot_a, job.robot_b, job.stamp_s, T_camA_bodyB, T_body_cam
            )
            if outcome is None:
                return None  # within rendezvous.sighting_period_s of the pair's last request
            merge, message = outcome
        else:
            merge, message = self.durable.request_rendezvous(
                job.robot_a, job.robot_b, job.stamp_s, T_camA_bodyB, T_body_cam
            )
        rospy.loginfo(
            "server: rendezvous request robot_%d / robot_%d: %s", job.robot_a, job.robot_b, message
        )
        if job.reply is not None:
            job.reply.set_result((merge, message))
        return [merge] if merge is not None else []

    def _work(self) -> None:
        while not rospy.is_shutdown():
            while not self.urgent.empty():
                job = self.urgent.get_nowait()
                try:
                    self._relocalize(job)
                except Exception as exc:  # noqa: BLE001 -- the worker must live on
                    rospy.logerr("server: relocalization failed (%s: %s)", type(exc).__name__, exc)
                    job.reply.set_result((None, f"server error: {exc}", False))
            try:
                item = self.queue.get(timeout=0.5)
            except queue.Empty:
                if self.durable.pull is not None:
                    self.durable.pull.expire(time.monotonic())
                try:
                    if self.durable.run_due_global_ba():
                        self._map_dirty = True
                except Exception as exc:  # noqa: BLE001 -- the worker must live on
                    rospy.logerr("server: global BA failed (%s: %s)", type(exc).__name__, exc)
                # The queue drained: show the final state of the map (once the builder is free).
                if self._map_dirty and not self.map_builder.busy:
                    stamp = rospy.Time.from_sec(self._last_stamp_s)
                    self._publish_tf(stamp)
                    self._publish_map(stamp)
                    self._publish_stats()
                elif (
                    not self._map_dirty
                    and not self.map_builder.busy
                    and not self._said_idle
                    and not (self.durable.pull is not None and self.durable.pull.pending)
                ):
                    # Nothing waits and the map is shown: said once (scripts/demo stops then).
                    self._said_idle = True
                    self._publish_stats(idle=True)
                continue
            if self._said_idle:  # busy again: said at once (a keyframe held back till the end)
                self._said_idle = False
                self._publish_stats()
            if item is None:  # a wake-up: urgent work came
                continue
            try:
                self._do(item)
            except Exception as exc:  # noqa: BLE001 -- the worker is the server: it must live on
                rospy.logerr(
                    "server: %s failed (%s: %s); the server carries on",
                    type(item).__name__.strip("_"),
                    type(exc).__name__,
                    exc,
                )
                reply = getattr(item, "reply", None)
                if reply is not None and not reply.done():
                    reply.set_result((None, f"server error: {type(exc).__name__}: {exc}"))

    def _do(self, item) -> None:
        """One job of the worker: a keyframe, a rendezvous request or sighting, a global BA."""
        if isinstance(item, _GlobalBaJob):
            self._global_ba(item)
            stamp = rospy.Time.from_sec(self._last_stamp_s)
            self._publish_tf(stamp)
            self._publish_map(stamp)
            return
        if isinstance(item, _RendezvousJob):
            merges = self._rendezvous(item)
            self._publish_requests()  # low-bandwidth mode: the pair's newest keyframes
            if merges is None:
                return
            stamp_s = merges[0].stamp_s if merges else (item.stamp_s or self._last_stamp_s)
        elif isinstance(item, _MapFileJob):
            self._map_file(item)
            return
        else:
            rec = item.record
            topic = f"/robot_{rec.robot_id}/keyframes"
            stamp_s = item.stamp_s
            try:
                taken = self.durable.add_keyframe(rec, item.session, item.sequence)
            except CoopSlamError as exc:
                self.rejects.reject(topic, str(exc))
                return
            finally:
                if rec.robot_id in self.pub_ack:
                    self._publish_ack(rec.robot_id)
            for why in taken.rejected or []:
                self.rejects.reject(topic, why)
            self._publish_requests()
            if taken.stale:
                self.rejects.reject(topic, "message of an earlier client session (restarted?)")
            self.duplicates += taken.duplicate
            if not taken.taken:
                return
            merges = taken.merges
        stamp_s = max(stamp_s, self._last_stamp_s)  # a late cue must not move the map back in time
        stamp = rospy.Time.from_sec(stamp_s)
        for m in merges:
            self._publish_merge(m, stamp_s)
        self._publish_constraints(stamp)
        if merges or self.server.map_moved:
            self._publish_tf(stamp)
        self._map_dirty, self._last_stamp_s = True, stamp_s
        self._merge_unshown |= bool(merges)
        if self.cadence.due(stamp_s, self._merge_unshown, time.monotonic()):
            self._publish_map(stamp)
        if len(self.server.keyframe_ms) % 10 == 0 or merges:
            self._publish_stats()

    def _publish_requests(self) -> None:
        """Low-bandwidth mode: ask robots for the whole keyframes the pull planner wants."""
        pull = self.durable.pull
        if pull is None:
            return
        for robot, ids in pull.take_requests().items():
            pub = self.pub_request.get(robot)
            if pub is None:
                continue
            self._request_count += 1
            rospy.loginfo(
                "server: asking robot %d for whole keyframes %s (low-bandwidth mode)",
                robot,
                sorted(ids),
            )
            pub.publish(
                self._KeyframeRequest(
                    robot_id=robot, request=self._request_count, keyframe_ids=sorted(ids)
                )
            )

    def _publish_merge(self, m, now_s: float = 0.0) -> None:
        """A merge event, stamped when it happened: the newest input's time (in low-bandwidth
        mode a pulled keyframe may be much older than the merge)."""
        msg = self._MergeEvent(
            type=m.type,
            robot_a=self.server.robot_of(m.robot_a),
            robot_b=self.server.robot_of(m.robot_b),
            keyframe_a=m.keyframe_a,
            keyframe_b=m.keyframe_b,
            T_mapA_mapB=transform_to_msg(m.T_mapA_mapB),
            T_camA_camB=transform_to_msg(m.T_camA_camB),
            inliers=m.inliers,
            residual_px=m.residual_px,
            scale=m.scale,
            group=sorted({self.server.robot_of(r) for r in m.group}),
        )
        msg.header.stamp = rospy.Time.from_sec(max(m.stamp_s, now_s))
        msg.header.frame_id = "world"
        self.pub_merge.publish(msg)  # the core logged the merge

    def _publish_constraints(self, stamp) -> None:
        """Constraints accepted inside a group since the last call, as merge events of type
        ``link`` (two robots) or ``loop`` (one robot); the core logged each."""
        new = self.server.constraints[self._constraints_published :]
        self._constraints_published += len(new)
        for c in new:
            (ra, ka), (rb, kb) = c.key_a, c.key_b
            robot_a, robot_b = self.server.robot_of(ra), self.server.robot_of(rb)
            msg = self._MergeEvent(
                type=TYPE_LOOP if robot_a == robot_b else TYPE_LINK,
                robot_a=robot_a,
                robot_b=robot_b,
                keyframe_a=ka,
                keyframe_b=kb,
                T_mapA_mapB=transform_to_msg(
                    np.linalg.inv(self.server.T_group_map(ra)) @ self.server.T_group_map(rb)
                ),
                T_camA_camB=transform_to_msg(c.T_camA_camB),
                inliers=c.inliers,
                residual_px=c.residual_px,
                scale=1.0,
                group=sorted({self.server.robot_of(r) for r in self.server.groups.members(ra)}),
            )
            msg.header.stamp = stamp
            msg.header.frame_id = "world"
            self.pub_merge.publish(msg)

    def _publish_tf(self, stamp) -> None:
        transforms = []
        for r in self.durable.robots:
            m = self.server.current_map(r)  # the map segment the client works in now
            T, merged = self.server.T_group_map(m), self.server.in_world(m)
            if merged:
                transforms.append(transform_stamped(T, "world", f"robot_{r}/map", stamp))
            corrected = self.server.pose_corrections(m)  # in the client's own units
            corr = self._MapCorrection(
                robot_id=r,
                merged=merged,
                T_world_map=transform_to_msg(T),
                keyframe_ids=list(corrected),
                keyframe_poses=[pose_to_msg(P) for P in corrected.values()],
                map_scale=self.server.map_scale(m),
                metric=self.server.is_metric(m),
            )
            corr.header.stamp, corr.header.frame_id = stamp, "world"
            self.pub_corr[r].publish(corr)
        if transforms:
            self.tf.sendTransform(transforms)

    def _publish_map(self, stamp) -> None:
        """The team map in ``world``: the markers (paths, merge edges, labels) now, the stitched
        cloud from the map builder. While the builder is busy the map stays due: the worker
        hands over a newer state when it is free (the next message, or idle)."""
        if self.map_builder.busy:
            self._map_dirty = True  # shown when the builder is free (idle: within 0.5 s)
            return
        self._map_dirty = self._merge_unshown = False
        self.map_builder.submit(self.server.team_cloud_job(), stamp.to_sec())
        self._publish_paths_and_markers(stamp)

    def _publish_cloud(self, cloud, stamp_s: float) -> None:
        """In the map builder's thread: a built cloud goes out."""
        if rospy.is_shutdown():  # built while the node stopped: nowhere to go
            return
        points, rgb, _ = cloud
        self.pub_cloud.publish(cloud_to_msg(points, "world", rospy.Time.from_sec(stamp_s), rgb))

    def _publish_paths_and_markers(self, stamp) -> None:
        from geometry_msgs.msg import Point
        from std_msgs.msg import ColorRGBA
        from visualization_msgs.msg import Marker, MarkerArray

        from ..team.fusion import robot_colours

        for r in self.durable.robots:
            poses = self.server.robot_keyframes(r)
            if not poses:
                continue
            m = self.server.current_map(r)
            merged = self.server.in_world(m)
            root = self.server.robot_of(self.server.groups.root(m))
            path = self._Path()
            path.header.stamp = stamp
            path.header.frame_id = "world" if merged else f"robot_{root}/map"
            for kf, (stamp_s, T) in poses.items():
                ps = PoseStamped(pose=pose_to_msg(T))
                ps.header.stamp = rospy.Time.from_sec(stamp_s)
                ps.header.frame_id = path.header.frame_id
                ps.header.seq = kf  # the keyframe id
                path.poses.append(ps)
            self.pub_path[r].publish(path)
        paths, edges = self.server.team_view()
        size = marker_scale(paths)
        markers = MarkerArray()
        clear = Marker(action=Marker.DELETEALL)
        clear.header.frame_id = "world"
        markers.markers.append(clear)

        def marker(ns, mid, kind, rgba, scale):
            m = Marker(ns=ns, id=mid, type=kind, action=Marker.ADD)
            m.header.frame_id, m.header.stamp = "world", stamp
            m.pose.orientation.w = 1.0
            m.scale.x = m.scale.y = m.scale.z = scale
            m.color = ColorRGBA(*rgba)
            return m

        for mid, pos in paths.items():  # per map (a robot's map segments apart)
            robot = self.server.robot_of(mid)
            c = robot_colours([robot])[0] / 255.0
            line = marker("paths", mid, Marker.LINE_STRIP, (*c, 1.0), 0.04 * size)
            line.points = [Point(*p) for p in pos]
            markers.markers.append(line)
            merged = self.server.in_world(mid)
            white = (1.0, 1.0, 1.0, 1.0)
            label = marker("labels", mid, Marker.TEXT_VIEW_FACING, white, 0.4 * size)
            label.text = f"robot_{robot}" + ("" if merged else " (unmerged)")
            if mid != robot:
                label.text += f" segment {self.server.segments.segment_of(mid)}"
            if not self.server.is_metric(mid):
                label.text += " (own scale)"  # a monocular map not merged with a metric one
            label.pose.position = Point(pos[-1][0], pos[-1][1], pos[-1][2] + 0.6 * size)
            markers.markers.append(label)
        colours = {
            "place_recognition": (1.0, 0.9, 0.1, 1.0),
            "rendezvous": (1.0, 0.2, 1.0, 1.0),
            TYPE_OVERLAP: (1.0, 0.6, 0.1, 1.0),
            TYPE_LOOP: (0.2, 1.0, 1.0, 1.0),
        }
        for k, (kind, pa, pb) in enumerate(edges):
            edge = marker(
                "merges", k, Marker.LINE_LIST, colours.get(kind, (1, 1, 1, 1)), 0.06 * size
            )
            edge.points = [Point(*pa), Point(*pb)]
            markers.markers.append(edge)
        self.pub_markers.publish(markers)

    def _publish_stats(self, idle: bool = False) -> None:
        """``idle``: no job waits, no global BA is due, no keyframe asked for is awaited and the
        team map shown is the latest."""
        ms = self.server.keyframe_ms
        opt = self.server.optimize_ms
        stats = {
            "keyframes": len(ms),
            "ms_per_keyframe_mean": sum(ms) / len(ms) if ms else None,
            "optimize_ms_mean": sum(opt) / len(opt) if opt else None,
            "merges": len(self.server.merges),
            "groups": [list(g) for g in self.server.robot_groups()],
            "loops": sum(c.type == TYPE_LOOP for c in self.server.constraints),
            "links": sum(c.type != TYPE_LOOP for c in self.server.constraints),
            "refused_constraints": self.server.rejected_constraints,
            "global_ba_runs": len(self.server.global_ba_runs),
            "verifications": self.server.verifications,
            "rejected": self.rejects.total,
            "duplicates": self.duplicates,
            "keyframes_stored": {str(r): n for r, n in self.durable.keyframes_stored().items()},
            "pull": self.durable.pull.stats() if self.durable.pull is not None else None,
            "metric": {
                str(r): self.server.is_metric(self.server.current_map(r))
                for r in self.durable.robots
            },
            "map_scale": {
                str(r): self.server.map_scale(self.server.current_map(r))
                for r in self.durable.robots
            },
            "map_file": self.durable.store.path if self.durable.store is not None else None,
            "idle": idle,
        }
        self.pub_stats.publish(String(data=json.dumps(stats)))


def main() -> None:
    rospy.init_node("server")
    forward_core_logs("server")
    try:
        node = ServerNode()
    except CoopSlamError as exc:
        rospy.logfatal("server: %s", exc)
        raise SystemExit(1) from exc
    rospy.on_shutdown(node._publish_stats)
    rospy.on_shutdown(lambda: node.rejects.flush(force=True))  # counts not logged yet
    rospy.spin()
