"""What to play for which robot, and when: sources resolved into robot streams, and the schedule.

A *source* is a synthetic scenario, a dataset folder (TUM or KITTI, optionally split into robots by
frame ranges) or a rosbag. :func:`load_streams` turns the first two into :class:`RobotStream` s with
ground truth in one shared world frame; :func:`build_schedule` orders all robots' frames on one
playback timeline (robots start together unless the original timing is kept).
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field

import numpy as np

from .datasets import (
    DatasetError,
    Frame,
    Sequence,
    is_euroc,
    parse_ranges,
    read_euroc,
    read_kitti,
    read_tum,
    split_equal,
    split_ranges,
)
from .errors import CoopSlamError

PLAYBACK_T0_S = 1.0  # first sim time when robots start together (ROS time 0 means "unset")
# The stereo baseline of synthetic robots playing stereo cameras (a ZED's) [m].
SYNTHETIC_STEREO_BASELINE_M = 0.12
# A monocular camera plays the colour image of RGB-D data or the left image of a stereo pair.
PLAYABLE_SENSORS = ("rgbd", "stereo", "mono")
# A robot's ground truth as the player publishes it (a sensor bag's is optional; its cameras:
# coop_slam.bag_topics).
GROUND_TRUTH_TOPIC = re.compile(r"^/robot_(\d+)/ground_truth/pose$")


class PlaybackError(CoopSlamError):
    """A playback source cannot be resolved (unknown scenario, bad split, missing folder)."""


@dataclass
class RobotStream:
    robot_id: int  # 1-based
    sequence: Sequence
    start_offset_s: float = 0.0

    @property
    def name(self) -> str:
        return f"robot_{self.robot_id}"


@dataclass
class Source:
    kind: str  # "scenario", "dataset" or "bag"
    streams: list[RobotStream] = field(default_factory=list)
    folder: str = ""  # data folder (generated world, dataset folder or bag file)
    meta: dict = field(default_factory=dict)  # synthetic world metadata (overlap events, ...)


def camera_topics(robot_id: int, sensor: str) -> dict:
    """A robot's camera topics, as the player publishes them and a client subscribes to them:
    ``image`` (colour of an RGB-D or monocular camera, left of a stereo pair), ``second`` (depth,
    or the right image; a monocular camera has none) and ``infos`` (name -> camera info topic). ROS
    stereo conventions for a pair; a monocular camera publishes as an RGB-D camera's colour."""
    cam = f"/robot_{robot_id}/camera"
    if sensor == "mono":
        return {
            "image": f"{cam}/color/image_raw",
            "infos": {"color": f"{cam}/color/camera_info"},
        }
    if sensor == "stereo":
        return {
            "image": f"{cam}/left/image_rect",
            "second": f"{cam}/right/image_rect",
            "infos": {"left": f"{cam}/left/camera_info", "right": f"{cam}/right/camera_info"},
        }
    return {
        "image": f"{cam}/color/image_raw",
        "second": f"{cam}/depth/image_raw",
        "infos": {"color": f"{cam}/color/camera_info"},
    }


def camera_topic_names(robot_id: int) -> set[str]:
    """Every camera topic of a robot a client may subscribe to, whatever its sensor: images and
    camera infos (see :func:`camera_topics`)."""
    names = set()
    for sensor in PLAYABLE_SENSORS:
        for v in camera_topics(robot_id, sensor).values():
            names.update(v.values() if isinstance(v, dict) else [v])
    return names


def image_topic(robot_id: int, sensor: str) -> str:
    """The topic of a robot's main image (see :func:`camera_topics`)."""
    return camera_topics(robot_id, sensor)["image"]


def parse_robot_ids(text) -> list[int] | None:
    """``"2"`` or ``"1,3"`` (or a list) -> robot ids; empty -> None."""
    if not text:
        return None
    try:
        ids = [int(x) for x in (text.split(",") if isinstance(text, str) else text)]
    except ValueError:
        raise PlaybackError(f"robot ids must be integers, comma-separated: '{text}'") from None
    if any(i < 1 for i in ids) or len(set(ids)) != len(ids):
        raise PlaybackError(f"robot ids must be distinct and >= 1: '{text}'")
    return sorted(ids)


def parse_sensors(text: str | None, n_robots: int | None = None) -> list[str] | None:
    """``rgbd,stereo,stereo`` (one per robot, or one for all) -> list; None for none given."""
    if not text:
        return None
    sensors = [s.strip() for s in text.split(",")]
    unknown = sorted(set(sensors) - set(PLAYABLE_SENSORS))
    if unknown:
        raise PlaybackError(
            f"unknown sensor(s) {', '.join(unknown)}; use {', '.join(PLAYABLE_SENSORS)}"
        )
    if n_robots is not None and len(sensors) not in (1, n_robots):
        raise PlaybackError(
            f"{len(sensors)} sensors given for {n_robots} robots (one, or one each)"
        )
    return sensors


def _with_sensor(stream: RobotStream, sensor: str) -> RobotStream:
    """The stream played as ``sensor``, when its data has what that sensor needs."""
    seq = stream.sequence
    if sensor == seq.camera.sensor:
        return stream
    frame = seq.frames[0]
    if sensor == "stereo" and (frame.right_path is None or seq.camera.baseline_m <= 0):
        raise PlaybackError(f"{stream.name}: its data has no right images to play a stereo camera")
    if sensor == "rgbd" and frame.depth_path is None:
        raise PlaybackError(f"{stream.name}: its data has no depth images to play an RGB-D camera")
    # A monocular camera: the colour (left) image and its intrinsics; no baseline.
    baseline_m = 0.0 if sensor == "mono" else seq.camera.baseline_m
    camera = dataclasses.replace(seq.camera, sensor=sensor, baseline_m=baseline_m)
    return dataclasses.replace(stream, sequence=dataclasses.replace(seq, camera=camera))


def _read_dataset(folder: str, camera_file: str | None) -> Sequence:
    if os.path.isfile(os.path.join(folder, "calib.txt")):
        return read_kitti(folder)
    if is_euroc(folder):
        return read_euroc(folder)
    return read_tum(folder, camera_file=camera_file)


def load_streams(
    scenario: str | None = None,
    dataset: str | None = None,
    split: str | None = None,
    robots: int | None = None,
    seed: int = 0,
    camera_file: str | None = None,
    start_offsets_s: list[float] | None = None,
    progress=None,
    world_params: dict | None = None,
    sensors: list[str] | None = None,
    only_robots: list[int] | None = None,
) -> Source:
    """Resolve a scenario name or a dataset folder into robot streams (see module doc).
    ``sensors`` (one for all robots, or one each) plays robots as RGB-D, stereo or monocular
    cameras where their data allows (a synthetic world is rendered with right images when one is
    stereo; a monocular camera plays the colour or left image of any data); None: as the data
    is. ``only_robots``: play these robots of the source alone, with their ids (a later session
    of a team, ``scripts/demo --only-robots``)."""
    if (scenario is None) == (dataset is None):
        raise PlaybackError("give exactly one of a synthetic scenario or a dataset folder")
    if scenario is not None:
        from .datasets.synthetic import read_synthetic
        from .synthetic.generate import generate

        params = dict(world_params or {})
        if robots is not None:
            params["robots"] = robots
        if sensors and "stereo" in sensors:
            params.setdefault("stereo_baseline_m", SYNTHETIC_STEREO_BASELINE_M)
        folder = generate(scenario, seed=seed, progress=progress, **params)
        world = read_synthetic(folder)
        seqs = [world.sequences[k] for k in sorted(world.sequences)]
        ids = sorted(world.sequences)
        if split is not None:
            raise PlaybackError("--split applies to a dataset folder, not to a synthetic scenario")
        streams = [RobotStream(robot_id=i, sequence=s) for i, s in zip(ids, seqs)]
        source = Source("scenario", streams, folder, dict(world.meta))
    else:
        try:
            seq = _read_dataset(dataset, camera_file)
        except DatasetError as exc:
            raise PlaybackError(str(exc)) from None
        if split is not None:
            parts = split_ranges(seq, parse_ranges(split))
            if robots is not None and robots != len(parts):
                raise PlaybackError(
                    f"--robots {robots} disagrees with --split, which gives {len(parts)}"
                )
        else:
            parts = split_equal(seq, robots or 1)
        streams = [RobotStream(robot_id=k + 1, sequence=s) for k, s in enumerate(parts)]
        source = Source("dataset", streams, dataset)
    if sensors:
        if len(sensors) not in (1, len(source.streams)):
            raise PlaybackError(
                f"{len(sensors)} sensors given for {len(source.streams)} robots (one, or one each)"
            )
        each = sensors * len(source.streams) if len(sensors) == 1 else sensors
        source.streams = [_with_sensor(s, k) for s, k in zip(source.streams, each)]
    if start_offsets_s:
        if len(start_offsets_s) != len(source.streams):
            raise PlaybackError(
                f"{len(start_offsets_s)} start offsets given for {len(source.streams)} robots"
            )
        for stream, off in zip(source.streams, start_offsets_s):
            if not np.isfinite(off) or off < 0:
                raise PlaybackError(f"start offset {off} of {stream.name} must be >= 0 s")
            stream.start_offset_s = float(off)
    if only_robots:
        ids = [s.robot_id for s in source.streams]
        unknown = sorted(set(only_robots) - set(ids))
        if unknown:
            raise PlaybackError(f"robots {unknown} are not in this source (it has {ids})")
        source.streams = [s for s in source.streams if s.robot_id in only_robots]
    return source


def ground_truth_by_frame(stream: RobotStream) -> dict[int, np.ndarray]:
    """Frame index -> ground-truth ``T_world_cam`` of a robot's frames (NaN where there is none)."""
    frames = stream.sequence.frames
    return dict(zip((f.index for f in frames), stream.sequence.frame_poses()))


def load_run_source(options: dict, progress=None) -> Source:
    """:func:`load_streams` from a run's options, keyed as ``scripts/demo``'s arguments and its
    ``run.json`` (scenario, dataset, split, robots, seed, camera; duration for a scenario)."""
    duration_s = options.get("duration")
    return load_streams(
        scenario=options.get("scenario"),
        dataset=options.get("dataset"),
        split=options.get("split"),
        robots=options.get("robots"),
        seed=options.get("seed") or 0,
        camera_file=options.get("camera"),
        progress=progress,
        world_params={"duration_s": duration_s} if duration_s else None,
        sensors=parse_sensors(options.get("sensors")),
        only_robots=parse_robot_ids(options.get("only_robots")),
    )


@dataclass(frozen=True)
class ScheduledFrame:
    play_s: float  # sim time at which the frame is published (also its header stamp)
    robot_id: int
    frame: Frame


def build_schedule(streams: list[RobotStream], keep_timing: bool = False) -> list[ScheduledFrame]:
    """All robots' frames on one timeline, sorted by play time (ties by robot id).

    Robots start together at PLAYBACK_T0_S (plus their start offsets) unless ``keep_timing``, which
    keeps each segment's original stamps so a split sequence plays as it was recorded.
    """
    out = []
    for stream in streams:
        stamps = stream.sequence.stamps_s
        if len(stamps) == 0:
            continue
        if np.any(np.diff(stamps) <= 0):
            raise PlaybackError(f"{stream.name}: frame timestamps are not strictly increasing")
        shift = stream.start_offset_s + (0.0 if keep_timing else PLAYBACK_T0_S - stamps[0])
        out.extend(
            ScheduledFrame(float(t + shift), stream.robot_id, f)
            for t, f in zip(stamps, stream.sequence.frames)
        )
    out.sort(key=lambda s: (s.play_s, s.robot_id))
    return out


def group_simultaneous(
    schedule: list[ScheduledFrame], tol_s: float = 1e-6
) -> list[list[ScheduledFrame]]:
    """Consecutive frames with the same play time, published together in lock-step mode."""
    groups: list[list[ScheduledFrame]] = []
    for item in schedule:
        if groups and abs(groups[-1][0].play_s - item.play_s) <= tol_s:
            groups[-1].append(item)
        else:
            groups.append([item])
    return groups


def parse_clock_offsets(text: str) -> dict[int, float]:
    """``"2:0.3,3:-0.1"`` -> {2: 0.3, 3: -0.1}: robots whose clock runs that far ahead of the
    master's [s] (rehearsal: ``scripts/demo --clock-offset``)."""
    out: dict[int, float] = {}
    for part in filter(None, (p.strip() for p in (text or "").split(","))):
        robot, sep, seconds = part.partition(":")
        try:
            if not sep:
                raise ValueError
            rid, offset = int(robot), float(seconds)
        except ValueError:
            raise PlaybackError(
                f"clock offset '{part}' is not ROBOT:SECONDS (for example 2:0.3)"
            ) from None
        if rid < 1 or not np.isfinite(offset) or rid in out:
            raise PlaybackError(f"clock offset '{part}': robot id >= 1, once, finite seconds")
        if offset <= -PLAYBACK_T0_S + 0.1:  # its first images would be stamped at or before 0
            raise PlaybackError(
                f"clock offset '{part}': a clock behind by {PLAYBACK_T0_S - 0.1:g} s or more "
                f"cannot be rehearsed (playback starts at {PLAYBACK_T0_S:g} s)"
            )
        out[rid] = offset
    return out
