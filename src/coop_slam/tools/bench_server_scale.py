"""``scripts/bench --only server_scale`` (issue #26): does the server keep up with a team of 8?

The keyframe streams of a team (a recorded demo run's, or synthesised from the synthetic ``multi``
world with 8 robots) are replayed into the server core at their real rate (or ``rate`` times it):
a feeder puts each message into a queue when it arrived, and ONE consumer hands them in order to
the server node's own worker (:class:`coop_slam.team.worker.ServerWorker`, with a map file as the
node keeps one, building the team map as the node does, publishing nothing), so the queue grows
exactly when the node would fall behind. Messages are decoded before the replay starts (the node
decodes them in its receiving threads, not its worker). The synthesised streams come from the
clients' own uplink (:class:`coop_slam.uplink.engine.ClientUplink`). Reported: server time per
message, the backlog over time (and whether it grows), merge latency, and the full optimization
of the final team graph and of a 1,000-keyframe one. Figures are printed, never asserted; a
picture of the backlog and of the time per message is written next to the bench output.

Synthesising the default streams runs the clients' visual odometry offline over 8 x 90 s of
rendered frames, one robot after the other on one core (some 15-20 minutes on the 2-core machine,
plus 5 to render the world when it is not cached yet): the result is cached under
``~/.cache/coop_slam/bench/``, so later runs start replaying at once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pickle
import queue
import sys
import tempfile
import threading
import time
from typing import Iterator, NamedTuple

import numpy as np

from ..errors import CoopSlamError
from ..team.worker import ServerOutputs, ServerWorker
from ..wire.legacy import is_legacy
from ..wire.messages import KIND_DELTA, KIND_KEYFRAME, KIND_REMOVAL, KeyframeMessage
from ..wire.record import ACTION_NEW, ACTION_REMOVE
from .paths import CONFIG_DIR

Figure = tuple[str, float, str]
# Bump when what the synthesised streams hold changes (client behaviour, message layout): the cache
# key has it, so an old cache is not replayed as if it were current.
STREAM_VERSION = "5"  # 5: keyframes carry their depth images (dense map)
DEFAULT_SCENARIO, DEFAULT_ROBOTS = "multi", 8


def _log(text: str) -> None:
    print(f"[server_scale] {text}", file=sys.stderr, flush=True)


# --- the streams ----------------------------------------------------------------------------------
class Arrival(NamedTuple):
    """One keyframe message of a robot's stream (a wire message; a recorded run's older format
    as it was recorded)."""

    t_s: float  # arrival on the stream's clock [s] (bag receive time or frame stamp)
    robot_id: int
    msg: KeyframeMessage


def message_kind(msg) -> str:
    """new, update or remove (the figures' kinds)."""
    if is_legacy(msg):
        return {ACTION_NEW: "new", ACTION_REMOVE: "remove"}.get(msg.action, "update")
    if msg.kind == KIND_REMOVAL:
        return "remove"
    if msg.kind == KIND_DELTA or (msg.kind == KIND_KEYFRAME and msg.keyframe[0].replaces):
        return "update"
    return "new"


def client_vo_config(T_base_cam: np.ndarray, ground_robot: bool):
    """The clients' odometry configuration (config/client.yaml, as client.launch sets it), with
    local mapping in the calling thread so that the synthesised streams are deterministic."""
    from ..config import load_yaml_config, with_values
    from ..vo.config import VoConfig

    cfg = load_yaml_config(VoConfig, os.path.join(CONFIG_DIR, "client.yaml"), section="vo")
    cfg = with_values(cfg, {"threaded": False, "planar": {"enabled": ground_robot}})
    if cfg.planar.enabled:  # the floor normal (base z) as the camera sees it, as the client node
        cfg.planar.up_cam = (T_base_cam[:3, :3].T @ [0.0, 0.0, 1.0]).tolist()
    return cfg


def robot_stream(robot_id: int, seq, cfg, T_base_cam: np.ndarray, label: str = "") -> list[Arrival]:
    """One robot's keyframe messages: its odometry run offline over the sequence and its events
    through the client's own uplink (:class:`coop_slam.uplink.engine.ClientUplink`), every message
    arriving at the stamp of the frame it went at."""
    from ..config import load_yaml_config
    from ..uplink.config import UplinkConfig
    from ..uplink.engine import ClientUplink
    from ..vo.pipeline import VisualOdometry

    uplink_cfg = load_yaml_config(UplinkConfig, os.path.join(CONFIG_DIR, "client.yaml"), "uplink")
    uplink = ClientUplink(robot_id, uplink_cfg, T_base_cam=T_base_cam)
    uplink.camera = seq.camera
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
            step = uplink.events(vo.drain_events(), frame.stamp_s)
            out += [Arrival(frame.stamp_s, robot_id, m) for m in step.messages]
            if (i + 1) % 150 == 0 or i + 1 == n:
                _log(
                    f"{label}frame {i + 1}/{n}, {uplink.keyframes_sent} keyframes, "
                    f"{len(out)} messages, {time.perf_counter() - t0:.0f} s"
                )
        vo.flush()
        last_s = seq.frames[-1].stamp_s if n else 0.0
        out += [Arrival(last_s, robot_id, m) for m in uplink.events(vo.drain_events(), None)[0]]
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
    ground = not SCENARIOS[scenario].hand_held
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # one core, as one client has: the machine is shared
    arrivals: list[Arrival] = []
    try:
        for k, robot in enumerate(world.robot_ids, 1):
            label = f"robot {k} of {len(world.robot_ids)}: "
            mount = world.mount(robot)
            cfg = client_vo_config(mount, ground)
            arrivals += robot_stream(robot, world.sequences[robot], cfg, mount, label)
    finally:
        cv2.setNumThreads(threads)
    # Stable: a robot's messages of one frame stay in their sending order.
    arrivals.sort(key=lambda a: (a.t_s, a.robot_id, a.msg.sequence))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path + ".tmp", "wb") as fh:
        pickle.dump(arrivals, fh, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(path + ".tmp", path)
    _log(f"streams cached in {path}")
    return arrivals


def run_streams(run_dir: str) -> tuple[list[Arrival], dict]:
    """The keyframe messages of a recorded demo run (``RUN/run.bag``, ``RUN/run.json``), arriving
    at the bag's receive times, and the run's info. Marker sightings are not part of the streams.
    Messages a client sent again (same session and sequence) are left out: resending answers a
    server that was slow to acknowledge in that run, which a replay without acknowledgements
    cannot model."""
    import json

    import rosbag

    from ..ros.recorded import KEYFRAME_TOPIC, keyframe_message

    with open(os.path.join(run_dir, "run.json"), encoding="utf-8") as fh:
        info = json.load(fh)
    bag_path = os.path.join(run_dir, "run.bag")
    if not os.path.isfile(bag_path):
        raise CoopSlamError(f"{bag_path} not found: the run was not recorded")
    topics = [KEYFRAME_TOPIC.format(r) for r in sorted(info["robot_ids"])]
    arrivals, again = [], 0
    seen: set[tuple[int, int, int]] = set()  # (robot, session, sequence) of sequenced messages
    with rosbag.Bag(bag_path) as bag:
        for _, msg, t in bag.read_messages(topics=topics):
            session, sequence = getattr(msg, "session", 0), getattr(msg, "sequence", 0)
            if session:
                if (msg.robot_id, session, sequence) in seen:
                    again += 1
                    continue
                seen.add((msg.robot_id, session, sequence))
            arrivals.append(Arrival(t.to_sec(), msg.robot_id, keyframe_message(msg)))
    if again:
        _log(f"left out: {again} keyframe messages sent again")
    return arrivals, info


# --- the replay -----------------------------------------------------------------------------------
class BenchOutputs(ServerOutputs):
    """The worker's outputs as the bench needs them: the team map is built (its cost is the
    node's), nothing is published."""

    wants_team_map = True

    def __init__(self):
        self.dense_out_s: list[float] = []  # perf_counter times the dense map and grid went out

    def dense_map(self, dense, stamp_s: float) -> None:
        self.dense_out_s.append(time.perf_counter())


def bench_worker(cfg, vocab, map_path: str | None) -> ServerWorker:
    """The server node's worker, as the node makes it (a map file, global BA when idle)."""
    from ..team.durable import DurableServer
    from ..team.server import TeamServer

    def open_map(resume, load_path):
        return DurableServer(cfg, lambda c: TeamServer(c, vocab), map_path, defer_global_ba=True)

    return ServerWorker(cfg, open_map, BenchOutputs())


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
    # per merge: from its decision to the first dense map and grid out after it [wall s]
    merge_to_grid_s: list[float] = dataclasses.field(default_factory=list)

    @property
    def robots(self) -> int:
        return len({m.robot_id for m in self.messages})

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            k: np.array([getattr(m, k) for m in self.messages], float)
            for k in ("arrive_s", "start_s", "end_s")
        }


def replay_at_rate(
    arrivals: list[Arrival], worker: ServerWorker, rate: float = 1.0, idle_timeout_s: float = 0.5
) -> ScaleRun:
    """Feed ``arrivals`` at ``rate`` x their real rate (a feeder thread puts each into a queue at
    t0 + t / rate) to one consumer (this thread) handing them to the node's ``worker``
    (:meth:`ServerWorker.idle` when none came for ``idle_timeout_s``, as the node)."""
    if rate <= 0:
        raise CoopSlamError(f"rate must be > 0, got {rate}")
    jobs = [worker.intake(a.msg, a.robot_id) for a in arrivals]  # refused ones: None
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
            if worker.idle():
                idle.append((s, time.perf_counter() - t0))
            continue
        if got is None:
            break
        i, arrive = got
        a = arrivals[i]
        start = time.perf_counter() - t0
        merges = worker.handle(jobs[i]) if jobs[i] is not None else []
        end = time.perf_counter() - t0
        decided = worker.last_decided_s
        for _ in merges:
            latencies.append(decided - t0 - arrive)
            merge_own.append(decided - t0 - start)
            merge_times.append(decided - t0)
        messages.append(Processed(a.robot_id, message_kind(a.msg), arrive, start, end, len(merges)))
    feeder.join()
    worker.map_builder.wait_idle(30.0)
    out_s = np.sort(np.array(getattr(worker.out, "dense_out_s", []), float)) - t0
    k = np.searchsorted(out_s, merge_times)
    return ScaleRun(
        messages,
        latencies,
        merge_own,
        merge_times,
        idle,
        (arrivals[-1].t_s - first_s) if arrivals else 0.0,
        rate,
        worker.rejected,
        [float(out_s[i] - t) for i, t in zip(k, merge_times) if i < len(out_s)],
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
    if run.merge_to_grid_s:
        # A merge shown: the dense map and grid out after it (the builder may be busy with the
        # map of the state before it, and the next build waits for the worker's next pass).
        grid = np.array(run.merge_to_grid_s)
        yield ("server_scale_merge_to_grid_mean", float(np.mean(grid)), "s")
        yield ("server_scale_merge_to_grid_max", float(np.max(grid)), "s")


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
    from ..default_vocabulary import ensure_default_vocabulary
    from ..team.synthetic_team import bench_full_optimization
    from .replay import _server_config

    t = time.perf_counter()
    vocab = Vocabulary.load(ensure_default_vocabulary())
    if run_dir:
        arrivals, info = run_streams(run_dir)
        cfg = _server_config(os.path.join(CONFIG_DIR, "server.yaml"), info, {})
        what = f"run {os.path.basename(os.path.normpath(run_dir))}"
    else:
        arrivals = synthesized_streams()
        cfg = _synthetic_server_config(DEFAULT_SCENARIO, sorted({a.robot_id for a in arrivals}))
        what = f"synthetic {DEFAULT_SCENARIO}"
    _log(f"{len(arrivals)} messages ready in {time.perf_counter() - t:.1f} s; replaying")
    with tempfile.TemporaryDirectory() as tmp:
        # The node keeps a map file by default (server.launch map:=): so does the replay.
        worker = bench_worker(cfg, vocab, os.path.join(tmp, "team_map.db"))
        try:
            t = time.perf_counter()
            run = replay_at_rate(arrivals, worker, rate)
            took = time.perf_counter() - t
            _log(f"replay took {took:.1f} s; {worker.map_builder.built} team clouds built")
            yield from scale_figures(run)
            server = worker.server
            yield ("server_scale_final_graph_keyframes", float(len(server.store)), "keyframes")
            # What showing the final team map takes the builder (a merge's map appears after it).
            for name, job in (
                ("team_cloud", server.team_cloud_job()),
                ("dense_map", server.dense_map_job()),
            ):
                if job is not None:
                    t = time.perf_counter()
                    job()
                    yield (f"server_scale_{name}_build", 1e3 * (time.perf_counter() - t), "ms")
            t = time.perf_counter()
            server.optimize(full=True)
            full_ms = 1e3 * (time.perf_counter() - t)
            yield ("server_scale_full_optimization_final_graph", full_ms, "ms")
        finally:
            worker.close()
            worker.durable.close()
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
