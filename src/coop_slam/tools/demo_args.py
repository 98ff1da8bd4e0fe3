"""The options of ``scripts/demo``: what they mean (its ``--help``) and which combinations it
refuses before any data is prepared."""

from __future__ import annotations

import argparse
import os

import numpy as np

from .sequence_args import add_duration_argument, check_duration

DESCRIPTION = (
    "The main job behind ``scripts/demo``: prepare data, launch the system headless, follow it "
    "with a progress line, and write the report."
)
DEFAULT_SCENARIO = "team"


def parse_args(argv=None) -> argparse.Namespace:
    """The demo's options from ``argv`` (the command line when None); exits with argparse's
    usage and message on a bad one."""
    parser = argparse.ArgumentParser(prog="scripts/demo", description=DESCRIPTION)
    # The order options are added in is the order --help lists them.
    _add_source_options(parser)
    _add_system_options(parser)
    _add_hosts_options(parser)
    _add_run_options(parser)
    args = parser.parse_args(argv)
    if args.scenario is None and args.dataset is None and args.bag is None:
        args.scenario = DEFAULT_SCENARIO
    _check(parser, args)
    return args


def operator_request(text: str) -> tuple[int, int, float]:
    """``A,B@T`` -> (robot A, robot B, seconds into the run)."""
    try:
        robots, at = text.split("@")
        a, b = (int(r) for r in robots.split(","))
        t_s = float(at)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected A,B@T (two robot ids, seconds into the run), e.g. 1,2@20"
        ) from None
    if a == b or min(a, b) < 1 or not np.isfinite(t_s) or t_s < 0:
        raise argparse.ArgumentTypeError(
            f"{text!r}: needs two different robot ids >= 1 and a time >= 0 s"
        )
    return a, b, t_s


def _add_source_options(p: argparse.ArgumentParser) -> None:
    """What is played, by which robots, how fast, and whether RViz is recorded."""
    src = p.add_mutually_exclusive_group()
    src.add_argument("--scenario", help=f"synthetic scenario (default: {DEFAULT_SCENARIO})")
    src.add_argument("--dataset", help="TUM RGB-D or KITTI odometry folder")
    src.add_argument("--bag", help="rosbag file to replay")
    p.add_argument("--robots", type=int, default=None, help="number of robots")
    p.add_argument(
        "--sensors",
        help="each robot's camera, comma-separated, or one for all: rgbd, stereo, mono (e.g. "
        "rgbd,stereo,stereo); default: RGB-D for synthetic worlds, what a dataset or bag has",
    )
    p.add_argument("--split", help="inclusive frame ranges, one robot each: 0-299,300-599")
    p.add_argument(
        "--only-robots",
        metavar="IDS",
        help="run only these robots of the scenario or split, with their ids (comma-separated), "
        "e.g. a later session: --only-robots 2 --load-map FILE",
    )
    p.add_argument(
        "--keep-timing",
        action="store_true",
        help="play split segments at their original times (default: all start together)",
    )
    p.add_argument("--seed", type=int, default=0, help="synthetic world seed")
    add_duration_argument(p)
    p.add_argument("--camera", help="camera.yaml for a dataset folder without one")
    p.add_argument(
        "--camera-preset",
        metavar="NAME[,NAME...]",
        help="the clients' camera preset (config/cameras/: kitti, euroc, tum_fr1, tum_fr2, "
        "tum_fr3, kinect_v1, realsense_d435), one per robot or one for all; default: a dataset "
        "folder's own (a KITTI folder: kitti), none for synthetic worlds and bags; 'none' for none",
    )
    p.add_argument(
        "--rate", type=float, default=None, help="play at RATE x real time instead of lock-step"
    )
    rec = p.add_mutually_exclusive_group()
    rec.add_argument(
        "--record",
        dest="record",
        action="store_true",
        default=True,
        help="record RViz headless to MP4 + PNG (the default)",
    )
    rec.add_argument("--no-record", dest="record", action="store_false", help="do not record RViz")


def _add_system_options(p: argparse.ArgumentParser) -> None:
    """How the server and clients are configured, and what the run does to them."""
    p.add_argument("--server-config", help="server YAML (default: config/server.yaml)")
    p.add_argument("--client-config", help="client YAML (default: config/client.yaml)")
    p.add_argument(
        "--no-markers",
        action="store_true",
        help="clients do not look for other robots' markers (rendezvous without cue)",
    )
    p.add_argument(
        "--ground-robots",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the cameras sit on bases driving on a level floor, so local BA keeps them level "
        "(client vo.planar.enabled); default: on for synthetic scenarios of wheeled robots, off "
        "for hand-held ones (kitchen), datasets and bags",
    )
    p.add_argument(
        "--rendezvous",
        action="append",
        default=[],
        type=operator_request,
        metavar="A,B@T",
        help="operator trigger: at T seconds into the run, tell the server (its ~rendezvous "
        "service) that robots A and B are together; repeatable",
    )
    p.add_argument(
        "--save-map",
        metavar="FILE",
        help="at the end, save the team map to FILE (the server's ~save_map) for a later session",
    )
    p.add_argument(
        "--load-map",
        metavar="FILE",
        help="start the server from a team map saved before (--save-map): a later session",
    )
    p.add_argument(
        "--faults",
        metavar="SPEC",
        help="fault injection: server-kill@T, client-kill:K@T (kill -9 at T s sim time, restarted "
        "by roslaunch), drop:P (a radio relay drops a share P of the keyframe messages); "
        "comma-separated, e.g. server-kill@25,drop:0.1",
    )
    p.add_argument(
        "--vocabulary",
        metavar="FILE",
        help="the team's vocabulary (scripts/train_vocabulary; default: the one setup builds)",
    )
    p.add_argument(
        "--clock-offset",
        action="append",
        default=[],
        type=clock_offset_spec,
        metavar="ROBOT:SECONDS",
        help="rehearse an unsynchronized clock: robot ROBOT's clock runs SECONDS ahead of the "
        "master's (its images and messages are stamped on it); the server estimates it "
        "(clock_offset_s in /server/stats and the report); repeatable",
    )
    p.add_argument(
        "--low-bandwidth",
        action="store_true",
        help="low-bandwidth mode: each new keyframe goes as its place signature (pose and BoW "
        "vector), whole only when the server asks for it (a place recognition or rendezvous "
        "candidate, a loop); server pull.* and client uplink.mode",
    )


def _add_hosts_options(p: argparse.ArgumentParser) -> None:
    """A team across hosts and radio links (network namespaces on this machine; needs root)."""
    hosts = p.add_argument_group("hosts and radio links (root: network namespaces and tc)")
    hosts.add_argument(
        "--hosts",
        action="store_true",
        help="run the master and server on a station host and every robot on a host of its own "
        "(one network namespace each, joined by a bridge: the radio); a robot's camera is "
        "played on its own host",
    )
    hosts.add_argument(
        "--link-rate",
        type=float,
        default=0.0,
        metavar="KBIT",
        help="with --hosts: every robot's radio link limited to KBIT kbit/s each way (tc tbf)",
    )
    hosts.add_argument(
        "--outage",
        action="append",
        default=[],
        type=outage_spec,
        metavar="ROBOT@START-END",
        help="with --hosts: robot ROBOT's radio link is down from START to END s of data time; "
        "repeatable",
    )


def clock_offset_spec(text: str) -> tuple[int, float]:
    """``ROBOT:SECONDS`` -> (robot, seconds)."""
    from ..playback import PlaybackError, parse_clock_offsets

    try:
        ((robot, seconds),) = parse_clock_offsets(text).items()
    except (PlaybackError, ValueError) as exc:
        raise argparse.ArgumentTypeError(str(exc) or f"'{text}' is not ROBOT:SECONDS") from None
    return robot, seconds


def outage_spec(text: str) -> tuple[int, float, float]:
    """``ROBOT@START-END`` -> (robot, start s, end s)."""
    try:
        robot, span = text.split("@")
        start, end = (float(v) for v in span.split("-"))
        robot_id = int(robot)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--outage {text}: expected ROBOT@START-END in seconds, e.g. 2@20-50"
        ) from None
    if not 0 <= start < end:
        raise argparse.ArgumentTypeError(f"--outage {text}: needs 0 <= START < END")
    return robot_id, start, end


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """Where the results go and how long the run may take."""
    p.add_argument("--out", help="results folder (default: results/<date>-<source>)")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds")
    p.add_argument(
        "--no-clients", action="store_true", help="only play the data (no clients, no server)"
    )
    p.add_argument(
        "--settle",
        type=float,
        default=2.0,
        help="seconds to wait at least after the last frame for the last keyframes and merges "
        "(then until the server is idle)",
    )


def _check(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse (``p.error``: usage, message, exit 2) combinations that cannot run. What needs the
    source's robots (``--rendezvous`` ids, ``--only-robots``) is checked once the data is ready."""
    if args.robots is not None and not 1 <= args.robots <= 8:
        p.error("--robots must be between 1 and 8")
    if args.rate is not None and args.rate <= 0:
        p.error("--rate must be > 0")
    check_duration(p, args)
    if args.split and not args.dataset:
        p.error("--split needs --dataset")
    if args.bag and args.clock_offset:
        p.error("--clock-offset rehearses a robot's clock on a played source; a bag has its own")
    if args.bag and (args.robots is not None or args.keep_timing or args.camera or args.sensors):
        p.error("--bag: robots, timing, camera and sensors come from the bag")
    if args.faults:
        from .faults import FaultError, parse_faults

        try:
            parse_faults(args.faults)
        except FaultError as exc:
            p.error(str(exc))
    if args.only_robots and args.bag:
        p.error("--only-robots: a bag plays the robots it has")
    if args.load_map and not os.path.isfile(args.load_map):
        p.error(f"--load-map: file not found: {args.load_map}")
    if (args.faults or args.save_map or args.load_map) and args.no_clients:
        p.error("--faults, --save-map and --load-map need the server: drop --no-clients")
    if (args.link_rate or args.outage) and not args.hosts:
        p.error("--link-rate and --outage shape the hosts' radio links: add --hosts")
    if args.hosts and (args.bag or args.no_clients):
        p.error("--hosts plays a scenario or dataset with clients (a bag plays on one host)")
    if args.link_rate < 0:
        p.error("--link-rate must be >= 0 [kbit/s]")
    if args.sensors:
        from ..playback import PlaybackError, parse_sensors

        try:
            parse_sensors(args.sensors, args.robots)
        except PlaybackError as exc:
            p.error(f"--sensors: {exc}")
