"""``scripts/bench --only server_scale`` (issue #26): does the server keep up with a team of 8?

The keyframe streams of a team (a recorded demo run's, or synthesised from the synthetic ``multi``
world with 8 robots) are replayed into the server core at their real rate (or ``rate`` times it):
a feeder puts each message into a queue when it arrived, and ONE consumer takes them in order and
does what the server node's worker does for a keyframe message (the durable server with a map file,
then the core work behind its TF, correction and team-map publishing), so the queue grows exactly
when the node would fall behind. Reported: server time per message, the backlog over time (and
whether it grows), merge latency, and the full optimization of the final team graph and of a
1,000-keyframe one. Figures are printed, never asserted; a picture of the backlog and of the time
per message is written next to the bench output.

Synthesising the default streams runs the clients' visual odometry offline over 8 x 90 s of
rendered frames, one robot after the other on one core (some 15-20 minutes on the 2-core machine,
plus 5 to render the world when it is not cached yet): the result is cached under
``~/.cache/coop_slam/bench/``, so later runs start replaying at once.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
import pickle
import queue
import sys
import tempfile
import threading
import time
from typing import Callable, Iterator, NamedTuple

import numpy as np

from ..errors import CoopSlamError
from ..keyframe_record import (
    ACTION_NEW,
    ACTION_REMOVE,
    ACTION_UPDATE,
    STATIC_ARRAYS,
    KeyframeError,
    KeyframeRecord,
    complete_update,
    decode_depths,
    decode_uv,
    encode_depths,
    encode_uv,
    patch_of,
    shared_descriptors,
)
from ..team.map_builder import TeamMapBuilder
from ..team.publish_cadence import PublishCadence, PublishCadenceConfig

Figure = tuple[str, float, str]
# Bump when what the synthesised streams hold changes (client behaviour, record layout): the cache
# key has it, so an old cache is not replayed as if it were current.
STREAM_VERSION = "3"
DEFAULT_SCENARIO, DEFAULT_ROBOTS = "multi", 8
SESSION = 1  # the synthesised clients' delivery session (one start each, sequences from 1)
_REPO = os.path.normpath(
    os.path.join(os.path.dirname(os.path.realpath(__file__)), "..", "..", "..")
)
CONFIG_DIR = os.path.join(_REPO, "config")
# The dtypes of the KeyFrame message's arrays: a record crosses the wire as these.
_WIRE_DTYPES = {
    "keypoints": np.float32,
    "octaves": np.uint8,
    "descriptors": np.uint8,
    "depths_m": np.float32,
    "map_point_ids": np.uint32,
    "map_points": np.float32,
    "covisible_ids": np.uint32,
    "covisible_weights": np.uint16,
}


def _log(text: str) -> None:
    print(f"[server_scale] {text}", file=sys.stderr, flush=True)


# --- the streams ----------------------------------------------------------------------------------
@dataclasses.dataclass
class NeedsStored:
    """A message completed from keyframes the server holds (an update sent without what the
    keyframe saw, ``KeyFrame.delta``, or a keyframe whose descriptors are other keyframes'): the
    server completes it when it takes it. ``complete(stored, known_robots)``, ``stored(keyframe
    id)`` the robot's keyframe of that map segment as the server holds it then (None: not held),
    raises CoopSlamError when it cannot."""

    robot_id: int
    map_segment: int
    keyframe_id: int
    stamp_s: float
    complete: Callable[[Callable[[int], KeyframeRecord | None], set], KeyframeRecord]
    action: int = ACTION_UPDATE


class Arrival(NamedTuple):
    """One keyframe message of a robot's stream."""

    t_s: float  # arrival on the stream's clock [s] (bag receive time or frame stamp)
    robot_id: int
    item: KeyframeRecord | NeedsStored
    session: int  # delivery (see coop_slam.delivery)
    sequence: int


def message_kind(item: KeyframeRecord | NeedsStored) -> str:
    if isinstance(item, NeedsStored):
        return "new" if item.action == ACTION_NEW else "update"
    return {ACTION_NEW: "new", ACTION_UPDATE: "update", ACTION_REMOVE: "remove"}[item.action]


def header_stamp_s(item: KeyframeRecord | NeedsStored) -> float:
    """The message's header stamp, as the node reads it (a removal's is 0)."""
    return float(item.stamp_s)


def complete_stripped(
    sent: KeyframeRecord,
    stored: Callable[[int], KeyframeRecord | None],
    known_robots: set,
    patched: np.ndarray | None = None,
    moves: tuple[np.ndarray, np.ndarray] | None = None,
) -> KeyframeRecord:
    """A delta update (``sent``, its static arrays empty, its observations a patch when
    ``patched`` is given) completed as ``keyframe_from_msg`` does it: from the keyframe as the
    server holds it (``stored``)."""
    base = stored(sent.keyframe_id)
    if base is None:
        raise KeyframeError(
            f"keyframe {sent.keyframe_id} of robot {sent.robot_id}: a delta update of a keyframe "
            "the server does not hold"
        )
    return complete_update(sent, base, patched, moves).validate(known_robots)


def complete_refs(
    sent: KeyframeRecord,
    refs: tuple[np.ndarray, np.ndarray],
    stored: Callable[[int], KeyframeRecord | None],
    known_robots: set,
) -> KeyframeRecord:
    """A full message whose descriptors partly come from keyframes the server holds (``refs``,
    see :class:`coop_slam.vo.outbox.Outgoing`), completed as ``keyframe_from_msg`` does it."""
    ref_keyframes, per_keypoint = refs
    descriptors = shared_descriptors(
        sent.map_point_ids,
        sent.descriptors[np.asarray(per_keypoint) == 0],
        per_keypoint,
        ref_keyframes,
        stored,
        f"keyframe {sent.keyframe_id} of robot {sent.robot_id}",
    )
    return dataclasses.replace(sent, descriptors=descriptors).validate(known_robots)


def as_sent(
    rec: KeyframeRecord,
    delta: bool,
    patched: np.ndarray | None = None,
    refs: tuple[np.ndarray, np.ndarray] | None = None,
    moves: tuple[np.ndarray, np.ndarray] | None = None,
) -> KeyframeRecord | NeedsStored:
    """The record as the server gets it from the wire: arrays in the message's dtypes, keypoints
    without their size and angle, keypoints and depths in their compact encodings, for a delta
    update without what the keyframe saw (and with only the ``patched`` keypoints' observations
    and ``moves``, when given), and with ``refs`` with the descriptors of other keyframes the
    server holds."""
    arrays = {k: np.asarray(getattr(rec, k), dtype) for k, dtype in _WIRE_DTYPES.items()}
    keypoints = arrays["keypoints"].reshape(-1, 4).copy()
    keypoints[:, 2], keypoints[:, 3] = 0.0, -1.0  # not sent
    coded = encode_uv(keypoints[:, :2], rec.camera.width, rec.camera.height)
    if coded is not None:  # as keyframe_to_msg sends them
        keypoints[:, :2] = decode_uv(*coded)
    half = encode_depths(arrays["depths_m"])
    if half is not None:
        arrays["depths_m"] = decode_depths(half)
    arrays["keypoints"] = keypoints
    arrays["descriptors"] = arrays["descriptors"].reshape(-1, 32)
    arrays["map_points"] = arrays["map_points"].reshape(-1, 3)
    rec = dataclasses.replace(rec, **arrays)
    if not delta:
        if refs is None:
            return rec
        return NeedsStored(
            rec.robot_id,
            rec.map_segment,
            rec.keyframe_id,
            rec.stamp_s,
            functools.partial(complete_refs, rec, refs),
            rec.action,
        )
    empty = {k: np.zeros((0,) + getattr(rec, k).shape[1:], _WIRE_DTYPES[k]) for k in STATIC_ARRAYS}
    if patched is not None:
        empty["map_point_ids"], empty["map_points"] = patch_of(rec, patched)
    stripped = dataclasses.replace(rec, **empty)
    return NeedsStored(
        rec.robot_id,
        rec.map_segment,
        rec.keyframe_id,
        rec.stamp_s,
        functools.partial(complete_stripped, stripped, patched=patched, moves=moves),
    )


class ClientSender:
    """What a client node sends for its odometry's events (``ClientNode._publish_events``, first
    start: keyframe ids and map segments as the odometry gives them): a record per keyframe event,
    an update without what the keyframe saw when that is unchanged since it went as new, each
    message numbered in the client's session."""

    def __init__(self, robot_id: int, camera, T_base_cam: np.ndarray, uplink=None):
        from ..vo.outbox import Uplink

        self.robot_id, self.camera, self.T_base_cam = robot_id, camera, T_base_cam
        self.uplink = Uplink(uplink)
        self.sequence = 0
        self.new_keyframes = 0

    def send(self, events, t_s: float, last: bool = False) -> list[Arrival]:
        """The messages that go at data time ``t_s`` for ``events`` (and what the uplink held
        before); ``last``: everything it holds goes too."""
        from ..vo.outbox import event_record
        from ..vo.types import EVENT_NEW_SEGMENT, KEYFRAME_ACTIONS

        going = []
        for ev in events:
            if ev.kind == EVENT_NEW_SEGMENT:  # the old map's keyframes go first
                going += self.uplink.flush()
            if ev.kind not in KEYFRAME_ACTIONS:  # warnings, new segments: nothing sent
                continue
            rec = event_record(ev, self.robot_id, self.camera, self.T_base_cam)
            going += self.uplink.offer(rec, t_s)
        going += self.uplink.flush() if last else self.uplink.due(t_s)
        out = []
        for rec, how in going:
            self.new_keyframes += rec.action == ACTION_NEW
            self.sequence += 1
            out.append(
                Arrival(
                    t_s,
                    self.robot_id,
                    as_sent(rec, how.delta, how.patched, how.refs, how.moves),
                    SESSION,
                    self.sequence,
                )
            )
        return out


def client_vo_config(T_base_cam: np.ndarray, ground_robot: bool):
    """The clients' odometry configuration (config/client.yaml, as client.launch sets it), with
    local mapping in the calling thread so that the synthesised streams are deterministic."""
    from ..config import load_yaml_config
    from ..vo.config import VoConfig

    cfg = load_yaml_config(VoConfig, os.path.join(CONFIG_DIR, "client.yaml"), section="vo")
    cfg = dataclasses.replace(cfg, threaded=False, planar_motion=ground_robot)
    if cfg.planar_motion:  # the floor normal (base z) as the camera sees it, as the client node
        cfg.planar_up_cam = (T_base_cam[:3, :3].T @ [0.0, 0.0, 1.0]).tolist()
    return cfg


def robot_stream(robot_id: int, seq, cfg, T_base_cam: np.ndarray, label: str = "") -> list[Arrival]:
    """One robot's keyframe messages: its odometry run offline over the sequence, every event
    arriving at the stamp of the frame it appeared at."""
    from ..config import load_yaml_config
    from ..vo.outbox import UplinkConfig
    from ..vo.pipeline import VisualOdometry

    uplink = load_yaml_config(UplinkConfig, os.path.join(CONFIG_DIR, "client.yaml"), "uplink")
    sender = ClientSender(robot_id, seq.camera, T_base_cam, uplink)
    vo = VisualOdometry(cfg, seq.camera)
    out: list[Arrival] = []
    t0, n = time.perf_counter(), len(seq)
    try:
        for i, frame in enumerate(seq.frames):
            if seq.camera.sensor == "mono":
                image, second = seq.load_color(frame), None
            else:
                image, second = seq.load_frame(frame)
            vo.track(frame.stamp_s, image, second)
            out += sender.send(vo.drain_events(), frame.stamp_s)
            if (i + 1) % 150 == 0 or i + 1 == n:
                _log(
                    f"{label}frame {i + 1}/{n}, {sender.new_keyframes} keyframes, "
                    f"{len(out)} messages, {time.perf_counter() - t0:.0f} s"
                )
        vo.flush()
        out += sender.send(vo.drain_events(), seq.frames[-1].stamp_s if n else 0.0, last=True)
    finally:
        vo.close()
    return out


def _cache_path(scenario: str, robots: int) -> str:
    """Keyed by the stream version, scenario, robots and the clients' configuration file."""
    root = os.environ.get("COOP_SLAM_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "coop_slam"
    )
    with open(os.path.join(CONFIG_DIR, "client.yaml"), "rb") as fh:
        config_digest = hashlib.sha256(fh.read()).hexdigest()[:10]
    name = f"server_scale-v{STREAM_VERSION}-{scenario}-{robots}robots-{config_digest}.pkl"
    return os.path.join(root, "bench", name)


def synthesized_streams(
    scenario: str = DEFAULT_SCENARIO, robots: int = DEFAULT_ROBOTS
) -> list[Arrival]:
    """Every robot's keyframe messages of the synthetic ``scenario`` world, in arrival order
    (cached; see :func:`_cache_path`)."""
    path = _cache_path(scenario, robots)
    if os.path.isfile(path):
        with open(path, "rb") as fh:
            arrivals = pickle.load(fh)
        _log(f"streams from the cache {path}")
        return arrivals
    import cv2

    from ..datasets.synthetic import read_synthetic
    from ..synthetic.generate import generate
    from ..synthetic.scenarios import SCENARIOS

    _log(f"synthesising the {robots} robots' streams of '{scenario}' (minutes; cached after)")

    def rendered(done: int, total: int) -> None:
        if done % 1000 == 0 or done == total:
            _log(f"rendering the world: frame {done}/{total}")

    world = read_synthetic(generate(scenario, robots=robots, progress=rendered))
    cfg = client_vo_config(world.T_base_cam, not SCENARIOS[scenario].hand_held)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # one core, as one client has: the machine is shared
    arrivals: list[Arrival] = []
    try:
        for k, robot in enumerate(world.robot_ids, 1):
            label = f"robot {k} of {len(world.robot_ids)}: "
            arrivals += robot_stream(robot, world.sequences[robot], cfg, world.T_base_cam, label)
    finally:
        cv2.setNumThreads(threads)
    # Stable: a robot's messages of one frame stay in their sending order.
    arrivals.sort(key=lambda a: (a.t_s, a.robot_id, a.sequence))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path + ".tmp", "wb") as fh:
        pickle.dump(arrivals, fh, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(path + ".tmp", path)
    _log(f"streams cached in {path}")
    return arrivals


def _complete_msg(
    msg, stored: Callable[[int], KeyframeRecord | None], known_robots: set
) -> KeyframeRecord:
    from ..ros.convert import keyframe_from_msg

    return keyframe_from_msg(msg, known_robots=known_robots, stored=stored)


def run_streams(run_dir: str, word_idf: np.ndarray | None = None) -> tuple[list[Arrival], dict]:
    """The keyframe messages of a recorded demo run (``RUN/run.bag``, ``RUN/run.json``), arriving
    at the bag's receive times, and the run's info. Marker sightings are not part of the streams.
    Messages the node would refuse on arrival are left out (and counted on stderr), and so are
    messages a client sent again (same session and sequence): resending answers a server that
    was slow to acknowledge in that run, which a replay without acknowledgements cannot model.
    ``word_idf``: the vocabulary's ``word_weights`` (for low-bandwidth runs' signatures)."""
    import json

    import rosbag

    from ..ros.convert import MessageError, keyframe_from_msg, needs_stored, unpacked

    with open(os.path.join(run_dir, "run.json"), encoding="utf-8") as fh:
        info = json.load(fh)
    bag_path = os.path.join(run_dir, "run.bag")
    if not os.path.isfile(bag_path):
        raise CoopSlamError(f"{bag_path} not found: the run was not recorded")
    robots = set(info["robot_ids"])
    topics = [f"/robot_{r}/keyframes" for r in sorted(robots)]
    arrivals, refused, again = [], 0, 0
    seen: set[tuple[int, int, int]] = set()  # (robot, session, sequence) of sequenced messages
    with rosbag.Bag(bag_path) as bag:
        for _, msg, t in bag.read_messages(topics=topics):
            session, sequence = getattr(msg, "session", 0), getattr(msg, "sequence", 0)
            if session:
                if (msg.robot_id, session, sequence) in seen:
                    again += 1
                    continue
                seen.add((msg.robot_id, session, sequence))
            try:
                msg = unpacked(msg)
                if needs_stored(msg):  # completed when taken, as the node does
                    item = NeedsStored(
                        msg.robot_id,
                        msg.map_segment,
                        msg.keyframe_id,
                        msg.header.stamp.to_sec(),
                        functools.partial(_complete_msg, msg),
                        msg.action,
                    )
                else:
                    item = keyframe_from_msg(msg, known_robots=robots, word_idf=word_idf)
            except MessageError:
                refused += 1
                continue
            arrivals.append(Arrival(t.to_sec(), msg.robot_id, item, session, sequence))
    if refused or again:
        _log(f"left out: {refused} keyframe messages refused on arrival, {again} sent again")
    return arrivals, info


# --- the replay -----------------------------------------------------------------------------------
class NodeWork:
    """The server node's worker without ROS (``ServerNode._do`` for a keyframe job, and its idle
    branch): the durable server takes the message; then the core work behind the node's
    publishing -- the robots' corrections and TF after a merge or an optimization, the team map
    (paths and merge edges here, the cloud in the map builder's thread,
    :mod:`coop_slam.team.map_builder`) when its cadence allows
    (:mod:`coop_slam.team.publish_cadence`), and when the queue has been empty for 0.5 s the
    global BA a merge left due, then both again. Building and serialising the ROS messages is left
    out. ``close()`` stops the builder."""

    def __init__(self, durable, cadence: PublishCadenceConfig | None = None):
        self.durable = durable
        self.cadence = PublishCadence(cadence)
        self.builder = TeamMapBuilder(lambda cloud, stamp_s: None, self.cadence)
        self.rejected = 0  # messages the server refused
        self.ack: tuple | None = None  # the last acknowledgement's content
        self._last_stamp_s, self._dirty, self._merge_unshown = 0.0, False, False

    def close(self) -> None:
        self.builder.close(timeout_s=None)

    @property
    def server(self):
        return self.durable.server

    def _pending(self, delta: NeedsStored):
        from ..team.durable import PendingKeyframe

        server = self.server
        return PendingKeyframe(
            delta.robot_id,
            lambda: delta.complete(
                functools.partial(server.stored_record, delta.robot_id, delta.map_segment),
                server.known_robots,
            ),
            delta.keyframe_id,
        )

    def keyframe(self, a: Arrival) -> tuple[list, float]:
        """One message through the worker: (merges it made, wall time they were decided)."""
        rec = self._pending(a.item) if isinstance(a.item, NeedsStored) else a.item
        try:
            taken = self.durable.add_keyframe(rec, a.session, a.sequence)
        except CoopSlamError:
            self.rejected += 1
            return [], time.perf_counter()
        finally:  # what the acknowledgement carries (the node sends one for every message)
            if a.robot_id in self.durable.robots:
                self.ack = (self.durable.acknowledged(a.robot_id), self.durable.last_ids())
        decided = time.perf_counter()
        self.rejected += len(taken.rejected or [])
        if not taken.taken:
            return [], decided
        merges = taken.merges
        # A late message must not move the map back in time (the node's rule).
        stamp_s = max(header_stamp_s(a.item), self._last_stamp_s)
        if merges or self.server.map_moved:
            self._corrections()
        self._dirty, self._last_stamp_s = True, stamp_s
        self._merge_unshown |= bool(merges)
        if self.cadence.due(stamp_s, self._merge_unshown, time.monotonic()):
            self._team_map()
        return merges, decided

    def idle(self) -> bool:
        """The queue drained: the global BA a merge left due, then the final state of the map
        (when it changed, and once the builder is free); True if work done."""
        ran = self.durable.run_due_global_ba()
        if ran:
            self._dirty = True
        if not self._dirty or self.builder.busy:
            return ran
        self._corrections()
        self._team_map()
        return True

    def _corrections(self) -> dict:
        """``ServerNode._publish_tf``: robot -> (T_group_map, merged, metric, corrected keyframe
        poses in the robot's own units), what the TF and correction messages carry."""
        server, out = self.server, {}
        for r in self.durable.robots:
            m = server.current_map(r)
            corrected = server.pose_corrections(m)
            out[r] = (server.T_group_map(m), server.in_world(m), server.is_metric(m), corrected)
        return out

    def _team_map(self) -> tuple | None:
        """``ServerNode._publish_map``: the stitched cloud handed to the builder, every robot's
        path (and the frame it is drawn in), the merge edges; None while the builder is busy."""
        if self.builder.busy:
            return None
        self._dirty = self._merge_unshown = False
        server = self.server
        self.builder.submit(server.team_cloud_job(), self._last_stamp_s)
        paths = {}
        for r in self.durable.robots:
            poses = server.robot_keyframes(r)
            if poses:
                m = server.current_map(r)
                root = server.robot_of(server.groups.root(m))
                paths[r] = (server.in_world(m), root, poses)
        return paths, server.team_view()


@dataclasses.dataclass
class Processed:
    """One message through the consumer; wall times [s] since the replay started."""

    robot_id: int
    kind: str  # new, update, remove
    arrive_s: float  # put into the queue
    start_s: float  # taken by the consumer
    end_s: float  # done, publishing work included
    merges: int


@dataclasses.dataclass
class ScaleRun:
    """What a replay measured."""

    messages: list[Processed]  # in processing order (= arrival order: one FIFO queue)
    merge_latencies_s: list[float]  # per merge: decided minus its message's arrival [wall s]
    merge_own_s: list[float]  # the part of it the message itself took (no queue): decided - start
    merge_times_s: list[float]  # wall time each merge was decided
    idle_work: list[tuple[float, float]]  # (start, end) of the idle publishing work [wall s]
    stream_s: float  # first to last arrival on the stream's clock
    rate: float
    rejected: int

    @property
    def robots(self) -> int:
        return len({m.robot_id for m in self.messages})

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            k: np.array([getattr(m, k) for m in self.messages], float)
            for k in ("arrive_s", "start_s", "end_s")
        }


def replay_at_rate(
    arrivals: list[Arrival], work: NodeWork, rate: float = 1.0, idle_timeout_s: float = 0.5
) -> ScaleRun:
    """Feed ``arrivals`` at ``rate`` x their real rate (a feeder thread puts each into a queue at
    t0 + t / rate) to one consumer (this thread) doing the node worker's ``work``."""
    if rate <= 0:
        raise CoopSlamError(f"rate must be > 0, got {rate}")
    q: queue.Queue = queue.Queue()
    first_s = arrivals[0].t_s if arrivals else 0.0
    t0 = time.perf_counter()

    def feed() -> None:
        for i, a in enumerate(arrivals):
            due = (a.t_s - first_s) / rate
            wait = t0 + due - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            # Arrived when due, even if put later: the consumer's native calls (GTSAM) may hold
            # the GIL for seconds, as they would stall the node's receiving threads while the
            # messages wait in its sockets.
            q.put((i, due))
        q.put(None)

    feeder = threading.Thread(target=feed, name="server_scale feeder", daemon=True)
    feeder.start()
    messages, latencies, merge_own, merge_times, idle = [], [], [], [], []
    while True:
        try:
            got = q.get(timeout=idle_timeout_s)
        except queue.Empty:
            s = time.perf_counter() - t0
            if work.idle():
                idle.append((s, time.perf_counter() - t0))
            continue
        if got is None:
            break
        i, arrive = got
        a = arrivals[i]
        start = time.perf_counter() - t0
        merges, decided = work.keyframe(a)
        end = time.perf_counter() - t0
        for _ in merges:
            latencies.append(decided - t0 - arrive)
            merge_own.append(decided - t0 - start)
            merge_times.append(decided - t0)
        messages.append(
            Processed(a.robot_id, message_kind(a.item), arrive, start, end, len(merges))
        )
    feeder.join()
    return ScaleRun(
        messages,
        latencies,
        merge_own,
        merge_times,
        idle,
        (arrivals[-1].t_s - first_s) if arrivals else 0.0,
        rate,
        work.rejected,
    )


# --- figures --------------------------------------------------------------------------------------
def backlog_at(run: ScaleRun, t_s) -> np.ndarray:
    """Messages arrived and not yet processed (the one in process included) at wall times t_s."""
    arr = run.arrays()
    t_s = np.asarray(t_s, float)
    arrived = np.searchsorted(np.sort(arr["arrive_s"]), t_s, side="right")
    done = np.searchsorted(np.sort(arr["end_s"]), t_s, side="right")
    return arrived - done


def backlog_growth_per_s(run: ScaleRun, samples: int = 400) -> float:
    """Slope [messages per wall s] of a line fit of the backlog over the second half of the
    stream (first to last arrival): ~0 keeps up, > 0 falls behind for good."""
    arrive = run.arrays()["arrive_s"]
    if len(arrive) < 2 or arrive[-1] <= arrive[0]:
        return 0.0
    t = np.linspace((arrive[0] + arrive[-1]) / 2, arrive[-1], samples)
    return float(np.polyfit(t, backlog_at(run, t), 1)[0])


def busy_share(run: ScaleRun, t_edges: np.ndarray) -> np.ndarray:
    """Share of each window [t_edges[k], t_edges[k+1]) the consumer spent working."""
    spans = [(m.start_s, m.end_s) for m in run.messages] + list(run.idle_work)
    busy = np.zeros(len(t_edges) - 1)
    for s, e in spans:
        busy += np.clip(np.minimum(t_edges[1:], e) - np.maximum(t_edges[:-1], s), 0.0, None)
    return busy / np.diff(t_edges)


def scale_figures(run: ScaleRun) -> Iterator[Figure]:
    """The replay's figures (names ``server_scale_*``)."""
    arr = run.arrays()
    ms = 1e3 * (arr["end_s"] - arr["start_s"])
    wait = arr["start_s"] - arr["arrive_s"]
    kinds = np.array([m.kind for m in run.messages])
    yield ("server_scale_robots", float(run.robots), "robots")
    yield ("server_scale_keyframe_messages", float(len(run.messages)), "messages")
    for kind in ("new", "update", "remove"):
        yield (f"server_scale_{kind}_messages", float(np.count_nonzero(kinds == kind)), "messages")
    yield ("server_scale_rejected_messages", float(run.rejected), "messages")
    yield ("server_scale_stream_duration", run.stream_s, "s")
    yield ("server_scale_replay_rate", run.rate, "x")
    if not len(ms):
        return
    stream_wall_s = max(arr["arrive_s"][-1] - arr["arrive_s"][0], 1e-9)
    yield ("server_scale_offered_messages_per_s", len(ms) / stream_wall_s, "1/s")
    span = max(arr["end_s"][-1] - arr["arrive_s"][0], 1e-9)
    yield ("server_scale_ms_per_message_mean", float(np.mean(ms)), "ms")
    yield ("server_scale_ms_per_message_p95", float(np.percentile(ms, 95)), "ms")
    yield ("server_scale_ms_per_message_max", float(np.max(ms)), "ms")
    for kind in ("new", "update"):
        sel = ms[kinds == kind]
        if len(sel):
            yield (f"server_scale_ms_per_{kind}_mean", float(np.mean(sel)), "ms")
            yield (f"server_scale_ms_per_{kind}_p95", float(np.percentile(sel, 95)), "ms")
    idle = sum(e - s for s, e in run.idle_work)
    yield ("server_scale_worker_busy", 100.0 * (float(np.sum(ms)) / 1e3 + idle) / span, "%")
    yield ("server_scale_queue_wait_mean", float(np.mean(wait)), "s")
    yield ("server_scale_queue_wait_p95", float(np.percentile(wait, 95)), "s")
    yield ("server_scale_backlog_max", float(np.max(backlog_at(run, arr["arrive_s"]))), "messages")
    # Still waiting (or in process) when the stream's last message came: 0 = kept up to the end.
    at_end = int(np.count_nonzero(arr["end_s"][:-1] > arr["arrive_s"][-1]))
    yield ("server_scale_backlog_at_stream_end", float(at_end), "messages")
    yield ("server_scale_backlog_growth", backlog_growth_per_s(run), "messages/s")
    yield (
        "server_scale_drain_after_stream_end",
        float(arr["end_s"][-1] - arr["arrive_s"][-1]),
        "s",
    )
    yield ("server_scale_merges", float(len(run.merge_latencies_s)), "merges")
    if run.merge_latencies_s:
        lat = np.array(run.merge_latencies_s)
        yield ("server_scale_merge_latency_mean", float(np.mean(lat)), "s")
        yield ("server_scale_merge_latency_max", float(np.max(lat)), "s")
        own = np.array(run.merge_own_s)  # the rest of the latency is queueing
        yield ("server_scale_merge_own_time_mean", float(np.mean(own)), "s")
        yield ("server_scale_merge_own_time_max", float(np.max(own)), "s")


def plot_run(run: ScaleRun, path: str, title: str) -> str:
    """Backlog, server time per message and the worker's busy share over the replay's wall time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arr = run.arrays()
    end = float(arr["end_s"][-1]) if len(arr["end_s"]) else 1.0
    t = np.linspace(0.0, end, 2000)
    fig, axes = plt.subplots(3, 1, figsize=(10, 8.5), sharex=True)
    ax = axes[0]
    ax.plot(t, backlog_at(run, t), color="tab:red", lw=1.2, drawstyle="steps-post")
    ax.set_ylabel("backlog [messages]")
    ax.set_ylim(bottom=0)
    ax.set_title(title)
    if len(arr["arrive_s"]):
        ax.axvline(arr["arrive_s"][-1], color="k", ls=":", lw=1, label="last message arrives")
    for axis in axes:
        for k, tm in enumerate(run.merge_times_s):
            label = "merge decided" if k == 0 and axis is ax else None
            axis.axvline(tm, color="tab:green", ls="--", lw=0.8, label=label)
    ax.legend(loc="upper left", fontsize=8)
    ax = axes[1]
    ms = 1e3 * (arr["end_s"] - arr["start_s"])
    kinds = np.array([m.kind for m in run.messages])
    for kind, colour in (("update", "tab:blue"), ("remove", "tab:gray"), ("new", "tab:orange")):
        sel = kinds == kind
        if np.any(sel):
            ax.scatter(
                arr["start_s"][sel], ms[sel], s=5, color=colour, label=f"{kind} ({sel.sum()})"
            )
    ax.set_yscale("log")
    ax.set_ylabel("server time per message [ms]")
    ax.legend(loc="upper left", fontsize=8, markerscale=2)
    ax.grid(True, which="major", alpha=0.3)
    ax = axes[2]
    window_s = float(np.clip(round(end / 30, 1), 0.5, 5.0))  # some 30 bars
    edges = np.append(np.arange(0.0, end, window_s), end)
    share = 100 * busy_share(run, edges)
    ax.bar(edges[:-1], share, width=np.diff(edges), align="edge", color="tab:purple", alpha=0.7)
    ax.axhline(100, color="k", lw=0.8)
    ax.set_ylim(0, 110)
    ax.set_xlim(0, end)
    ax.set_ylabel(f"worker busy [% of {window_s:g} s]")
    ax.set_xlabel("wall time since the replay started [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --- the benchmark --------------------------------------------------------------------------------
def _synthetic_server_config(scenario: str, robot_ids: list[int]):
    from ..synthetic.scenarios import SCENARIOS
    from .replay import _server_config

    info = {"ground_robots": not SCENARIOS[scenario].hand_held, "robot_ids": robot_ids}
    return _server_config(os.path.join(CONFIG_DIR, "server.yaml"), info, {})


def bench_server_scale(
    run_dir: str | None = None, rate: float = 1.0, out_dir: str = "."
) -> Iterator[Figure]:
    """The keyframe streams of a recorded run (``run_dir``) or of the synthetic ``multi`` world
    with 8 robots, replayed into the server at ``rate`` x their real rate."""
    from ..bow import Vocabulary
    from ..bow.training import ensure_default_vocabulary
    from ..team.durable import DurableServer
    from ..team.pose_graph import bench_full_optimization
    from ..team.server import TeamServer
    from .replay import _server_config

    t = time.perf_counter()
    vocab = Vocabulary.load(ensure_default_vocabulary())
    if run_dir:
        arrivals, info = run_streams(run_dir, vocab.word_weights)
        cfg = _server_config(os.path.join(CONFIG_DIR, "server.yaml"), info, {})
        what = f"run {os.path.basename(os.path.normpath(run_dir))}"
    else:
        arrivals = synthesized_streams()
        cfg = _synthetic_server_config(DEFAULT_SCENARIO, sorted({a.robot_id for a in arrivals}))
        what = f"synthetic {DEFAULT_SCENARIO}"
    _log(f"{len(arrivals)} messages ready in {time.perf_counter() - t:.1f} s; replaying")
    with tempfile.TemporaryDirectory() as tmp:
        # The node keeps a map file by default (server.launch map:=): so does the replay.
        durable = DurableServer(
            cfg,
            lambda c: TeamServer(c, vocab),
            os.path.join(tmp, "team_map.db"),
            defer_global_ba=True,  # as the node: when no message waits
        )
        work = NodeWork(durable)
        try:
            t = time.perf_counter()
            run = replay_at_rate(arrivals, work, rate)
            took = time.perf_counter() - t
            _log(f"replay took {took:.1f} s; {work.builder.built} team clouds built")
            yield from scale_figures(run)
            server = durable.server
            yield ("server_scale_final_graph_keyframes", float(len(server.store)), "keyframes")
            t = time.perf_counter()
            server.optimize(full=True)
            full_ms = 1e3 * (time.perf_counter() - t)
            yield ("server_scale_full_optimization_final_graph", full_ms, "ms")
        finally:
            work.close()
            durable.close()
    if run.messages:
        os.makedirs(out_dir or ".", exist_ok=True)
        title = f"server_scale: {what}, {run.robots} robots, {len(run.messages)} messages"
        path = plot_run(
            run, os.path.join(out_dir or ".", "bench_server_scale.png"), f"{title} at {rate:g}x"
        )
        _log(f"picture: {os.path.abspath(path)}")
    yield (
        "server_scale_full_optimization_1000_keyframes",
        bench_full_optimization(1000, 4),
        "ms",
    )
