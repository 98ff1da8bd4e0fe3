"""The main job behind ``scripts/demo``, as the steps it prints: prepare the data ([1/3]); start the
system, follow its progress to the last frame, let the server settle and stop it ([2/3]); evaluate
and report ([3/3]).

Its options are :mod:`.demo_args`; the ROS processes it starts and watches, :mod:`.demo_launch`.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import signal
import sys
import time
from dataclasses import dataclass

import numpy as np

from ..errors import CoopSlamError
from ..evaluation.run_report import RunInput, evaluate_results, run_input_of
from ..geometry import T_base_cam_of, quat_from_se3
from ..playback import Source, load_run_source
from .demo_args import parse_args
from .demo_hosts import HostsTeam
from .demo_launch import (
    Monitor,
    Operator,
    System,
    launch_arguments,
    private_master,
    save_map,
    start_recording,
    start_system,
    stop_recording,
    stop_system,
    wait_for_master,
    watch_nodes,
)
from .faults import Faults, kill_node, parse_faults
from .paths import git_commit
from .progress import throttled

# After the last frame the server may still be working off its queue: wait until its stats say it
# is idle (and stayed so for SETTLE_IDLE_S), or, when they do not say, while they change (quiet
# for SETTLE_QUIET_S); at most SETTLE_MAX_S [s].
SETTLE_IDLE_S = 1.0
SETTLE_QUIET_S = 5.0
SETTLE_MAX_S = 180.0
# Messages a client sends again go at most max_resend_after_s (30 s) apart: wait that long and a
# little for them to be stored [s].
SETTLE_UNACKED_S = 40.0
# In the results folder: what the system published (evaluated), and the team map's file.
RUN_BAG = "run.bag"
TEAM_MAP = "team_map.db"


@dataclass
class _RunPlan:
    """What a run plays and judges, once its data is ready."""

    source: Source | None  # None for a bag: it is played as it is
    inputs: RunInput
    all_ids: list[int]  # the source's robots
    robot_ids: list[int]  # those that run (--only-robots)
    sensors: list[str]  # the cameras of all_ids
    frames: int  # frames played
    t0: float  # the first frame's time [s]
    t1: float  # the last played frame's time [s]
    faults: Faults
    ground: bool  # the robots drive on a level floor (client vo.planar.enabled)
    base_cam: list  # the cameras' mounting [x y z qx qy qz qw]; [] = the launch file's default
    base_cams: dict  # robot id -> its own mounting, for robots whose mount differs (or {})
    clock_offsets: dict  # robot id -> how far its clock runs ahead (rehearsed) [s]
    presets: str  # the clients' camera presets (demo.launch cameras; "" = none)
    record_ids: list[int]  # the robots the bag records and the report covers


def main(argv=None) -> int:
    args = parse_args(argv)
    # A kill (SIGTERM) stops the run as Ctrl-C does: what it made (hosts, processes) is removed.
    signal.signal(signal.SIGTERM, _interrupted)
    try:
        return run(args)
    except CoopSlamError as exc:
        say(f"ERROR: {exc}")
        return 2
    except KeyboardInterrupt:
        say("interrupted")
        return 130


def _interrupted(signum, frame) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    """One demo run, step by step; 0 when done (raises CoopSlamError when it cannot run)."""
    out = _results_folder(args)
    t_start = time.monotonic()
    plan = _prepare_data(args)
    team = HostsTeam.make(args, plan.robot_ids, say) if args.hosts else None
    try:
        monitor = _run_system(args, plan, out, team)
    finally:
        if team is not None:
            team.close()
    json_path, md_path, ply = _evaluate(plan, monitor, out)
    _say_results(args, out, json_path, md_path, ply, t_start)
    return 0


def _run_system(
    args: argparse.Namespace, plan: _RunPlan, out: str, team: HostsTeam | None
) -> Monitor:
    """[2/3]: start the system (on the hosts of ``team``), follow it to the last frame, let the
    server settle and stop it; what the monitor saw."""
    master = team.master(out) if team else private_master(out)
    launch_args = _launch_arguments(args, plan, out)
    _write_run_info(out, args, plan)
    rviz_config = (
        _framed_rviz_config(out, plan.source, plan.inputs, plan.base_cam, team is not None)
        if args.record
        else None
    )
    log_path = os.path.join(out, "roslaunch.log")
    say(f"[2/3] running the system (ROS master {master.uri}; log {log_path})")
    if team is None:
        system = start_system(master, launch_args, log_path)
    else:
        system = team.start(master, launch_args, out, _host_topics(plan))
        team.enter_station()  # the monitor (and RViz) run on the station
    try:
        monitor = _start_watching(args, plan, system, out, rviz_config, station=team is not None)
        if team is not None:
            team.count_from_now()
        _follow_progress(args, plan, system, monitor, team)
        _settle(monitor, args.settle, say, team.sending if team is not None else None)
        if team is not None:
            monitor.run.radio_bytes = team.radio_used()
            team.say_radio(monitor.run.radio_bytes, plan.t1 - plan.t0)
            _add_run_info(out, radio_bytes=monitor.run.radio_bytes)
        _wrap_up(args, plan, system, monitor)
    finally:
        stop_system(system)
    return monitor


def _host_topics(plan: _RunPlan):
    """What each host of ``--hosts`` records: ``(where, robot) -> topics``."""
    from ..ros.run_recorder import RunRecorder

    def topics(where: str, robot: int | None) -> list[str]:
        return list(RunRecorder([robot] if robot else plan.record_ids).topics(where))

    return topics


def say(msg: str) -> None:
    print(f"[demo] {msg}", flush=True)


def _camera_presets(args: argparse.Namespace) -> str:
    """The clients' camera presets (demo.launch ``cameras``): --camera-preset, else a dataset
    folder's own; checked here, so that a wrong name fails before anything starts."""
    from ..camera_presets import load_preset, preset_for_dataset

    text = args.camera_preset or (preset_for_dataset(args.dataset) if args.dataset else "")
    if text == "none":
        return ""
    for name in filter(None, text.split(",")):
        load_preset(name)
    if text:
        say(f"      camera preset: {text} (config/cameras/)")
    return text


def _results_folder(args: argparse.Namespace) -> str:
    """``--out``, or results/<date>-<source>; created."""
    name = args.scenario or os.path.basename(os.path.normpath(args.dataset or args.bag or "run"))
    out = os.path.abspath(
        args.out or os.path.join("results", f"{datetime.datetime.now():%Y%m%d-%H%M%S}-{name}")
    )
    os.makedirs(out, exist_ok=True)
    return out


def _prepare_data(args: argparse.Namespace) -> _RunPlan:
    """[1/3]: read the bag or load (render) the source, and check what needs its robots."""
    source, inputs = _read_bag(args.bag) if args.bag else _load_source(args)
    all_ids = inputs.robot_ids
    sensors = inputs.sensors or ["rgbd"] * len(all_ids)
    robot_ids, frames, t1 = _played_robots(args, source, inputs)
    if len(set(sensors)) > 1 or sensors[0] != "rgbd":
        say(f"      cameras: {', '.join(f'robot_{r} {s}' for r, s in zip(robot_ids, sensors))}")
    for a, b, _ in args.rendezvous:
        if a not in robot_ids or b not in robot_ids:
            raise CoopSlamError(f"--rendezvous {a},{b}: this run has robots {robot_ids}")
    if args.rendezvous and args.no_clients:
        raise CoopSlamError("--rendezvous needs the server: drop --no-clients")
    if args.vocabulary and not os.path.isfile(args.vocabulary):
        raise CoopSlamError(f"--vocabulary {args.vocabulary}: no such file")
    return _RunPlan(
        source=source,
        inputs=inputs,
        all_ids=all_ids,
        robot_ids=robot_ids,
        sensors=sensors,
        frames=frames,
        t0=inputs.start_s,
        t1=t1,
        faults=parse_faults(args.faults or "", robot_ids),
        ground=_ground_robots(args),
        base_cam=_base_cam(source),
        base_cams=_base_cams(source),
        clock_offsets=dict(args.clock_offset),
        presets=_camera_presets(args),
        # A loaded map's robots do not run, but the server shows them: record them for the report.
        record_ids=all_ids if args.load_map else robot_ids,
    )


def _read_bag(bag: str) -> tuple[None, RunInput]:
    """A sensor bag's robots and ground truth (no run source: the bag is played as it is)."""
    from ..ros.run_recorder import read_bag_input

    say(f"[1/3] reading the bag {bag}")
    inputs = read_bag_input(bag)
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
    return None, inputs


def _load_source(args: argparse.Namespace) -> tuple[Source, RunInput]:
    """The scenario (rendered when not cached) or dataset, and its run input."""
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
    say(f"      {len(inputs.robot_ids)} robots, {inputs.frames} frames, data in {source.folder}")
    return source, inputs


def _played_robots(
    args: argparse.Namespace, source: Source | None, inputs: RunInput
) -> tuple[list[int], int, float]:
    """The robots that run, their frames and the time of their last one: all of the source's, or
    those of ``--only-robots``."""
    if not args.only_robots:
        return inputs.robot_ids, inputs.frames, inputs.end_s
    from ..playback import PlaybackError, build_schedule, parse_robot_ids

    try:
        played = parse_robot_ids(args.only_robots)
    except PlaybackError as exc:
        raise CoopSlamError(f"--only-robots: {exc}") from None
    if set(played) - set(inputs.robot_ids):
        raise CoopSlamError(f"--only-robots {args.only_robots}: the source has {inputs.robot_ids}")
    schedule = build_schedule(
        [st for st in source.streams if st.robot_id in played], args.keep_timing
    )
    say(f"      playing robots {played} only")
    return played, len(schedule), schedule[-1].play_s


def _ground_robots(args: argparse.Namespace) -> bool:
    """``--ground-robots``, by default: synthetic robots drive on the floor unless people carry
    the cameras (hand-held scenarios)."""
    if args.ground_robots is not None:
        return args.ground_robots
    return bool(args.scenario) and not _hand_held(args.scenario)


def _hand_held(scenario: str) -> bool:
    """Whether people carry the scenario's cameras (6-DoF motion: no ground-robot prior)."""
    from ..synthetic.scenarios import SCENARIOS

    spec = SCENARIOS.get(scenario)
    return bool(spec is not None and spec.hand_held)


def _base_cam(source: Source | None) -> list:
    """The source's camera mounting as [x y z qx qy qz qw] (rounded as the launch file gets it),
    or [] when it has none."""
    if source is None or "T_base_cam" not in (source.meta or {}):
        return []
    return _mount_numbers(source.meta["T_base_cam"])


def _base_cams(source: Source | None) -> dict:
    """Robot id -> its own camera mounting [x y z qx qy qz qw], for the source's robots that
    carry one (a synthetic world's robots each do)."""
    robots = (source.meta or {}).get("robots") if source is not None else None
    return {
        int(r["id"]): _mount_numbers(r["T_base_cam"])
        for r in robots or []
        if isinstance(r, dict) and "T_base_cam" in r
    }


def _mount_numbers(T_base_cam) -> list:
    t, q = quat_from_se3(np.asarray(T_base_cam, float))
    return [round(float(v), 6) for v in (*t, *q)]


def _launch_arguments(args: argparse.Namespace, plan: _RunPlan, out: str) -> list[str]:
    """demo.launch's arguments; the team map's file in ``out`` is emptied for this run."""
    from ..team.map_store import remove_map_file

    map_path = os.path.join(out, TEAM_MAP)
    launch_args = launch_arguments(
        args,
        all_ids=plan.all_ids,
        played_ids=plan.robot_ids,
        sensors=plan.sensors,
        base_cam=plan.base_cam,
        base_cams=plan.base_cams,
        presets=plan.presets,
        ground=plan.ground,
        faults=plan.faults,
        map_path=map_path,
        bag_path=os.path.join(out, RUN_BAG),
        record_ids=plan.record_ids,
    )
    remove_map_file(map_path)  # a results folder used again: this run's map starts empty
    shutil.rmtree(os.path.join(out, "spool"), ignore_errors=True)  # and its clients' spools
    return launch_args


def _write_run_info(out: str, args: argparse.Namespace, plan: _RunPlan) -> None:
    """What ``scripts/evaluate`` needs to find the ground truth of this run again, and
    ``scripts/replay`` the server's launch settings."""
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
        "robot_ids": plan.robot_ids,
        "only_robots": args.only_robots,
        "load_map": os.path.abspath(args.load_map) if args.load_map else None,
        "faults": args.faults,
        "rate": args.rate,  # None: lock-step
        "low_bandwidth": args.low_bandwidth,
        "sensors": args.sensors,
        "camera_presets": plan.presets,
        "vocabulary": os.path.abspath(args.vocabulary) if args.vocabulary else None,
        "ground_robots": plan.ground,
        "commit": git_commit(),
        "T_base_cam": plan.base_cam,  # [x y z qx qy qz qw], [] = the launch file's default
        "T_base_cams": {str(r): v for r, v in plan.base_cams.items()},  # robots' own, where given
        "hosts": args.hosts,
        "link_rate": args.link_rate,  # [kbit/s], 0 = unlimited
        "outage": [f"{r}@{a:g}-{b:g}" for r, a, b in args.outage],
        # robot -> how far its clock ran ahead (rehearsed) [s]: its stamps are on that clock
        "clock_offsets": {str(r): s for r, s in plan.clock_offsets.items()},
    }
    with open(os.path.join(out, "run.json"), "w", encoding="utf-8") as fh:
        json.dump(info, fh, indent=2)


def _add_run_info(out: str, **fields) -> None:
    """Add what the run measured (e.g. radio bytes) to ``run.json`` for ``scripts/evaluate``."""
    path = os.path.join(out, "run.json")
    with open(path, encoding="utf-8") as fh:
        info = json.load(fh)
    info.update(fields)
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(info, fh, indent=2)


def _framed_rviz_config(
    out: str, source, inputs, base_cam: list, station_only: bool = False
) -> str | None:
    """A copy of rviz/coop_slam.rviz in ``out`` whose view frames the map this run builds (see
    :mod:`.framing`: ground-truth cameras and what they see, in ``world``); None (the package's
    default view) without ground truth of the first robot, whose map ``world`` is.
    ``station_only`` (--hosts): without the robots' own topics, which would cross the radio."""
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
            station_only=station_only,
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


def _start_watching(
    args: argparse.Namespace,
    plan: _RunPlan,
    system: System,
    out: str,
    rviz_config: str | None,
    station: bool = False,
) -> Monitor:
    """Once roslaunch started: wait for its master, then follow what the system publishes (this
    process's monitor node; on the ``station`` of --hosts, what the station publishes) and record
    RViz when asked."""
    wait_for_master(system.master.uri, 30.0)
    monitor = Monitor(
        plan.record_ids,
        ack=args.no_clients,
        sensors=[plan.sensors[plan.all_ids.index(r)] for r in plan.record_ids],
        station=station,
    )
    if args.record:
        start_recording(system, out, rviz_config)
    return monitor


def _follow_progress(
    args: argparse.Namespace,
    plan: _RunPlan,
    system: System,
    monitor: Monitor,
    team: HostsTeam | None = None,
) -> None:
    """Until the player's last frame went through: the progress line (rewritten in place on a
    terminal, every 10 s into a log), and the operator's requests, the faults and the radio
    outages at their times. Raises when the system stops early or the run outlasts
    ``--timeout``."""
    operator = Operator(args.rendezvous, plan.t0, say)
    deadline = time.monotonic() + args.timeout
    tty = sys.stdout.isatty()
    last_line = 0.0
    while not monitor.done:
        watch_nodes(system)
        if time.monotonic() > deadline:
            raise CoopSlamError(
                f"run did not finish within {args.timeout:.0f} s; see {system.log_path}"
            )
        operator.poll(monitor.sim_s)
        if team is not None:
            team.poll(monitor.sim_s - plan.t0)
        for kill in plan.faults.kills:
            if not kill.tried and monitor.sim_s - plan.t0 >= kill.at_s:
                kill.tried = True
                say(f"      fault: {kill_node(system.launch_of(kill.robot_id).proc.pid, kill)}")
        got = monitor.frames
        span = plan.t1 - plan.t0
        elapsed = min(max(monitor.sim_s - plan.t0, 0.0), span)
        line = (
            f"[demo]       sim time {elapsed:6.1f}/{span:.1f} s "
            f"({100 * elapsed / max(span, 1e-9):3.0f} %), frames received {got}/{plan.frames}"
        )
        if tty:
            print("\r" + line, end="", flush=True)
        elif time.monotonic() - last_line > 10.0:
            last_line = time.monotonic()
            print(line, flush=True)
        time.sleep(0.5)
    if team is not None:
        team.end_outages()


def _settle(monitor, settle_s: float, say, sending=None) -> None:
    """After the last frame: wait ``settle_s`` for the last keyframes and merges, and longer (at
    most ``SETTLE_MAX_S``) while the server is still working off keyframes it received (until its
    stats say idle, or stop changing): a team of eight on two cores leaves it a backlog; while
    ``sending()`` (a slow radio still carries what the robots sent); and (at most
    ``SETTLE_UNACKED_S``) while a client waits for the server to store messages it sent again (a
    lossy radio, a restarted server)."""
    t_end = time.monotonic() + settle_s
    t_cap = time.monotonic() + max(settle_s, SETTLE_MAX_S)
    t_unacked, gave_up = t_end + SETTLE_UNACKED_S, False
    last, changed = None, time.monotonic()
    said = False
    while time.monotonic() < t_cap:
        now = time.monotonic()
        stats = json.dumps(monitor.run.server_stats, sort_keys=True, default=str)
        if stats != last:
            last, changed = stats, now
        idle = bool((monitor.run.server_stats or {}).get("idle"))
        quiet = now - changed >= (SETTLE_IDLE_S if idle else SETTLE_QUIET_S)
        robots = list(monitor.run.robots.items())
        unacked = {} if gave_up else {r: run.unacked for r, run in robots if run.unacked}
        if unacked and now >= t_unacked:
            say(
                "      after %.0f s robots still wait for the server to store keyframe messages "
                "(%s): evaluating"
                % (SETTLE_UNACKED_S, ", ".join(f"robot_{r}: {n}" for r, n in unacked.items()))
            )
            gave_up, unacked = True, {}
        if now >= t_end and quiet and not unacked and not (sending is not None and sending()):
            return
        if now >= t_end and not said:
            say("      the server is still working off its queue: waiting for it")
            said = True
        time.sleep(0.5)
    say(f"      the server was still busy after {max(settle_s, SETTLE_MAX_S):.0f} s: evaluating")


def _wrap_up(args: argparse.Namespace, plan: _RunPlan, system: System, monitor: Monitor) -> None:
    """After the server settled, while the system still runs: save the team map and end the
    recording (it takes the final picture of the map on its way out)."""
    if args.save_map:
        say(f"      saving the team map: {save_map(args.save_map)}")
    if system.recorder is not None:
        say("      stopping the recording (final picture of the map)")
        stop_recording(system)
    monitor.run.duration_s = plan.t1 - plan.t0
    if sys.stdout.isatty():
        print(flush=True)  # ends the progress line, rewritten in place until now


def _evaluate(plan: _RunPlan, monitor: Monitor, out: str) -> tuple[str, str, str | None]:
    """[3/3]: the report from the recorded bag (what this process received when there is none);
    its JSON and Markdown files and the team map's PLY (or None)."""
    from ..ros.run_recorder import run_bags, run_data_from_bag
    from . import framing

    say("[3/3] evaluating")
    run_data = monitor.run
    bag_path = os.path.join(out, RUN_BAG)
    if os.path.isfile(bag_path):  # what the system published, as recorded
        bags = run_bags(out)
        say(f"      from the recorded bag{'s' * (len(bags) > 1)} {', '.join(bags)}")
        run_data = run_data_from_bag(bags, plan.record_ids, plan.clock_offsets)
    else:
        say("      WARNING: no bag was recorded; evaluating what this process received")
    run_data.duration_s = monitor.run.duration_s
    run_data.radio_bytes = monitor.run.radio_bytes
    report, json_path, md_path, ply = evaluate_results(
        out,
        run_data,
        {r: plan.inputs.gts[r] for r in plan.record_ids},
        plan.inputs.overlap,
        extra={"faults": plan.faults.summary()} if plan.faults.any else None,
        T_base_cam=T_base_cam_of(plan.base_cam),
        dense_truth=framing.dense_truth_of(plan.inputs, T_base_cam_of(plan.base_cam)),
    )
    for entry in report["robots"]:
        if entry.get("keyframes_lost"):
            say(
                f"      WARNING: robot_{entry['id']}: {entry['keyframes_lost']} of "
                f"{entry['keyframes_sent']} keyframes sent never reached the map"
            )
    return json_path, md_path, ply


def _say_results(
    args: argparse.Namespace,
    out: str,
    json_path: str,
    md_path: str,
    ply: str | None,
    t_start: float,
) -> None:
    """Where the run's results are."""
    say(f"done in {time.monotonic() - t_start:.0f} s")
    say(f"report:       {json_path}")
    say(f"              {md_path}")
    say(
        f"trajectories: {os.path.join(out, 'trajectories')}  "
        f"(plot: {os.path.join(out, 'trajectories.png')})"
    )
    if ply:
        say(f"team map:     {ply}")
    if args.record:
        say(
            f"video:        {os.path.join(out, 'video', 'rviz.mp4')}  (final view: "
            f"{os.path.join(out, 'video', 'map.png')})"
        )


if __name__ == "__main__":
    sys.exit(main())
