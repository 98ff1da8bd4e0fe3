"""Server node: receives every robot's keyframes, stitches the maps, publishes merges and TF.

Subscribes ``/robot_k/keyframes`` for each configured robot; publishes ``/merge_events``
(``coop_slam/MergeEvent``), TF ``world -> robot_k/map`` for every robot in the master's group,
``/robot_k/correction`` (``coop_slam/MapCorrection``), the team map (``/team_map/cloud``,
``/team_map/markers``, ``/team_map/robot_k/path``: optimized keyframe poses, in ``world`` once
merged, else in the robot's group root map) and ``/server/stats``. Keyframes are processed
in one worker thread in arrival order, so callbacks never block and the graph has one writer.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import threading
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String

from ..bow import Vocabulary
from ..config import load_yaml_config
from ..errors import CoopSlamError
from ..geometry import invert, se3_from_quat
from ..keyframe_record import KeyframeRecord
from ..team.config import ServerConfig
from ..team.results import TYPE_LINK, TYPE_LOOP, TYPE_OVERLAP
from ..team.server import TeamServer
from ..team.view import marker_scale
from .convert import (
    MessageError,
    cloud_to_msg,
    keyframe_from_msg,
    pose_from_msg,
    pose_to_msg,
    transform_stamped,
    transform_to_msg,
)
from .log_bridge import forward_core_logs
from .validation import RejectCounter

# Work for the worker thread, which alone changes the team map. A request that waits for its
# answer (a service call) carries a Future the worker completes.


@dataclass
class _KeyframeJob:
    record: KeyframeRecord


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


class ServerNode:
    def __init__(self):
        import tf2_ros

        from coop_slam.msg import KeyFrame, MapCorrection, MergeEvent

        node_params = ("config", "vocabulary", "T_base_cam", "cloud_period_s")
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
        self.server = TeamServer(self.cfg, Vocabulary.load(vocab_path))
        self.rejects = RejectCounter("server")
        self._constraints_published = 0  # server.constraints already sent as merge events
        self.queue: queue.Queue = queue.Queue()
        self.tf = tf2_ros.StaticTransformBroadcaster()
        self.pub_merge = rospy.Publisher("/merge_events", MergeEvent, queue_size=20, latch=True)
        self.pub_stats = rospy.Publisher("/server/stats", String, queue_size=5, latch=True)
        from coop_slam.msg import Vocabulary as VocabularyMsg

        self.pub_vocab = rospy.Publisher(
            "/server/vocabulary", VocabularyMsg, queue_size=1, latch=True
        )
        with open(vocab_path, "rb") as fh:
            data = fh.read()
        self.pub_vocab.publish(
            VocabularyMsg(
                format="coop_slam-npz" if data[:2] == b"PK" else "dbow2-text",
                sha256=hashlib.sha256(data).hexdigest(),
                k=self.server.vocabulary.k,
                levels=self.server.vocabulary.levels,
                data=data,
            )
        )
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        self.cloud_period_s = float(rospy.get_param("~cloud_period_s", 2.0))
        self._last_cloud_s = -1e9
        self.pub_cloud = rospy.Publisher("/team_map/cloud", PointCloud2, queue_size=1, latch=True)
        self.pub_markers = rospy.Publisher(
            "/team_map/markers", MarkerArray, queue_size=1, latch=True
        )
        from nav_msgs.msg import Path

        self._Path = Path
        self.pub_path = {
            r: rospy.Publisher(f"/team_map/robot_{r}/path", Path, queue_size=1, latch=True)
            for r in self.cfg.robots
        }
        self.pub_corr = {
            r: rospy.Publisher(f"/robot_{r}/correction", MapCorrection, queue_size=5, latch=True)
            for r in self.cfg.robots
        }
        self._MergeEvent, self._MapCorrection = MergeEvent, MapCorrection
        self.subs = [
            rospy.Subscriber(
                f"/robot_{r}/keyframes",
                KeyFrame,
                self._on_keyframe,
                callback_args=r,
                queue_size=500,
                buff_size=2**24,
            )
            for r in self.cfg.robots
        ]
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
        self._map_dirty, self._last_stamp_s = False, 0.0
        self.worker = threading.Thread(target=self._work, daemon=True)
        self.worker.start()
        self._publish_tf(rospy.Time.now())
        rospy.loginfo("server: robots %s, waiting for keyframes", self.cfg.robots)

    def _on_keyframe(self, msg, topic_robot: int) -> None:
        topic = f"/robot_{topic_robot}/keyframes"
        try:
            rec = keyframe_from_msg(msg, known_robots=self.server.known_robots)
        except MessageError as exc:
            self.rejects.reject(topic, str(exc))
            return
        if rec.robot_id != topic_robot:
            self.rejects.reject(
                topic, f"keyframe of robot {rec.robot_id} on robot {topic_robot}'s topic"
            )
            return
        self.queue.put(_KeyframeJob(rec))

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

    def _global_ba(self, job: _GlobalBaJob) -> None:
        from ..team.global_ba import GlobalBaError

        try:
            r = self.server.global_bundle_adjustment(job.robot_id)
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
            outcome = self.server.sighting(
                job.robot_a, job.robot_b, job.stamp_s, T_camA_bodyB, T_body_cam
            )
            if outcome is None:
                return None  # within rendezvous.sighting_period_s of the pair's last request
            merge, message = outcome
        else:
            merge, message = self.server.request_rendezvous(
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
            try:
                item = self.queue.get(timeout=0.5)
            except queue.Empty:
                if self._map_dirty:  # the queue drained: show the final state of the map
                    stamp = rospy.Time.from_sec(self._last_stamp_s)
                    self._publish_tf(stamp)
                    self._publish_map(stamp)
                    self._publish_stats()
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
            if merges is None:
                return
            stamp_s = merges[0].stamp_s if merges else (item.stamp_s or self._last_stamp_s)
        else:
            rec = item.record
            try:
                merges = self.server.add_keyframe(rec)
            except CoopSlamError as exc:
                self.rejects.reject(f"/robot_{rec.robot_id}/keyframes", str(exc))
                return
            stamp_s = rec.stamp_s
        stamp_s = max(stamp_s, self._last_stamp_s)  # a late cue must not move the map back in time
        stamp = rospy.Time.from_sec(stamp_s)
        for m in merges:
            self._publish_merge(m)
        self._publish_constraints(stamp)
        if merges or self.server.map_moved:
            self._publish_tf(stamp)
        self._map_dirty, self._last_stamp_s = True, stamp_s
        if merges or stamp_s - self._last_cloud_s >= self.cloud_period_s:
            self._last_cloud_s = stamp_s
            self._publish_map(stamp)
        if len(self.server.keyframe_ms) % 10 == 0 or merges:
            self._publish_stats()

    def _publish_merge(self, m) -> None:
        msg = self._MergeEvent(
            type=m.type,
            robot_a=m.robot_a,
            robot_b=m.robot_b,
            keyframe_a=m.keyframe_a,
            keyframe_b=m.keyframe_b,
            T_mapA_mapB=transform_to_msg(m.T_mapA_mapB),
            T_camA_camB=transform_to_msg(m.T_camA_camB),
            inliers=m.inliers,
            residual_px=m.residual_px,
            group=m.group,
        )
        msg.header.stamp = rospy.Time.from_sec(m.stamp_s)
        msg.header.frame_id = "world"
        self.pub_merge.publish(msg)  # the core logged the merge

    def _publish_constraints(self, stamp) -> None:
        """Constraints accepted inside a group since the last call, as merge events of type
        ``link`` (two robots) or ``loop`` (one robot); the core logged each."""
        new = self.server.constraints[self._constraints_published :]
        self._constraints_published += len(new)
        for c in new:
            (ra, ka), (rb, kb) = c.key_a, c.key_b
            msg = self._MergeEvent(
                type=TYPE_LOOP if ra == rb else TYPE_LINK,
                robot_a=ra,
                robot_b=rb,
                keyframe_a=ka,
                keyframe_b=kb,
                T_mapA_mapB=transform_to_msg(
                    np.linalg.inv(self.server.T_group_map(ra)) @ self.server.T_group_map(rb)
                ),
                T_camA_camB=transform_to_msg(c.T_camA_camB),
                inliers=c.inliers,
                residual_px=c.residual_px,
                group=self.server.groups.members(ra),
            )
            msg.header.stamp = stamp
            msg.header.frame_id = "world"
            self.pub_merge.publish(msg)

    def _publish_tf(self, stamp) -> None:
        transforms = []
        for r in self.cfg.robots:
            T, merged = self.server.T_group_map(r), self.server.in_world(r)
            if merged:
                transforms.append(transform_stamped(T, "world", f"robot_{r}/map", stamp))
            corrected = self.server.corrected_keyframes(r)
            corr = self._MapCorrection(
                robot_id=r,
                merged=merged,
                T_world_map=transform_to_msg(T),
                keyframe_ids=list(corrected),
                keyframe_poses=[pose_to_msg(P) for P in corrected.values()],
            )
            corr.header.stamp, corr.header.frame_id = stamp, "world"
            self.pub_corr[r].publish(corr)
        if transforms:
            self.tf.sendTransform(transforms)

    def _publish_map(self, stamp) -> None:
        """Stitched team cloud and the markers (paths, merge edges, labels), in ``world``."""
        self._map_dirty = False
        from geometry_msgs.msg import Point
        from std_msgs.msg import ColorRGBA
        from visualization_msgs.msg import Marker, MarkerArray

        from ..team.fusion import robot_colours

        points, rgb, _ = self.server.team_cloud()
        self.pub_cloud.publish(cloud_to_msg(points, "world", stamp, rgb))
        for r in self.cfg.robots:
            poses = self.server.optimized_keyframes(r)
            if not poses:
                continue
            merged = self.server.in_world(r)
            path = self._Path()
            path.header.stamp = stamp
            path.header.frame_id = "world" if merged else f"robot_{self.server.groups.root(r)}/map"
            for kf, T in poses.items():
                ps = PoseStamped(pose=pose_to_msg(T))
                ps.header.stamp = rospy.Time.from_sec(self.server.store.stamp((r, kf)))
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

        for robot, pos in paths.items():
            c = robot_colours([robot])[0] / 255.0
            line = marker("paths", robot, Marker.LINE_STRIP, (*c, 1.0), 0.04 * size)
            line.points = [Point(*p) for p in pos]
            markers.markers.append(line)
            merged = self.server.in_world(robot)
            white = (1.0, 1.0, 1.0, 1.0)
            label = marker("labels", robot, Marker.TEXT_VIEW_FACING, white, 0.4 * size)
            label.text = f"robot_{robot}" + ("" if merged else " (unmerged)")
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

    def _publish_stats(self) -> None:
        ms = self.server.keyframe_ms
        opt = self.server.optimize_ms
        stats = {
            "keyframes": len(ms),
            "ms_per_keyframe_mean": sum(ms) / len(ms) if ms else None,
            "optimize_ms_mean": sum(opt) / len(opt) if opt else None,
            "merges": len(self.server.merges),
            "groups": self.server.groups.groups(),
            "loops": sum(c.type == TYPE_LOOP for c in self.server.constraints),
            "links": sum(c.type != TYPE_LOOP for c in self.server.constraints),
            "refused_constraints": self.server.rejected_constraints,
            "global_ba_runs": len(self.server.global_ba_runs),
            "verifications": self.server.verifications,
            "rejected": self.rejects.total,
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
