"""The ROS side of ``scripts/demo``: the run's own ROS master, demo.launch's arguments, the
processes it starts (roslaunch, the RViz recording) and how they are watched and stopped, and this
process's own node that follows what the system publishes.

The demo runs its own ROS master on a free port, so it never disturbs (or is disturbed by) a master
the user already has running.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import socket
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass

from ..errors import CoopSlamError
from .faults import Faults
from .paths import REPO

HOST = "127.0.0.1"


@dataclass
class Master:
    """The run's own ROS master (not started yet) and the environment of the nodes that use it."""

    port: int
    uri: str
    env: dict[str, str]


@dataclass
class Launch:
    """One roslaunch process (the run's, or one host's with ``--hosts``) and its output file."""

    proc: subprocess.Popen
    log_path: str
    log_read: int = 0  # how far watch_nodes has read log_path [bytes]
    robot_id: int | None = None  # the robot whose host it runs on (None: the station / all)


@dataclass
class System:
    """The processes of a run: roslaunch (master, player, server, clients, bag recorder) -- one per
    host with ``--hosts`` -- and the RViz recording (when asked for). Each runs in its own process
    group, so that stopping it stops all it started."""

    master: Master
    launches: list[Launch]
    recorder: subprocess.Popen | None = None

    @property
    def log_path(self) -> str:
        return self.launches[0].log_path

    def launch_of(self, robot_id: int | None) -> Launch:
        """The roslaunch that runs robot ``robot_id``'s nodes (None: the server's)."""
        for launch in self.launches:
            if launch.robot_id == robot_id:
                return launch
        return self.launches[0]


def private_master(out: str) -> Master:
    """A master on a free port, with ROS logs in ``out``. This process's environment points at it
    too: its monitor node and service calls talk to the run's master."""
    port = _free_port()
    uri = f"http://{HOST}:{port}"
    env = dict(
        os.environ,
        ROS_MASTER_URI=uri,
        ROS_HOSTNAME=HOST,
        ROS_LOG_DIR=os.path.join(out, "ros_log"),
    )
    os.environ.update(ROS_MASTER_URI=uri, ROS_HOSTNAME=HOST)
    return Master(port, uri, env)


def launch_arguments(
    args: argparse.Namespace,
    *,
    all_ids: list[int],
    played_ids: list[int],
    sensors: list[str],
    base_cam: list,
    base_cams: dict,
    presets: str,
    ground: bool,
    faults: Faults,
    map_path: str,
    bag_path: str,
    record_ids: list[int],
) -> list[str]:
    """demo.launch's arguments for this run. ``all_ids`` are the source's robots, ``played_ids``
    those that run (``--only-robots``), ``sensors`` the cameras of ``all_ids``, ``base_cam`` the
    cameras' mounting (``[]``: the launch file's default), ``base_cams`` robots' own where they
    differ, ``presets`` the clients' camera presets, ``record_ids`` the robots whose topics go into
    ``bag_path``."""
    from ..ros.run_recorder import RunRecorder

    launch_args = [
        f"robots:={len(all_ids)}",
        f"sensors:={','.join(sensors)}",
        f"seed:={args.seed}",
        f"keep_timing:={str(args.keep_timing).lower()}",
    ]
    if args.only_robots:
        launch_args.append(f"only_robots:={','.join(map(str, played_ids))}")
    launch_args += _source_arguments(args)
    if args.rate is not None:
        launch_args += ["lockstep:=false", f"rate:={args.rate}"]
    mounts = [base_cams.get(r, base_cam) for r in range(1, max(all_ids) + 1)]
    if any(mounts):  # robot k's is the k-th; one robot's without one gets the launch default
        text = [",".join(f"{v:.6f}" for v in m) for m in mounts]
        launch_args.append(f"T_base_cams:={';'.join(text)}")
    if args.no_clients:
        launch_args += ["clients:=false", "server:=false"]
    launch_args += _config_arguments(args)
    if args.no_markers:
        launch_args.append("marker_every_frames:=0")
    launch_args.append(f"ground_robots:={str(ground).lower()}")
    launch_args.append(f"map:={map_path}")
    # The run's own spools: a client killed by --faults sends what it kept after its restart.
    launch_args.append(f"spool_dir:={os.path.join(os.path.dirname(map_path), 'spool')}")
    if args.load_map:
        launch_args.append(f"load_map:={os.path.abspath(args.load_map)}")
    if faults.kills:  # killed nodes come back; the server carries on from its map file
        launch_args += ["respawn:=true", "resume:=true"]
    if faults.drop:
        launch_args.append(f"radio_drop:={faults.drop}")
    if args.low_bandwidth:
        launch_args.append("low_bandwidth:=true")
    if args.vocabulary:
        launch_args.append(f"vocabulary:={os.path.abspath(args.vocabulary)}")
    if presets:
        launch_args.append(f"cameras:={presets}")
    if args.clock_offset:
        text = ",".join(f"{r}:{s:g}" for r, s in args.clock_offset)
        launch_args.append(f"clock_offsets:={text}")
    launch_args.append(f"record_bag:={bag_path}")
    launch_args.append(f"record_topics:={' '.join(RunRecorder(record_ids).topics())}")
    return launch_args


def _source_arguments(args: argparse.Namespace) -> list[str]:
    """What the player plays: a scenario, a bag or a dataset."""
    if args.scenario:
        return [f"scenario:={args.scenario}"] + (
            [f"duration:={args.duration}"] if args.duration else []
        )
    if args.bag:
        return [f"bag:={os.path.abspath(args.bag)}"]
    source_args = [f"dataset:={os.path.abspath(args.dataset)}"]
    if args.split:
        source_args.append(f"split:={args.split}")
    if args.camera:
        source_args.append(f"camera_file:={os.path.abspath(args.camera)}")
    return source_args


def _config_arguments(args: argparse.Namespace) -> list[str]:
    """The server's and clients' YAML files, when given (raises when one is missing)."""
    config_args = []
    for flag, arg in (("server_config", args.server_config), ("client_config", args.client_config)):
        if arg:
            if not os.path.isfile(arg):
                raise CoopSlamError(f"--{flag.replace('_', '-')}: file not found: {arg}")
            config_args.append(f"{flag}:={os.path.abspath(arg)}")
    return config_args


def start_system(master: Master, launch_args: list[str], log_path: str) -> System:
    """Start roslaunch (its master on ``master.port``), its output into ``log_path``; the caller
    waits for the master (:func:`wait_for_master`) and stops the system (:func:`stop_system`)."""
    launch = start_launch(["-p", str(master.port)], launch_args, log_path, master.env)
    return System(master, [launch])


def start_launch(
    prefix: list[str],
    launch_args: list[str],
    log_path: str,
    env: dict[str, str],
    robot_id: int | None = None,
    wrapper: list[str] | None = None,
) -> Launch:
    """``roslaunch PREFIX coop_slam demo.launch ARGS`` (under ``wrapper``: e.g. on a host),
    its output into ``log_path``."""
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [*(wrapper or []), "roslaunch", *prefix, "coop_slam", "demo.launch", *launch_args],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
    return Launch(proc, log_path, robot_id=robot_id)


def wait_for_master(uri: str, timeout_s: float) -> None:
    import rosgraph

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if rosgraph.Master("/demo", master_uri=uri).is_online():
            return
        time.sleep(0.2)
    raise CoopSlamError(f"ROS master at {uri} did not come up within {timeout_s:.0f} s")


# A node that gives up says so at FATAL level (the nodes' output is roslaunch's, output="screen");
# roslaunch names a required node that died.
_GAVE_UP = re.compile(r"\[FATAL\]|REQUIRED process \[.*\] has died|process has died")


def _node_reasons(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() if _GAVE_UP.search(line)]


def watch_nodes(system: System) -> None:
    """Raise, naming the node and its reason, when a node gave up (a FATAL line: a corrupt map
    file, a camera it cannot use, ...) or the system stopped before the run's end (a roslaunch
    exited: a required node died)."""
    for launch in system.launches:
        _watch_launch(launch)


def _watch_launch(launch: Launch) -> None:
    with open(launch.log_path, "rb") as fh:
        fh.seek(launch.log_read)
        data = fh.read()
    data = data[: data.rfind(b"\n") + 1]  # whole lines only: the rest is read next time
    launch.log_read += len(data)
    new = data.decode("utf-8", "replace")
    fatal = [line for line in _node_reasons(new) if "[FATAL]" in line]
    if fatal:
        raise CoopSlamError(
            "a node gave up: " + " | ".join(fatal[:3]) + f" (see {launch.log_path})"
        )
    if launch.proc.poll() is not None:
        with open(launch.log_path, encoding="utf-8", errors="replace") as fh:
            reasons = _node_reasons(fh.read())
        raise CoopSlamError(
            f"roslaunch exited early (code {launch.proc.returncode})"
            + (": " + " | ".join(reasons[-3:]) if reasons else "")
            + f"; see {launch.log_path}"
        )


def start_recording(system: System, out: str, rviz_config: str | None) -> None:
    """Record RViz headless into ``out``/video (``rviz_config``: its view; None: the package's)."""
    with open(os.path.join(out, "record.log"), "w") as log:
        system.recorder = subprocess.Popen(
            [
                os.path.join(REPO, "scripts", "record_rviz"),
                "--headless",
                "--out",
                os.path.join(out, "video"),
                *(["--config", rviz_config] if rviz_config else []),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=system.master.env,
            start_new_session=True,
        )


def stop_recording(system: System) -> None:
    """End the recording and wait for it: it takes the final picture of the map on its way out."""
    os.killpg(system.recorder.pid, signal.SIGINT)
    try:
        system.recorder.wait(120)
    except subprocess.TimeoutExpired:
        os.killpg(system.recorder.pid, signal.SIGKILL)


def stop_system(system: System) -> None:
    """Stop whatever still runs (after the run, or when it failed): robots' hosts first, the
    station (master) last."""
    if system.recorder is not None and system.recorder.poll() is None:
        os.killpg(system.recorder.pid, signal.SIGINT)
    for launch in reversed(system.launches):
        if launch.proc.poll() is None:
            os.killpg(launch.proc.pid, signal.SIGINT)
    for launch in reversed(system.launches):
        try:
            launch.proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(launch.proc.pid, signal.SIGKILL)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


class Monitor:
    """Follows the run from inside this process (progress line) and records what the system
    publishes into a :class:`~coop_slam.ros.run_recorder.RunRecorder`.

    With ``ack`` it also acknowledges frames itself (no clients running), so lock-step playback
    still advances. On the station of ``--hosts`` (``station``) it follows only what the station
    publishes, so that it costs the radio nothing, and counts frames by the conductor's steps.
    """

    def __init__(self, robot_ids: list[int], ack: bool, sensors: list[str], station=False):
        import rospy
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import Image

        from coop_slam.msg import FrameStats

        from ..playback import image_topic
        from ..ros.run_recorder import RunRecorder, message_class

        rospy.init_node("demo_monitor", anonymous=True, disable_signals=True)
        self.recorder = RunRecorder(robot_ids)
        self.run = self.recorder.run
        self.sim_s = 0.0
        self.ack = ack
        self.frames_stepped = 0  # --hosts: frames the conductor has stepped through
        self._subs = [rospy.Subscriber("/clock", Clock, self._on_clock, queue_size=1)]
        if station:
            from std_msgs.msg import Header

            from ..ros.conductor import STEP_TOPIC

            self._subs.append(rospy.Subscriber(STEP_TOPIC, Header, self._on_step, queue_size=10))
        for topic, type_name in self.recorder.topics("station" if station else "all").items():
            if ack and topic.endswith("/frame_stats"):
                continue  # this monitor publishes them itself
            if station and topic == "/robot_sightings":
                continue  # the robots publish them: across the radio
            self._subs.append(
                rospy.Subscriber(
                    topic,
                    rospy.AnyMsg,
                    self._on_any,
                    (topic, message_class(type_name)),
                    queue_size=500,
                    buff_size=2**25,
                )
            )
        self._acks = {}
        for r in robot_ids if ack else ():
            self._subs.append(
                rospy.Subscriber(
                    image_topic(r, sensors[robot_ids.index(r)]),
                    Image,
                    self._on_image,
                    r,
                    queue_size=5,
                    buff_size=2**24,
                )
            )
            self._acks[r] = rospy.Publisher(f"/robot_{r}/frame_stats", FrameStats, queue_size=10)
        self._FrameStats = FrameStats

    @property
    def done(self) -> bool:
        return self.recorder.done

    @property
    def frames(self) -> int:
        """Frames played so far (as the clients report them, or as the conductor stepped)."""
        return self.frames_stepped or sum(r.frames for r in self.run.robots.values())

    def _on_clock(self, msg) -> None:
        self.sim_s = msg.clock.to_sec()

    def _on_step(self, msg) -> None:
        self.frames_stepped = int(msg.frame_id or 0)

    def _on_any(self, raw, args) -> None:
        topic, cls = args
        msg = cls()
        msg.deserialize(raw._buff)
        self.recorder.feed(topic, msg, self.sim_s, len(raw._buff))

    def _on_image(self, msg, robot_id: int) -> None:
        ack = self._FrameStats(robot_id=robot_id, tracking_ok=True)
        ack.header.stamp = msg.header.stamp
        self.recorder.feed(f"/robot_{robot_id}/frame_stats", ack, self.sim_s, 0)
        self._acks[robot_id].publish(ack)


class Operator:
    """Plays the person who tells the server that two robots are together (``--rendezvous``):
    calls the server's ~rendezvous service once the run reaches each request's time. Calls run in
    threads: lock-step playback must not wait for the server's answer."""

    SERVICE = "/server/rendezvous"

    def __init__(
        self, requests: list[tuple[int, int, float]], t0: float, say: Callable[[str], None]
    ):
        self.pending = sorted(requests, key=lambda r: r[2])
        self.t0 = t0
        self.say = say

    def poll(self, sim_s: float) -> None:
        import threading

        while self.pending and sim_s - self.t0 >= self.pending[0][2]:
            a, b, t_s = self.pending.pop(0)
            threading.Thread(target=self._call, args=(a, b, t_s), daemon=True).start()

    def _call(self, a: int, b: int, t_s: float) -> None:
        import rospy

        from coop_slam.srv import Rendezvous

        try:
            rospy.wait_for_service(self.SERVICE, timeout=30.0)
            res = rospy.ServiceProxy(self.SERVICE, Rendezvous)(
                robot_a=a, robot_b=b, stamp=rospy.Time.from_sec(self.t0 + t_s)
            )
            self.say(f"      operator rendezvous {a},{b}@{t_s:g}: {res.message}")  # says if merged
        except (rospy.ROSException, rospy.ServiceException) as exc:
            self.say(f"      operator rendezvous {a},{b}@{t_s:g} failed: {exc}")


def save_map(path: str) -> str:
    """Have the server save the team map to ``path``; its answer (raises when it has none)."""
    import rospy

    from coop_slam.srv import SaveMap

    try:
        rospy.wait_for_service("/server/save_map", timeout=60.0)
        res = rospy.ServiceProxy("/server/save_map", SaveMap)(path=os.path.abspath(path))
    except (rospy.ROSException, rospy.ServiceException) as exc:
        raise CoopSlamError(f"--save-map {path}: the server did not answer ({exc})") from exc
    if not res.success:
        raise CoopSlamError(f"--save-map {path}: {res.message}")
    return res.message
