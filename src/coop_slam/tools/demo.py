"""The main job behind ``scripts/demo``: prepare data, launch the system headless, follow it with a
progress line, and write the report.

The demo runs its own ROS master on a free port, so it never disturbs (or is disturbed by) a master
the user already has running.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np

from ..errors import CoopSlamError
from ..evaluation.run_report import evaluate_results, run_input_of
from ..geometry import T_base_cam_of, quat_from_se3
from ..playback import load_run_source
from .demo_args import parse_args
from .progress import throttled

# After the last frame the server may still be working off its queue: wait until its stats say it
# is idle (and stayed so for SETTLE_IDLE_S), or, when they do not say, while they change (quiet
# for SETTLE_QUIET_S); at most SETTLE_MAX_S [s].
SETTLE_IDLE_S = 1.0
SETTLE_QUIET_S = 5.0
SETTLE_MAX_S = 180.0


REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.realpath(__file__)), "..", "..", ".."))


def _write_run_info(
    out: str, args: argparse.Namespace, robot_ids: list[int], ground: bool, base_cam: list
) -> None:
    """What ``scripts/evaluate`` needs to find the ground truth of this run again, and
    ``scripts/replay`` the server's launch settings."""
    import json

    info = {
        "scenario": args.scenario,
        "dataset": os.path.abspath(args.dataset) if args.dataset else None,
        "split": args.split,
        "robots": args.robots,
        "seed": args.seed,
        "duration": args.duration,
        "camera": os.path.abspath(args.camera) if args.camera else None,
        "keep_timing": args.keep_timing,
        "bag": os.path.abspath(args.bag) if args.bag else None,
        "robot_ids": robot_ids,
        "only_robots": args.only_robots,
        "load_map": os.path.abspath(args.load_map) if args.load_map else None,
        "faults": args.faults,
        "rate": args.rate,  # None: lock-step
        "low_bandwidth": args.low_bandwidth,
        "sensors": args.sensors,
        "ground_robots": ground,
        "commit": _commit(),
        "T_base_cam": base_cam,  # [x y z qx qy qz qw], [] = the launch file's default
    }
    with open(os.path.join(out, "run.json"), "w", encoding="utf-8") as fh:
        json.dump(info, fh, indent=2)


def _commit() -> str | None:
    """The code's git commit (with ``+`` when the working tree has changes), when known."""
    try:
        head = subprocess.run(
            ["git", "-C", REPO, "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        dirty = subprocess.run(
            ["git", "-C", REPO, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+" if dirty.stdout.strip() else "")


def _framed_rviz_config(out: str, source, inputs, base_cam: list) -> str | None:
    """A copy of rviz/coop_slam.rviz in ``out`` whose view frames the map this run builds (see
    :mod:`.framing`: ground-truth cameras and what they see, in ``world``); None (the package's
    default view) without ground truth of the first robot, whose map ``world`` is."""
    from . import framing
    from .record import DEFAULT_SIZE, find_config

    try:
        T_world_gt = framing.T_world_gt(inputs.gts, T_base_cam_of(base_cam))
        poses = framing.world_camera_poses(inputs.gts, T_world_gt)
        seen, images = (
            framing.seen_depth_points(source.streams, T_world_gt)
            if source is not None
            else (np.zeros((0, 3)), 0)
        )
        half_tan = (
            framing.half_tangents(source.streams[0].sequence.camera)
            if source is not None and source.streams
            else framing.HALF_TAN
        )
        points = framing.framing_points(poses, seen, half_tan)
        template = find_config()
        default = framing.template_view(template)  # its pitch, yaw and FOV are kept
        view = framing.fit_orbit_view(
            points,
            pitch=default.pitch,
            yaws=(default.yaw, default.yaw - np.pi / 2),
            fov=default.fov,
            aspect=DEFAULT_SIZE[0] / DEFAULT_SIZE[1],
        )
        what = (
            f"what {images} depth images see"
            if images
            else f"their views {framing.LOOK_AHEAD_M:g} m ahead (no depth images)"
        )
        path = framing.framed_config(
            template,
            os.path.join(out, "video", "rviz_view.rviz"),
            view,
            f"Framed on the ground-truth cameras and {what}.",
            # the robots' axes as large on screen as in the package's view
            axes_scale=min(1.0, view.distance / default.distance),
        )
    except Exception as exc:  # noqa: BLE001 - a recording detail: never worth failing the run
        say(f"      RViz keeps the package's default view (rviz/coop_slam.rviz): {exc}")
        return None
    lo, hi = points.min(axis=0), points.max(axis=0)
    say(
        f"      RViz view framed on the ground-truth cameras and {what}: "
        f"{hi[0] - lo[0]:.1f} m x {hi[1] - lo[1]:.1f} m of world, from {view.distance:.1f} m "
        f"(the world group only: unmerged maps drawn aside are not framed; {path})"
    )
    return str(path)


def _hand_held(scenario: str) -> bool:
    """Whether people carry the scenario's cameras (6-DoF motion: no ground-robot prior)."""
    from ..synthetic.scenarios import SCENARIOS

    spec = SCENARIOS.get(scenario)
    return bool(spec is not None and spec.hand_held)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def say(msg: str) -> None:
    print(f"[demo] {msg}", flush=True)


class _Monitor:
    """Follows the run from inside this process (progress line) and records what the system
    publishes into a :class:`RunRecorder`.

    With ``ack`` it also acknowledges frames itself (no clients running), so lock-step playback
    still advances.
    """

    def __init__(self, robot_ids: list[int], ack: bool, sensors: list[str]):
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
        self._subs = [rospy.Subscriber("/clock", Clock, self._on_clock, queue_size=1)]
        for topic, type_name in self.recorder.topics().items():
            if ack and topic.endswith("/frame_stats"):
                continue  # this monitor publishes them itself
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

    def _on_clock(self, msg) -> None:
        self.sim_s = msg.clock.to_sec()

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


class _Operator:
    """Plays the person who tells the server that two robots are together (``--rendezvous``):
    calls the server's ~rendezvous service once the run reaches each request's time. Calls run in
    threads: lock-step playback must not wait for the server's answer."""

    SERVICE = "/server/rendezvous"

    def __init__(self, requests: list[tuple[int, int, float]], t0: float):
        self.pending = sorted(requests, key=lambda r: r[2])
        self.t0 = t0

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
            say(f"      operator rendezvous {a},{b}@{t_s:g}: {res.message}")  # says if merged
        except (rospy.ROSException, rospy.ServiceException) as exc:
            say(f"      operator rendezvous {a},{b}@{t_s:g} failed: {exc}")


def _save_map(path: str) -> str:
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


def _wait_for_master(uri: str, timeout_s: float) -> None:
    import rosgraph

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if rosgraph.Master("/demo", master_uri=uri).is_online():
            return
        time.sleep(0.2)
    raise CoopSlamError(f"ROS master at {uri} did not come up within {timeout_s:.0f} s")


def run(args: argparse.Namespace) -> int:
    from ..ros.run_recorder import RunRecorder, read_bag_input, run_data_from_bag

    name = args.scenario or os.path.basename(os.path.normpath(args.dataset or args.bag or "run"))
    out = os.path.abspath(
        args.out or os.path.join("results", f"{datetime.datetime.now():%Y%m%d-%H%M%S}-{name}")
    )
    os.makedirs(out, exist_ok=True)
    t_start = time.monotonic()

    if args.bag:
        say(f"[1/3] reading the bag {args.bag}")
        source, inputs = None, read_bag_input(args.bag)
        if inputs.robot_ids != list(range(1, len(inputs.robot_ids) + 1)):
            # demo.launch starts clients robot_1..robot_N
            raise CoopSlamError(
                f"--bag: the demo runs robots numbered 1..N, the bag has robots "
                f"{inputs.robot_ids}; remap its topics (rosbag filter or roslaunch coop_slam "
                "client.launch per robot)"
            )
        say(
            f"      {len(inputs.robot_ids)} robots, {inputs.frames} frames, "
            f"{inputs.end_s - inputs.start_s:.1f} s, ground truth for "
            f"{sum(len(s) > 0 for s, _ in inputs.gts.values())} robots"
        )
    else:
        what = f"scenario {args.scenario}" if args.scenario else args.dataset
        say(f"[1/3] preparing data ({what})")
        progress = throttled(
            lambda done, total: say(
                f"      rendering {done}/{total} frames ({100.0 * done / max(total, 1):.0f} %)"
            )
        )
        # Every robot of the source (ground truth for judging merges with loaded robots); the
        # player plays --only-robots.
        source = load_run_source(dict(vars(args), only_robots=None), progress)
        inputs = run_input_of(source, args.keep_timing)
        say(
            f"      {len(inputs.robot_ids)} robots, {inputs.frames} frames, data in {source.folder}"
        )
    robot_ids, total, t0, t1 = inputs.robot_ids, inputs.frames, inputs.start_s, inputs.end_s
    sensors = inputs.sensors or ["rgbd"] * len(robot_ids)
    all_ids = robot_ids
    if args.only_robots:
        from ..playback import PlaybackError, build_schedule, parse_robot_ids

        try:
            played = parse_robot_ids(args.only_robots)
        except PlaybackError as exc:
            raise CoopSlamError(f"--only-robots: {exc}") from None
        if set(played) - set(robot_ids):
            raise CoopSlamError(f"--only-robots {args.only_robots}: the source has {robot_ids}")
        schedule = build_schedule(
            [st for st in source.streams if st.robot_id in played], args.keep_timing
        )
        robot_ids, total, t1 = played, len(schedule), schedule[-1].play_s
        say(f"      playing robots {played} only")
    if len(set(sensors)) > 1 or sensors[0] != "rgbd":
        say(f"      cameras: {', '.join(f'robot_{r} {s}' for r, s in zip(robot_ids, sensors))}")
    for a, b, _ in args.rendezvous:
        if a not in robot_ids or b not in robot_ids:
            raise CoopSlamError(f"--rendezvous {a},{b}: this run has robots {robot_ids}")
    if args.rendezvous and args.no_clients:
        raise CoopSlamError("--rendezvous needs the server: drop --no-clients")
    from .faults import kill_node, parse_faults

    faults = parse_faults(args.faults or "", robot_ids)

    port = _free_port()
    uri = f"http://127.0.0.1:{port}"
    env = dict(
        os.environ,
        ROS_MASTER_URI=uri,
        ROS_HOSTNAME="127.0.0.1",
        ROS_LOG_DIR=os.path.join(out, "ros_log"),
    )
    os.environ.update(ROS_MASTER_URI=uri, ROS_HOSTNAME="127.0.0.1")
    launch_args = [
        f"robots:={len(all_ids)}",
        f"sensors:={','.join(sensors)}",
        f"seed:={args.seed}",
        f"keep_timing:={str(args.keep_timing).lower()}",
    ]
    if args.only_robots:
        launch_args.append(f"only_robots:={','.join(map(str, robot_ids))}")
    if args.scenario:
        launch_args.append(f"scenario:={args.scenario}")
        if args.duration:
            launch_args.append(f"duration:={args.duration}")
    elif args.bag:
        launch_args.append(f"bag:={os.path.abspath(args.bag)}")
    else:
        launch_args.append(f"dataset:={os.path.abspath(args.dataset)}")
        if args.split:
            launch_args.append(f"split:={args.split}")
        if args.camera:
            launch_args.append(f"camera_file:={os.path.abspath(args.camera)}")
    if args.rate is not None:
        launch_args += ["lockstep:=false", f"rate:={args.rate}"]
    base_cam = []
    if source is not None and "T_base_cam" in (source.meta or {}):
        t, q = quat_from_se3(np.asarray(source.meta["T_base_cam"], float))
        base_cam = [round(float(v), 6) for v in (*t, *q)]
        launch_args.append(f"T_base_cam:=[{', '.join(f'{v:.6f}' for v in base_cam)}]")
    if args.no_clients:
        launch_args += ["clients:=false", "server:=false"]
    for flag, arg in (("server_config", args.server_config), ("client_config", args.client_config)):
        if arg:
            if not os.path.isfile(arg):
                raise CoopSlamError(f"--{flag.replace('_', '-')}: file not found: {arg}")
            launch_args.append(f"{flag}:={os.path.abspath(arg)}")
    if args.no_markers:
        launch_args.append("marker_every_frames:=0")
    # Synthetic robots drive on the floor unless people carry the cameras (hand-held scenarios).
    ground = (
        args.ground_robots
        if args.ground_robots is not None
        else bool(args.scenario) and not _hand_held(args.scenario)
    )
    launch_args.append(f"ground_robots:={str(ground).lower()}")
    from ..team.map_store import remove_map_file

    map_path = os.path.join(out, "team_map.db")
    remove_map_file(map_path)  # a results folder used again: this run's map starts empty
    launch_args.append(f"map:={map_path}")
    if args.load_map:
        launch_args.append(f"load_map:={os.path.abspath(args.load_map)}")
    if faults.kills:  # killed nodes come back; the server carries on from its map file
        launch_args += ["respawn:=true", "resume:=true"]
    if faults.drop:
        launch_args.append(f"radio_drop:={faults.drop}")
    if args.low_bandwidth:
        launch_args.append("low_bandwidth:=true")
    bag_path = os.path.join(out, "run.bag")
    launch_args.append(f"record_bag:={bag_path}")
    # A loaded map's robots do not run, but the server shows them: record them for the report.
    record_ids = all_ids if args.load_map else robot_ids
    launch_args.append(f"record_topics:={' '.join(RunRecorder(record_ids).topics())}")
    _write_run_info(out, args, robot_ids, ground, base_cam)
    rviz_config = _framed_rviz_config(out, source, inputs, base_cam) if args.record else None
    log_path = os.path.join(out, "roslaunch.log")
    say(f"[2/3] running the system (ROS master {uri}; log {log_path})")
    recorder = None
    with open(log_path, "w") as log:
        launch = subprocess.Popen(
            ["roslaunch", "-p", str(port), "coop_slam", "demo.launch", *launch_args],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
    try:
        _wait_for_master(uri, 30.0)
        monitor = _Monitor(
            record_ids,
            ack=args.no_clients,
            sensors=[sensors[all_ids.index(r)] for r in record_ids],
        )
        if args.record:
            recorder = subprocess.Popen(
                [
                    os.path.join(REPO, "scripts", "record_rviz"),
                    "--headless",
                    "--out",
                    os.path.join(out, "video"),
                    *(["--config", rviz_config] if rviz_config else []),
                ],
                stdout=open(os.path.join(out, "record.log"), "w"),
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
            )
        operator = _Operator(args.rendezvous, t0)
        deadline = time.monotonic() + args.timeout
        tty = sys.stdout.isatty()
        last_line = 0.0
        while not monitor.done:
            if launch.poll() is not None:
                raise CoopSlamError(
                    f"roslaunch exited early (code {launch.returncode}); see {log_path}"
                )
            if time.monotonic() > deadline:
                raise CoopSlamError(
                    f"run did not finish within {args.timeout:.0f} s; see {log_path}"
                )
            operator.poll(monitor.sim_s)
            for kill in faults.kills:
                if not kill.tried and monitor.sim_s - t0 >= kill.at_s:
                    kill.tried = True
                    say(f"      fault: {kill_node(launch.pid, kill)}")
            got = sum(r.frames for r in monitor.run.robots.values())
            elapsed = min(max(monitor.sim_s - t0, 0.0), t1 - t0)
            line = (
                f"[demo]       sim time {elapsed:6.1f}/{t1 - t0:.1f} s "
                f"({100 * elapsed / max(t1 - t0, 1e-9):3.0f} %), frames received {got}/{total}"
            )
            if tty:
                print("\r" + line, end="", flush=True)
            elif time.monotonic() - last_line > 10.0:
                last_line = time.monotonic()
                print(line, flush=True)
            time.sleep(0.5)
        _settle(monitor, args.settle, say)
        if args.save_map:
            say(f"      saving the team map: {_save_map(args.save_map)}")
        if recorder is not None:
            say("      stopping the recording (final picture of the map)")
            os.killpg(recorder.pid, signal.SIGINT)
            try:
                recorder.wait(120)
            except subprocess.TimeoutExpired:
                os.killpg(recorder.pid, signal.SIGKILL)
        monitor.run.duration_s = t1 - t0
        if tty:
            print(flush=True)
    finally:
        if recorder is not None and recorder.poll() is None:
            os.killpg(recorder.pid, signal.SIGINT)
        if launch.poll() is None:
            os.killpg(launch.pid, signal.SIGINT)
            try:
                launch.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(launch.pid, signal.SIGKILL)

    say("[3/3] evaluating")
    run_data = monitor.run
    if os.path.isfile(bag_path):  # what the system published, as recorded
        say(f"      from the recorded bag {bag_path}")
        run_data = run_data_from_bag(bag_path, record_ids)
    else:
        say("      WARNING: no bag was recorded; evaluating what this process received")
    run_data.duration_s = monitor.run.duration_s
    report, json_path, md_path, ply = evaluate_results(
        out,
        run_data,
        {r: inputs.gts[r] for r in record_ids},
        inputs.overlap,
        extra={"faults": faults.summary()} if faults.any else None,
        T_base_cam=T_base_cam_of(base_cam),
    )
    for entry in report["robots"]:
        if entry.get("keyframes_lost"):
            say(
                f"      WARNING: robot_{entry['id']}: {entry['keyframes_lost']} of "
                f"{entry['keyframes_sent']} keyframes sent never reached the map"
            )
    traj_dir = os.path.join(out, "trajectories")
    say(f"done in {time.monotonic() - t_start:.0f} s")
    say(f"report:       {json_path}")
    say(f"              {md_path}")
    say(f"trajectories: {traj_dir}  (plot: {os.path.join(out, 'trajectories.png')})")
    if ply:
        say(f"team map:     {ply}")
    if args.record:
        say(
            f"video:        {os.path.join(out, 'video', 'rviz.mp4')}  (final view: "
            f"{os.path.join(out, 'video', 'map.png')})"
        )
    return 0


def _settle(monitor, settle_s: float, say) -> None:
    """After the last frame: wait ``settle_s`` for the last keyframes and merges, and longer (at
    most ``SETTLE_MAX_S``) while the server is still working off keyframes it received (until its
    stats say idle, or stop changing): a team of eight on two cores leaves it a backlog."""
    t_end = time.monotonic() + settle_s
    t_cap = time.monotonic() + max(settle_s, SETTLE_MAX_S)
    last, changed = None, time.monotonic()
    said = False
    while time.monotonic() < t_cap:
        now = time.monotonic()
        stats = json.dumps(monitor.run.server_stats, sort_keys=True, default=str)
        if stats != last:
            last, changed = stats, now
        idle = bool((monitor.run.server_stats or {}).get("idle"))
        if now >= t_end and now - changed >= (SETTLE_IDLE_S if idle else SETTLE_QUIET_S):
            return
        if now >= t_end and not said:
            say("      the server is still working off its queue: waiting for it")
            said = True
        time.sleep(0.5)
    say(f"      the server was still busy after {max(settle_s, SETTLE_MAX_S):.0f} s: evaluating")


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        return run(args)
    except CoopSlamError as exc:
        say(f"ERROR: {exc}")
        return 2
    except KeyboardInterrupt:
        say("interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
