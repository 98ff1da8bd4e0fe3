"""Server node: receives every robot's keyframes, stitches the maps, publishes merges and TF.

Subscribes ``/robot_k/keyframes`` and ``/robot_k/description`` (each robot's camera and marker
mounts, :mod:`coop_slam.robot_description`) for each configured robot and ``/robot_sightings``;
publishes
``/merge_events`` (``coop_slam/MergeEvent``), TF ``world -> robot_k/map`` for every robot in the
master's group, ``/robot_k/correction`` (``coop_slam/MapCorrection``), the team map
(``/team_map/cloud``, ``/team_map/markers``, ``/team_map/robot_k/path``: optimized keyframe poses,
in ``world`` once merged, else in the robot's group root map) and ``/server/stats``. Services
``~rendezvous``, ``~global_ba``, ``~relocalize``, ``~save_map``, ``~load_map``.

The work is :class:`coop_slam.team.worker.ServerWorker`'s, in one thread that alone changes the
team map; this node only translates between ROS and it. The team map is durable
(:mod:`coop_slam.team.durable`): every input is committed to the map file (``~map``; default a
new file per run under ``$ROS_HOME/coop_slam``, ``off`` for none) before ``/robot_k/keyframe_ack``
acknowledges it; ``~resume`` rebuilds the team map from that file after a crash or restart,
``~load_map`` starts from a map saved in an earlier session. The parameter ``/team_map/map_id``
names the team map (kept on resume): a client's spool made for another map is set aside, unsent.

A keyframe link that rospy dropped (a message it could not read) is subscribed again
(:class:`.link_watch.LinkWatch`): rospy itself never reconnects while the publisher stays
registered.
"""

from __future__ import annotations

import functools
import hashlib
import os
import threading
from concurrent.futures import Future

import rospy

from ..bow import Vocabulary
from ..config import load_yaml_config
from ..errors import CoopSlamError
from ..team.config import ServerConfig
from ..team.durable import DurableServer
from ..team.jobs import GlobalBaJob, MapFileJob, RelocalizeJob, RendezvousJob
from ..team.publish_cadence import PublishCadenceConfig
from ..team.server import TeamServer
from ..team.worker import ServerWorker, default_map_path
from ..wire.codec import WireError, signature_bow
from ..wire.messages import KeyframeMessage
from .convert import MessageError, description_from_msg, marker_seen_from_msg
from .link_watch import LinkWatch
from .log_bridge import forward_core_logs
from .params import server_params
from .server_outputs import RosServerOutputs
from .uplink_bridge import VOCABULARY_SHA256_TOPIC
from .wire_bridge import from_ros


def load_vocabulary(path: str) -> tuple[Vocabulary, bytes]:
    """The shared vocabulary (``path``, or the default one setup builds) and its file's bytes."""
    if not path:
        from ..default_vocabulary import default_vocabulary_path

        path = default_vocabulary_path()
    if not os.path.isfile(path):
        raise CoopSlamError(
            f"vocabulary file not found: {path} (run scripts/setup, which builds the default "
            "vocabulary, or set ~vocabulary)"
        )
    rospy.loginfo("server: loading vocabulary %s", path)
    with open(path, "rb") as fh:
        data = fh.read()
    return Vocabulary.load(path), data


class ServerNode:
    def __init__(self):
        from std_msgs.msg import String

        from coop_slam.msg import KeyframeMessage as KeyframeMessageRos
        from coop_slam.msg import RobotDescription as RobotDescriptionMsg
        from coop_slam.msg import RobotSighting
        from coop_slam.msg import Vocabulary as VocabularyMsg
        from coop_slam.srv import GlobalBundleAdjustment, LoadMap, Relocalize, Rendezvous, SaveMap

        p, overrides = server_params(rospy.get_param("~", {}))
        self.cfg = load_yaml_config(ServerConfig, p.config, "server", overrides)
        self.vocabulary, vocab_data = load_vocabulary(p.vocabulary)
        self.vocab_sha256 = hashlib.sha256(vocab_data).hexdigest()
        map_path = p.map.strip()
        self.map_path = None if map_path == "off" else (map_path or default_map_path())
        # Topics of every robot the worker names (a loaded map may add robots).
        self.out = RosServerOutputs(self.cfg.pull.enabled, on_robots=self._subscribe)
        # Its digest alone (a few bytes) first: a robot that has the same file never downloads
        # the vocabulary (3 MB) across the radio.
        self.pub_vocab_sha = rospy.Publisher(
            VOCABULARY_SHA256_TOPIC, String, queue_size=1, latch=True
        )
        self.pub_vocab_sha.publish(String(self.vocab_sha256))
        self.pub_vocab = rospy.Publisher(
            "/server/vocabulary", VocabularyMsg, queue_size=1, latch=True
        )
        self.pub_vocab.publish(
            VocabularyMsg(
                format="coop_slam-npz" if vocab_data[:2] == b"PK" else "dbow2-text",
                sha256=self.vocab_sha256,
                k=self.vocabulary.k,
                levels=self.vocabulary.levels,
                data=vocab_data,
            )
        )
        self._KeyframeMessage = KeyframeMessageRos
        self._RobotDescription = RobotDescriptionMsg
        self.watch = LinkWatch("server")
        self.subs: set[int] = set()  # robots whose keyframes are subscribed
        self.worker = ServerWorker(
            self.cfg,
            self._open_map,
            self.out,
            cadence=PublishCadenceConfig(p.cloud_period_s, p.cloud_max_busy_share),
            resume=p.resume,
            load_path=p.load_map.strip() or None,
        )
        self.worker.start()
        self.watch.watch(
            "/robot_sightings",
            lambda: rospy.Subscriber(
                "/robot_sightings", RobotSighting, self._on_sighting, queue_size=20
            ),
            "the robots' sightings",
        )
        self.srv = [
            rospy.Service("~rendezvous", Rendezvous, self._on_rendezvous),
            rospy.Service("~global_ba", GlobalBundleAdjustment, self._on_global_ba),
            rospy.Service("~save_map", SaveMap, self._on_save_map),
            rospy.Service("~load_map", LoadMap, self._on_load_map),
            rospy.Service("~relocalize", Relocalize, self._on_relocalize),
        ]
        self.thread = threading.Thread(
            target=self.worker.run, args=(rospy.is_shutdown,), daemon=True
        )
        self.thread.start()
        rospy.loginfo("server: robots %s, waiting for keyframes", self.cfg.robots)

    def _open_map(self, resume: bool, load_path: str | None) -> DurableServer:
        """The durable team map: a new map file, the one resumed, or a saved map loaded."""
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
            load_path=load_path,
            vocabulary_sha256=self.vocab_sha256,
            progress=progress,
            defer_global_ba=True,  # after a merge: when no keyframe message waits
        )
        rospy.set_param("/team_map/map_id", durable.map_id)
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

    def _subscribe(self, robot_ids) -> None:
        for r in robot_ids:
            if r not in self.subs:
                self.subs.add(r)
                self.watch.watch(
                    f"/robot_{r}/keyframes",
                    functools.partial(
                        rospy.Subscriber,
                        f"/robot_{r}/keyframes",
                        self._KeyframeMessage,
                        self._on_keyframe,
                        callback_args=r,
                        queue_size=500,
                        buff_size=2**24,
                    ),
                    f"robot {r}'s keyframe",
                )
                rospy.Subscriber(
                    f"/robot_{r}/description",
                    self._RobotDescription,
                    self._on_description,
                    callback_args=r,
                    queue_size=2,
                )

    # --- callbacks: ROS in, jobs to the worker ----------------------------------------------------
    def _on_keyframe(self, msg, topic_robot: int) -> None:
        self.worker.receive(from_ros(msg, KeyframeMessage), topic_robot, rospy.get_time())

    def _on_sighting(self, msg) -> None:
        """A marker sighting asks for a rendezvous check (at most once per pair and period)."""
        known = self.worker.server.known_robots
        if msg.observer_id not in known or msg.observed_id not in known:
            self.worker.reject(
                "/robot_sightings",
                f"sighting between unknown robots {msg.observer_id} and {msg.observed_id}",
            )
            return
        try:
            seen = marker_seen_from_msg(msg)
        except MessageError as exc:
            self.worker.reject("/robot_sightings", str(exc))
            return
        self.worker.put(
            RendezvousJob(msg.observer_id, msg.observed_id, msg.header.stamp.to_sec(), seen, True)
        )

    def _on_description(self, msg, topic_robot: int) -> None:
        """A robot's own description: how its sightings are placed."""
        topic = f"/robot_{topic_robot}/description"
        try:
            description = description_from_msg(msg)
        except MessageError as exc:
            self.worker.reject(topic, str(exc))
            return
        if description.robot_id != topic_robot:
            self.worker.reject(topic, f"describes robot {description.robot_id}")
            return
        self.worker.sightings.describe(description)

    def _ask(self, job, timeout_s: float, urgent: bool = False):
        """Hand ``job`` to the worker and wait for its answer (None: timed out)."""
        (self.worker.put_urgent if urgent else self.worker.put)(job)
        try:
            return job.reply.result(timeout=timeout_s)
        except TimeoutError:
            return None

    def _on_rendezvous(self, req):
        from coop_slam.srv import RendezvousResponse

        job = RendezvousJob(req.robot_a, req.robot_b, req.stamp.to_sec() or None, reply=Future())
        answer = self._ask(job, 60.0)
        if answer is None:
            return RendezvousResponse(accepted=False, message="server busy: request timed out")
        merge, message = answer
        return RendezvousResponse(accepted=merge is not None, message=message)

    def _on_global_ba(self, req):
        from coop_slam.srv import GlobalBundleAdjustmentResponse as Response

        answer = self._ask(GlobalBaJob(req.robot_id or None, Future()), 600.0)
        if answer is None:
            return Response(success=False, message="server busy: timed out")
        r, message = answer
        if r is None:
            return Response(success=False, message=message)
        return Response(
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
        answer = self._ask(MapFileJob(os.path.expanduser(path.strip()), load, Future()), 600.0)
        return answer if answer is not None else (False, "server busy: timed out", "")

    def _on_relocalize(self, req):
        """A lost robot's view -> the team's local map there (answered before waiting keyframes)."""
        from coop_slam.srv import RelocalizeResponse

        try:
            bow = signature_bow(
                bytes(req.bow_word_gaps), bytes(req.bow_weights), float(req.bow_weight_max)
            )
        except WireError as exc:
            self.worker.reject("~relocalize", str(exc))
            return RelocalizeResponse(found=False, message=str(exc))
        if req.robot_id not in self.worker.server.known_robots:
            message = f"robot {req.robot_id} is unknown to the server"
            self.worker.reject("~relocalize", message)
            return RelocalizeResponse(found=False, message=message)
        job = RelocalizeJob(req.robot_id, req.map_segment, bow, Future())
        answer = self._ask(job, 10.0, urgent=True)
        if answer is None:
            return RelocalizeResponse(found=False, message="server busy: timed out")
        local, message, pending = answer
        if local is None:
            return RelocalizeResponse(found=False, pending=pending, message=message)
        return RelocalizeResponse(
            found=True,
            message=message,
            points=local.points_map.ravel().tolist(),
            descriptors=local.descriptors.tobytes(),
        )

    def shutdown(self) -> None:
        self.out.stats(self.worker.stats())
        self.out.rejects.flush(force=True)  # counts not logged yet


def main() -> None:
    rospy.init_node("server")
    forward_core_logs("server")
    try:
        node = ServerNode()
    except CoopSlamError as exc:
        rospy.logfatal("server: %s", exc)
        raise SystemExit(1) from exc
    rospy.on_shutdown(node.shutdown)
    rospy.spin()
