"""The server's engine: one worker that alone changes the team map, driven the same way by the
server node, ``scripts/replay`` and ``scripts/bench``.

Inputs come as jobs (:class:`KeyframeJob` from :meth:`ServerWorker.intake`, rendezvous requests
and marker sightings, a global BA, saving or loading the map file, a lost robot's relocalization);
the worker takes them one at a time (:meth:`ServerWorker.handle`; :meth:`ServerWorker.run` is the
node's loop over a queue), and when none waits it does what a quiet moment allows
(:meth:`ServerWorker.idle`: expire unanswered keyframe requests, the global BA a merge left due,
show the final state of the map). What it decides goes to a :class:`ServerOutputs` -- the node
publishes it, the bench and replay count or ignore it -- so every entry point runs this code and no
copy of it.
"""

from __future__ import annotations

import logging
import os
import queue
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import CoopSlamError
from ..wire.codec import WireError, decode
from ..wire.delivery import new_session
from ..wire.legacy import decode_legacy, is_legacy
from ..wire.messages import Header, KeyframeAck, KeyframeMessage, KeyframeRequest, Stamp
from .assisted_relocalization import local_map_for
from .clocks import RobotClocks
from .config import ServerConfig
from .dense_map import DenseMap
from .durable import DurableServer
from .global_ba import GlobalBaError
from .jobs import GlobalBaJob, KeyframeJob, MapFileJob, RelocalizeJob, RendezvousJob
from .map_builder import TeamMapBuilder
from .map_store import MapStoreError, remove_map_file
from .publish_cadence import PublishCadence, PublishCadenceConfig
from .results import TYPE_LINK, TYPE_LOOP
from .sightings import SightingPlacer

log = logging.getLogger(__name__)


# --- what the worker says ------------------------------------------------------------------------
@dataclass
class TeamEvent:
    """A merge (``place_recognition``, ``rendezvous``) or a constraint inside a group (``link``
    between two robots, ``loop`` within one), by robot id."""

    type: str
    robot_a: int
    robot_b: int
    keyframe_a: int
    keyframe_b: int
    T_mapA_mapB: np.ndarray
    T_camA_camB: np.ndarray
    inliers: int
    residual_px: float
    scale: float
    group: list[int]
    stamp_s: float


@dataclass
class RobotCorrection:
    """Where a robot's current map is in its group (``T_group_map``; the team's ``world`` when
    ``merged``) and the optimized poses of its keyframes in its own units."""

    robot_id: int
    merged: bool
    T_group_map: np.ndarray
    keyframe_poses: dict[int, np.ndarray]
    map_scale: float
    metric: bool


@dataclass
class MapLabel:
    """How one map (a robot's map segment) is shown: its path and what its label says."""

    map_id: int
    robot_id: int
    path_xyz: np.ndarray  # (K, 3) keyframe positions in the team frame
    merged: bool
    segment: int | None  # None: the robot's first map
    metric: bool


@dataclass
class TeamMapView:
    """The team map as the node shows it besides the cloud: every robot's optimized keyframes
    (in ``world`` when merged, else in its group root's map), each map's path and label, and the
    edges of merges, links and loops."""

    robot_paths: dict[int, tuple[str, dict[int, tuple[float, np.ndarray]]]]  # robot -> (frame, ..)
    maps: list[MapLabel] = field(default_factory=list)
    edges: list[tuple[str, np.ndarray, np.ndarray]] = field(default_factory=list)


class ServerOutputs:
    """Where the worker's decisions go; every method may be left as this no-op. The server node
    publishes them; the bench and replay count what they need."""

    # Whether the team map is shown (built): the node and the bench (which measures its cost)
    # say so; a replay does not need it.
    wants_team_map = False

    def reject(self, where: str, why: str) -> None:
        """A message or request refused (the node counts and logs them)."""

    def event(self, event: TeamEvent) -> None:
        """A merge, link or loop."""

    def corrections(self, corrections: list[RobotCorrection], stamp_s: float) -> None:
        """Every robot's place in the team and its keyframes' optimized poses."""

    def team_map(self, view: TeamMapView, stamp_s: float) -> None:
        """Paths, labels and edges of the team map (the cloud comes by :meth:`cloud`)."""

    def cloud(self, cloud: tuple, stamp_s: float) -> None:
        """The stitched cloud (points, colours, ...), in the map builder's thread."""

    def dense_map(self, dense: DenseMap, stamp_s: float) -> None:
        """The dense cloud and the occupancy grid (:mod:`.dense_map`), in the builder's thread."""

    def ack(self, ack: KeyframeAck) -> None:
        """An acknowledgement (or a receipt) for one robot; any thread."""

    def request(self, request: KeyframeRequest) -> None:
        """Low-bandwidth mode: ask a robot for whole keyframes."""

    def stats(self, stats: dict) -> None:
        """The server's counters (``idle``: nothing waits and the map shown is the latest)."""

    def robots(self, robot_ids: list[int]) -> None:
        """The robots the server knows (a loaded map may add some)."""


def default_map_path() -> str:
    """A new map file per run in ``$ROS_HOME/coop_slam`` (``~/.ros`` by default)."""
    home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    folder = os.path.join(home, "coop_slam")
    os.makedirs(folder, exist_ok=True)
    return os.path.join(folder, time.strftime("team_map_%Y%m%d-%H%M%S.db"))


class ServerWorker:
    """The team map's one writer. ``open_map(resume, load_path)`` gives the durable server (the
    node's opens a file, a replay's none); ``defer_global_ba``: a merge's global BA waits until no
    job waits (the node), else it runs at once (a replay: deterministic)."""

    def __init__(
        self,
        cfg: ServerConfig,
        open_map: Callable[[bool, str | None], DurableServer],
        outputs: ServerOutputs | None = None,
        cadence: PublishCadenceConfig | None = None,
        resume: bool = False,
        load_path: str | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.cfg = cfg
        self.out = outputs or ServerOutputs()
        self.clock = clock
        self._open_map = open_map
        self.durable = open_map(resume, load_path)
        self.sightings = SightingPlacer()  # each robot's description places its sightings
        self.clocks = RobotClocks(cfg.clock)  # each robot's clock against the server's
        self.cadence = PublishCadence(cadence)
        self.map_builder = TeamMapBuilder(self._built, self.cadence)
        self.queue: queue.Queue = queue.Queue()
        self.urgent: queue.Queue = queue.Queue()  # answered before the keyframes waiting
        self.server_session = new_session()  # this run (a restart lost what it had not stored)
        self.duplicates = 0  # keyframe messages received again (a client re-sending)
        self.rejected = 0
        self.last_decided_s = 0.0  # wall clock when the last keyframe job was taken
        self._acks: dict[int, KeyframeAck] = {}
        self._constraints_published = 0
        self._request_count = 0
        self._map_dirty = self._merge_unshown = self._said_idle = False
        self._last_stamp_s = 0.0

    @property
    def server(self):
        return self.durable.server

    def start(self) -> None:
        """Say what a started server holds: its robots, their acknowledgements, its map."""
        self.out.robots(self.durable.robots)
        for r in self.durable.robots:
            self.acknowledge(r)
        self._publish_tf(0.0)
        if self.durable.rebuilt is not None or self.durable.loaded is not None:
            self._publish_map(0.0)

    def close(self) -> None:
        self.map_builder.close(timeout_s=None)

    # --- intake (any thread) ----------------------------------------------------------------------
    def reject(self, where: str, why: str) -> None:
        self.rejected += 1
        self.out.reject(where, why)

    def intake(
        self, msg: KeyframeMessage, topic_robot: int, arrived_s: float = 0.0
    ) -> KeyframeJob | None:
        """A robot's keyframe message as a job (decoded and checked here, in the receiving
        thread, so the worker only applies it); None when refused. A message of a run recorded
        before each kind had its own type is read as such (:mod:`coop_slam.wire.legacy`).
        ``arrived_s``: when it arrived on the server's clock (0: not known); with when it was
        sent on the robot's, it measures the robot's clock, and its stamps are taken in the
        server's time (see :mod:`.clocks`)."""
        topic = f"/robot_{topic_robot}/keyframes"
        if msg.robot_id != topic_robot:
            self.reject(topic, f"keyframe of robot {msg.robot_id} on robot {topic_robot}'s topic")
            return None
        known, idf = self.server.known_robots, self.server.vocabulary.word_weights
        try:
            item = decode_legacy(msg, known, idf) if is_legacy(msg) else decode(msg, known, idf)
        except WireError as exc:
            self.reject(topic, str(exc))
            return None
        sent = getattr(msg, "sent", None)  # (not in older recordings)
        if sent is not None and arrived_s > 0:
            self.clocks.observe(topic_robot, sent.to_sec(), arrived_s)
        shift_s = self.clocks.correction(topic_robot)
        item = self.clocks.to_server_time(item, shift_s)
        stamp_s = msg.header.stamp.to_sec()
        if stamp_s > 0:  # (a removal carries none)
            stamp_s -= shift_s
        session, sequence = getattr(msg, "session", 0), getattr(msg, "sequence", 0)
        return KeyframeJob(item, stamp_s, session, sequence)

    def receive(self, msg: KeyframeMessage, topic_robot: int, arrived_s: float = 0.0) -> None:
        """The node's subscriber: :meth:`intake`, queue the job, and say it was received."""
        job = self.intake(msg, topic_robot, arrived_s)
        if job is None:
            return
        self.queue.put(job)
        if msg.session:
            self.receipt(topic_robot, msg.session, msg.sequence)

    def put(self, job) -> None:
        self.queue.put(job)

    def put_urgent(self, job: RelocalizeJob) -> None:
        self.urgent.put(job)
        self.queue.put(None)  # wakes the worker if it waits for keyframes

    # --- acknowledgements -------------------------------------------------------------------------
    def acknowledge(self, robot_id: int) -> KeyframeAck:
        """What is stored for ``robot_id``, acknowledged."""
        session, sequence = self.durable.acknowledged(robot_id)
        last_kf, last_seg = self.durable.last_ids().get(robot_id, (0, 0))
        ack = KeyframeAck(
            header=Header(stamp=Stamp.from_sec(time.time())),
            robot_id=robot_id,
            session=session,
            sequence=sequence,
            last_keyframe_id=last_kf,
            last_map_segment=last_seg,
            durable=self.durable.store is not None,
            refused_keyframe_ids=self.durable.refused(robot_id),
            server_session=self.server_session,
        )
        self._acks[robot_id] = ack
        self.out.ack(ack)
        return ack

    def receipt(self, robot_id: int, session: int, sequence: int) -> None:
        """A numbered message arrived and waits to be stored: the client need not send it again
        while this server is busy with what came before (the newest acknowledgement of what is
        stored, with the receipt added)."""
        stored = self._acks.get(robot_id)
        if stored is None:
            return
        ack = KeyframeAck(**{**stored.__dict__})
        ack.header = Header(stamp=Stamp.from_sec(time.time()))
        ack.received_session, ack.received_sequence = session, sequence
        self.out.ack(ack)

    # --- the loop ---------------------------------------------------------------------------------
    def run(self, stopped: Callable[[], bool], idle_after_s: float = 0.5) -> None:
        """Take jobs until ``stopped()``; urgent ones first, :meth:`idle` when none came for
        ``idle_after_s``."""
        while not stopped():
            while not self.urgent.empty():
                self.handle(self.urgent.get_nowait())
            try:
                job = self.queue.get(timeout=idle_after_s)
            except queue.Empty:
                self.idle()
                continue
            if job is not None:  # (None: a wake-up, urgent work came)
                self.handle(job)

    def handle(self, job) -> list:
        """One job; the merges it made. The worker is the server: a job that fails is logged and
        answered, and the worker carries on."""
        if self._said_idle:  # busy again: said at once
            self._said_idle = False
            self._publish_stats()
        try:
            return self._do(job)
        except Exception as exc:  # noqa: BLE001 -- the worker must live on
            log.error(
                "%s failed (%s: %s); the server carries on",
                type(job).__name__,
                type(exc).__name__,
                exc,
            )
            reply = getattr(job, "reply", None)
            if reply is not None and not reply.done():
                reply.set_result((None, f"server error: {type(exc).__name__}: {exc}"))
            return []

    def idle(self) -> bool:
        """No job waits: expire unanswered keyframe requests, run the global BA a merge left
        due, show the final state of the map (once the builder is free), and say once that the
        server is idle. True if it did work."""
        pull = self.durable.pull
        if pull is not None:
            pull.expire(self.clock())
        worked = False
        try:
            if self.durable.run_due_global_ba():
                self._map_dirty = worked = True
        except Exception as exc:  # noqa: BLE001 -- the worker must live on
            log.error("global BA failed (%s: %s)", type(exc).__name__, exc)
        if self._map_dirty and not self.map_builder.busy:
            self._publish_tf(self._last_stamp_s)
            self._publish_map(self._last_stamp_s)
            self._publish_stats()
            return True
        if (
            not self._map_dirty
            and not self.map_builder.busy
            and not self._said_idle
            and not (pull is not None and pull.pending)
        ):
            self._said_idle = True  # said once (scripts/demo stops then)
            self._publish_stats(idle=True)
        return worked

    # --- jobs -------------------------------------------------------------------------------------
    def _do(self, job) -> list:
        if isinstance(job, GlobalBaJob):
            self._global_ba(job)
            self._publish_tf(self._last_stamp_s)
            self._publish_map(self._last_stamp_s)
            return []
        if isinstance(job, MapFileJob):
            self._map_file(job)
            return []
        if isinstance(job, RelocalizeJob):
            self._relocalize(job)
            return []
        if isinstance(job, RendezvousJob):
            merges = self._rendezvous(job)
            self._publish_requests()  # low-bandwidth mode: the pair's newest keyframes
            if merges is None:
                return []
            stamp_s = merges[0].stamp_s if merges else (job.stamp_s or self._last_stamp_s)
        else:
            merges = self._keyframe(job)
            if merges is None:
                return []
            stamp_s = job.stamp_s
        self._after(merges, stamp_s)
        return merges

    def _keyframe(self, job: KeyframeJob) -> list | None:
        """The merges a keyframe message made; None when nothing was taken."""
        robot_id = job.item.robot_id
        topic = f"/robot_{robot_id}/keyframes"
        try:
            taken = self.durable.add_keyframe(job.item, job.session, job.sequence)
        except CoopSlamError as exc:
            self.reject(topic, str(exc))
            return None
        finally:
            self.last_decided_s = time.perf_counter()
            if robot_id in self.durable.robots:
                self.acknowledge(robot_id)
        for why in taken.rejected or []:
            self.reject(topic, why)
        self._publish_requests()
        if taken.stale:
            self.reject(topic, "message of an earlier client session (restarted?)")
        self.duplicates += taken.duplicate
        return taken.merges if taken.taken else None

    def _after(self, merges: list, stamp_s: float) -> None:
        """What a job that changed the map publishes: merges and constraints, the robots' place
        when their maps moved, the team map when its cadence allows."""
        stamp_s = max(stamp_s, self._last_stamp_s)  # a late cue must not move the map back
        for m in merges:
            self.out.event(self._merge_event(m, stamp_s))
        self._publish_constraints(stamp_s)
        if merges or self.server.map_moved:
            self._publish_tf(stamp_s)
        self._map_dirty, self._last_stamp_s = True, stamp_s
        self._merge_unshown |= bool(merges)
        if self.cadence.due(stamp_s, self._merge_unshown, time.monotonic()):
            self._publish_map(stamp_s)
        if len(self.server.keyframe_ms) % 10 == 0 or merges:
            self._publish_stats()

    def _rendezvous(self, job: RendezvousJob) -> list | None:
        """The merges a request made; None for a sighting that is not a request."""
        refusal = self.clocks.refusal(job.robot_a, job.robot_b)
        if refusal is not None:
            if not job.sighting:
                log.warning("rendezvous request robot_%d / robot_%d: %s", *job.pair, refusal)
            if job.reply is not None:
                job.reply.set_result((None, refusal))
            return None if job.sighting else []
        if job.sighting and job.stamp_s is not None:  # seen on the observer's clock
            job.stamp_s -= self.clocks.correction(job.robot_a)
        T_camA_bodyB, T_bodyB_camB = self.sightings.place(job.robot_b, job.marker)
        if job.sighting:
            outcome = self.durable.sighting(
                job.robot_a, job.robot_b, job.stamp_s, T_camA_bodyB, T_bodyB_camB
            )
            if outcome is None:
                return None  # within rendezvous.sighting_period_s of the pair's last request
            merge, message = outcome
        else:
            merge, message = self.durable.request_rendezvous(
                job.robot_a, job.robot_b, job.stamp_s, T_camA_bodyB, T_bodyB_camB
            )
        log.info("rendezvous request robot_%d / robot_%d: %s", job.robot_a, job.robot_b, message)
        if job.reply is not None:
            job.reply.set_result((merge, message))
        return [merge] if merge is not None else []

    def _global_ba(self, job: GlobalBaJob) -> None:
        try:
            r = self.durable.global_bundle_adjustment(job.robot_id)
            result = r, (
                f"{r.keyframes} keyframes, {r.points} points: "
                f"reprojection RMS {r.rms_before:.2f} -> {r.rms_after:.2f} px"
            )
        except GlobalBaError as exc:  # the core logged a run; a refusal is logged here
            result = None, str(exc)
            log.warning("global BA: %s", exc)
        job.reply.set_result(result)

    def _relocalize(self, job: RelocalizeJob) -> None:
        """A lost robot's view -> the team's local map there (see
        :mod:`coop_slam.team.assisted_relocalization`)."""
        cfg, server = self.cfg.assisted_relocalization, self.server
        local, message, pending = None, "assisted relocalization is off", None
        try:
            if cfg.enabled:
                segment = server.segments.segment_of(server.current_map(job.robot_id))
                pull = self.durable.pull
                if segment != job.map_segment:
                    message = (
                        f"robot {job.robot_id} asks in map segment {job.map_segment}, the "
                        f"server holds segment {segment} as its newest"
                    )
                elif pull is not None and (  # the place's keyframe may be a signature only
                    pending := pull.ask_for_view(job.robot_id, job.bow, self.clock())
                ):
                    message = (
                        f"asked robot {pending[0]} for keyframe {pending[1]}, the best match of "
                        "its view (low-bandwidth mode): ask again"
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
        except Exception as exc:  # noqa: BLE001 -- the worker must live on
            log.error("relocalization failed (%s: %s)", type(exc).__name__, exc)
            local, message = None, f"server error: {exc}"
        log.info("relocalization for robot %d: %s", job.robot_id, message)
        job.reply.set_result((local, message, pending is not None))

    def _map_file(self, job: MapFileJob) -> None:
        """Save the team map, or load a saved one as the starting map."""
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
                store = self.durable.store
                self.durable.close()
                if store is not None:
                    remove_map_file(store.path)  # nothing taken yet: the file starts again
                self.durable = self._open_map(False, job.path)
                # A new run for the clients: what the old one received and had not stored is
                # gone, so their receipts no longer count.
                self.server_session = new_session()
                self.start()
                result = True, f"loaded {job.path}: robots {self.durable.robots}", job.path
        except MapStoreError as exc:
            result = False, str(exc), ""
        (log.info if result[0] else log.warning)("%s", result[1])
        job.reply.set_result(result)

    # --- what the worker says ---------------------------------------------------------------------
    def _publish_requests(self) -> None:
        """Low-bandwidth mode: ask robots for the whole keyframes the pull planner wants."""
        pull = self.durable.pull
        if pull is None:
            return
        for robot, ids in pull.take_requests().items():
            if robot not in self.durable.robots:
                continue
            self._request_count += 1
            log.info(
                "asking robot %d for whole keyframes %s (their place signatures matched)",
                robot,
                sorted(ids),
            )
            self.out.request(
                KeyframeRequest(
                    header=Header(stamp=Stamp.from_sec(time.time())),
                    robot_id=robot,
                    request=self._request_count,
                    keyframe_ids=sorted(ids),
                )
            )

    def _merge_event(self, m, now_s: float) -> TeamEvent:
        """A merge, stamped when it happened: the newest input's time (in low-bandwidth mode a
        pulled keyframe may be much older than the merge)."""
        robot_of = self.server.robot_of
        return TeamEvent(
            type=m.type,
            robot_a=robot_of(m.map_a),
            robot_b=robot_of(m.map_b),
            keyframe_a=m.keyframe_a,
            keyframe_b=m.keyframe_b,
            T_mapA_mapB=m.T_mapA_mapB,
            T_camA_camB=m.T_camA_camB,
            inliers=m.inliers,
            residual_px=m.residual_px,
            scale=m.scale,
            group=sorted({robot_of(r) for r in m.group}),
            stamp_s=max(m.stamp_s, now_s),
        )

    def _publish_constraints(self, stamp_s: float) -> None:
        """Constraints accepted inside a group since the last call, as events of type ``link``
        (two robots) or ``loop`` (one robot); the core logged each."""
        server = self.server
        new = server.constraints[self._constraints_published :]
        self._constraints_published += len(new)
        for c in new:
            (ra, ka), (rb, kb) = c.key_a, c.key_b
            robot_a, robot_b = server.robot_of(ra), server.robot_of(rb)
            self.out.event(
                TeamEvent(
                    type=TYPE_LOOP if robot_a == robot_b else TYPE_LINK,
                    robot_a=robot_a,
                    robot_b=robot_b,
                    keyframe_a=ka,
                    keyframe_b=kb,
                    T_mapA_mapB=np.linalg.inv(server.T_group_map(ra)) @ server.T_group_map(rb),
                    T_camA_camB=c.T_camA_camB,
                    inliers=c.inliers,
                    residual_px=c.residual_px,
                    scale=1.0,
                    group=sorted({server.robot_of(r) for r in server.groups.members(ra)}),
                    stamp_s=stamp_s,
                )
            )

    def _publish_tf(self, stamp_s: float) -> None:
        server, out = self.server, []
        for r in self.durable.robots:
            m = server.current_map(r)  # the map segment the client works in now
            out.append(
                RobotCorrection(
                    robot_id=r,
                    merged=server.in_world(m),
                    T_group_map=server.T_group_map(m),
                    keyframe_poses=server.pose_corrections(m),  # in the client's own units
                    map_scale=server.map_scale(m),
                    metric=server.is_metric(m),
                )
            )
        self.out.corrections(out, stamp_s)

    def _publish_map(self, stamp_s: float) -> None:
        """The team map: the view now, the stitched cloud from the map builder. While the builder
        is busy the map stays due: the worker hands over a newer state when it is free."""
        if self.map_builder.busy:
            self._map_dirty = True  # shown when the builder is free (idle: within 0.5 s)
            return
        self._map_dirty = self._merge_unshown = False
        if not self.out.wants_team_map:
            return
        bodies = {r: (d.T_base_cam, d.body_size_m) for r, d in self.sightings.descriptions.items()}
        cloud, dense = self.server.team_cloud_job(), self.server.dense_map_job(bodies)

        def build():
            # The dense map and grid first, out as soon as built: a planner waits for the grid,
            # and fusing the sparse cloud of a large team takes longer than they do.
            self._dense_out(dense, stamp_s)
            return cloud()

        self.map_builder.submit(build, stamp_s)
        self.out.team_map(self._team_map_view(), stamp_s)

    def _dense_out(self, job, stamp_s: float) -> None:
        """In the map builder's thread: the dense map and grid of ``job`` (None: none) go out; a
        build or publish that fails is said and costs the team its dense map this time, not its
        stitched cloud."""
        if job is None:
            return
        try:
            self.out.dense_map(job(), stamp_s)
        except Exception as exc:  # noqa: BLE001 -- the sparse cloud must still go out
            log.error("team map: the dense map failed (%s: %s)", type(exc).__name__, exc)

    def _built(self, cloud: tuple, stamp_s: float) -> None:
        """In the map builder's thread: the stitched cloud goes out."""
        self.out.cloud(cloud, stamp_s)

    def _team_map_view(self) -> TeamMapView:
        server = self.server
        robot_paths = {}
        for r in self.durable.robots:
            poses = server.robot_keyframes(r)
            if not poses:
                continue
            m = server.current_map(r)
            root = server.robot_of(server.groups.root(m))
            robot_paths[r] = ("world" if server.in_world(m) else f"robot_{root}/map", poses)
        paths, edges = server.team_view()
        maps = [
            MapLabel(
                map_id=mid,
                robot_id=server.robot_of(mid),
                path_xyz=np.asarray(pos),
                merged=server.in_world(mid),
                segment=None if mid == server.robot_of(mid) else server.segments.segment_of(mid),
                metric=server.is_metric(mid),
            )
            for mid, pos in paths.items()
        ]
        return TeamMapView(robot_paths, maps, edges)

    def _publish_stats(self, idle: bool = False) -> None:
        """``idle``: no job waits, no global BA is due, no keyframe asked for is awaited and the
        team map shown is the latest."""
        self.out.stats(self.stats(idle))

    def stats(self, idle: bool = False) -> dict:
        server, durable = self.server, self.durable
        ms, opt = server.keyframe_ms, server.optimize_ms
        robots = durable.robots
        return {
            "keyframes": len(ms),
            "ms_per_keyframe_mean": sum(ms) / len(ms) if ms else None,
            "optimize_ms_mean": sum(opt) / len(opt) if opt else None,
            "merges": len(server.merges),
            "groups": [list(g) for g in server.robot_groups()],
            "loops": sum(c.type == TYPE_LOOP for c in server.constraints),
            "links": sum(c.type != TYPE_LOOP for c in server.constraints),
            "refused_constraints": server.rejected_constraints,
            "global_ba_runs": len(server.global_ba_runs),
            "verifications": server.verifications,
            "rejected": self.rejected,
            "duplicates": self.duplicates,
            "keyframes_stored": {str(r): n for r, n in durable.keyframes_stored().items()},
            "pull": durable.pull.stats() if durable.pull is not None else None,
            "metric": {str(r): server.is_metric(server.current_map(r)) for r in robots},
            "map_scale": {str(r): server.map_scale(server.current_map(r)) for r in robots},
            "map_file": durable.store.path if durable.store is not None else None,
            # Robot clock minus the server's [s], low by the smallest transit time
            "clock_offset_s": {str(r): o for r, o in self.clocks.said().items()},
            "idle": idle,
        }
