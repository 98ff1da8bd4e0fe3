"""Benchmarks behind ``scripts/bench``: each prints ``name value unit`` lines; all go to bench.json.

Speed lives here, not in tests (tests must not depend on machine speed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Callable, Iterator

from .paths import CONFIG_DIR, SHARED_DATA

Figure = tuple[str, float, str]
SHARED = SHARED_DATA
REDKITCHEN = os.path.join(SHARED, "redkitchen_0000_0599")
KITTI = os.path.join(SHARED, "kitti_clip_straight", "sequences", "00")
EUROC = os.path.join(SHARED, "euroc_v101_static95")


def bench_render() -> Iterator[Figure]:
    import cv2

    cv2.setNumThreads(1)
    yield ("render_fps_640x480_one_core", render_fps(), "frames/s")


def render_fps(frames: int = 60, camera=None, noise: bool = True) -> float:
    """Frames per second of ``Renderer.render`` at the camera's size on ONE core (noise on).

    Uses the first robot's route of the 'revisit' scenario; textures are built in a warm-up pass
    first, so the figure is the steady-state rendering rate.
    """
    import cv2
    import numpy as np

    from ..synthetic.render import DEFAULT_CAMERA, NoiseConfig, Renderer
    from ..synthetic.scenarios import make_scenario
    from ..synthetic.world import build_world

    camera = camera or DEFAULT_CAMERA
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        scenario = make_scenario("revisit", seed=0, robots=2)
        world = build_world(scenario.layout, seed=0)
        renderer = Renderer(world, camera, NoiseConfig(enabled=noise))
        traj = scenario.trajectories[0]
        idx = np.linspace(0, len(traj.stamps_s) - 1, max(1, frames)).astype(int)
        poses = [traj.poses_se3[i] @ scenario.mount(traj.robot_id) for i in idx]
        for T in poses:
            renderer.render(T)  # warm-up: build the textures this route sees
        start = time.perf_counter()
        for k, T in enumerate(poses):
            renderer.render(T, noise_seed=k)
        elapsed = time.perf_counter() - start
    finally:
        cv2.setNumThreads(threads)
    return len(poses) / elapsed


def bench_bow() -> Iterator[Figure]:
    from ..bow import Vocabulary, bench_transform
    from ..default_vocabulary import ensure_default_vocabulary

    vocab = Vocabulary.load(ensure_default_vocabulary())
    yield ("bow_transform_1000_descriptors", bench_transform(vocab), "ms")


def _vo_runs():
    """(name, sequence, ground robot, paced) of the odometry benchmarks: a synthetic (wheeled) robot
    with an RGB-D and with a stereo camera, RedKitchen (hand-held RGB-D; whole, whole paced at the
    camera's 30 Hz as a live camera delivers it, as two robots, and its colour images alone as a
    monocular camera's), the KITTI clip (stereo,
    1226x370 at 10 Hz) and the EuRoC clip (stereo, 752x480 at 20 Hz) when the shared data is
    present. Unpaced runs hand over the next frame as soon as tracking returns. Each with the
    camera preset scripts/demo picks for its folder ('' for synthetic worlds)."""
    import dataclasses

    from ..camera_presets import preset_for_dataset
    from ..datasets import read_euroc, read_kitti, read_tum, split_ranges
    from ..datasets.synthetic import read_synthetic
    from ..playback import SYNTHETIC_STEREO_BASELINE_M
    from ..synthetic.generate import generate

    world = read_synthetic(generate("revisit"))
    yield "revisit_robot_1", world.sequences[1], True, False, ""
    stereo = read_synthetic(generate("revisit", stereo_baseline_m=SYNTHETIC_STEREO_BASELINE_M))
    seq = stereo.sequences[1]
    camera = dataclasses.replace(seq.camera, sensor="stereo")
    yield "stereo_revisit_robot_1", dataclasses.replace(seq, camera=camera), True, False, ""
    if os.path.isdir(REDKITCHEN):
        seq, preset = read_tum(REDKITCHEN), preset_for_dataset(REDKITCHEN)
        yield "redkitchen", seq, False, False, preset
        yield "redkitchen_paced", seq, False, True, preset
        for part in split_ranges(seq, "0-299,300-599"):
            yield f"redkitchen_{part.name.rsplit('_', 1)[1]}", part, False, False, preset
        mono = dataclasses.replace(seq, camera=dataclasses.replace(seq.camera, sensor="mono"))
        yield "mono_redkitchen", mono, False, False, preset  # its colour images only
    if os.path.isdir(KITTI):
        yield "stereo_kitti_clip", read_kitti(KITTI), False, False, preset_for_dataset(KITTI)
    if os.path.isdir(EUROC):
        yield "stereo_euroc_static", read_euroc(EUROC), False, False, preset_for_dataset(EUROC)


def bench_vo() -> Iterator[Figure]:
    """Tracking time with local mapping running alongside, keyframes/s, ATE and keyframe message
    size."""

    import numpy as np

    from ..camera_presets import load_preset
    from ..config import load_yaml_config, with_values
    from ..evaluation.vo_run import keyframe_ate, run_sequence
    from ..geometry import path_length
    from ..vo.config import VoConfig

    for name, seq, ground, paced, preset in _vo_runs():
        cfg = load_yaml_config(
            VoConfig, os.path.join(CONFIG_DIR, "client.yaml"), "vo", load_preset(preset).get("vo")
        )
        duration = seq.stamps_s[-1] - seq.stamps_s[0]
        rate_hz = (len(seq) - 1) / duration if paced else None
        # As scripts/demo runs them: synthetic robots are ground robots.
        run = run_sequence(seq, with_values(cfg, {"planar": {"enabled": ground}}), rate_hz=rate_hz)
        if not paced:
            _VO_RUNS[name] = (run, seq)
        yield (f"vo_{name}_track_ms_mean", float(np.mean(run.track_ms)), "ms")
        yield (f"vo_{name}_track_ms_p95", float(np.percentile(run.track_ms, 95)), "ms")
        yield (f"vo_{name}_keyframes_per_s", run.keyframes_created / duration, "1/s")
        ate = keyframe_ate(run, seq)
        yield (f"vo_{name}_keyframe_ate", ate, "m")
        yield (
            f"vo_{name}_keyframe_ate_percent_of_path",
            100 * ate / max(path_length(seq.frame_poses()), 1e-9),
            "%",
        )
        yield (f"vo_{name}_lost_frames", float(np.count_nonzero(~run.ok)), "frames")
        yield (f"vo_{name}_mapping_backlog_max", float(run.mapping_backlog.max()), "keyframes")
        yield (
            f"vo_{name}_frames_mapping_behind",
            float(np.count_nonzero(run.mapping_backlog > 1)),
            "frames",
        )
        size = _keyframe_msg_bytes(run.keyframes, seq.camera)
        if size is not None:
            yield (f"vo_{name}_keyframe_msg_bytes_mean", size, "bytes")


def _keyframe_msg_bytes(keyframes, camera):
    """The mean size of the keyframes' whole-keyframe messages, serialized as ROS sends them."""
    import io

    from ..uplink.records import keyframe_record
    from ..wire.codec import encode

    try:
        from ..ros.wire_bridge import to_ros
    except ImportError:  # no catkin workspace sourced: no generated messages
        return None
    sizes = []
    for kf in keyframes:
        buf = io.BytesIO()
        to_ros(encode(keyframe_record(kf, 1, camera), frame_id="robot_1/map")).serialize(buf)
        sizes.append(buf.tell())
    return sum(sizes) / len(sizes) if sizes else None


_VO_RUNS: dict = {}  # name -> (VoRun, Sequence), filled by bench_vo for bench_server


def bench_server() -> Iterator[Figure]:
    """Server cost per incoming keyframe (insert + query + verification) on two robots' keyframes
    (RedKitchen halves when present, else the synthetic revisit robots)."""
    import time

    import numpy as np

    from ..bow import Vocabulary
    from ..default_vocabulary import ensure_default_vocabulary
    from ..team.config import ServerConfig
    from ..team.server import TeamServer
    from ..uplink.records import keyframe_record

    if not _VO_RUNS:
        list(bench_vo())
    halves = [k for k in _VO_RUNS if k.startswith("redkitchen_")] or ["revisit_robot_1"]
    server = TeamServer(ServerConfig(robots=[1, 2]), Vocabulary.load(ensure_default_vocabulary()))
    records = []
    for robot_id, name in enumerate(halves, 1):
        run, seq = _VO_RUNS[name]
        for kf in run.keyframes:
            records.append(keyframe_record(kf, robot_id, seq.camera))
    records.sort(key=lambda r: r.stamp_s)
    t0 = time.perf_counter()
    for rec in records:
        server.add_keyframe(rec)
    wall = time.perf_counter() - t0
    yield ("server_ms_per_keyframe_mean", float(np.mean(server.keyframe_ms)), "ms")
    yield ("server_ms_per_keyframe_max", float(np.max(server.keyframe_ms)), "ms")
    yield ("server_keyframes_per_s_capacity", len(records) / wall, "1/s")
    yield ("server_merges", float(len(server.merges)), "merges")
    yield from _bench_store(records)


def _bench_store(records) -> Iterator[Figure]:
    """The durable map store's cost: the same keyframes through the server with the store on and
    off, in turn (the machine is noisy: medians of alternating runs)."""
    import tempfile

    import numpy as np

    from ..bow import Vocabulary
    from ..default_vocabulary import ensure_default_vocabulary
    from ..team.config import ServerConfig
    from ..team.durable import DurableServer
    from ..team.server import TeamServer

    vocab = Vocabulary.load(ensure_default_vocabulary())
    walls = {"off": [], "on": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(4):
            mode = ("off", "on")[k % 2]
            path = os.path.join(tmp, f"map{k}.db") if mode == "on" else None
            durable = DurableServer(
                ServerConfig(robots=[1, 2]), lambda cfg: TeamServer(cfg, vocab), path
            )
            t0 = time.perf_counter()
            for rec in records:
                durable.add_keyframe(rec)
            walls[mode].append(1e3 * (time.perf_counter() - t0) / len(records))
            if mode == "on":
                size_mb = os.path.getsize(path) / 1e6
            durable.close()
    off, on = float(np.median(walls["off"])), float(np.median(walls["on"]))
    yield ("server_ms_per_keyframe_store_off", off, "ms")
    yield ("server_ms_per_keyframe_store_on", on, "ms")
    yield ("server_store_cost", 100.0 * (on - off) / off, "%")
    yield ("server_store_mb_per_keyframe", size_mb / len(records), "MB")


def bench_pose_graph() -> Iterator[Figure]:
    from ..team.synthetic_team import bench_full_optimization

    yield ("pose_graph_full_optimization_1000_keyframes", bench_full_optimization(1000, 4), "ms")


def bench_server_scale(run_dir=None, rate=1.0, out_dir=".") -> Iterator[Figure]:
    from .bench_server_scale import bench_server_scale as bench

    yield from bench(run_dir=run_dir, rate=rate, out_dir=out_dir)


REGISTRY: dict[str, Callable[..., Iterator[Figure]]] = {
    "render": bench_render,
    "bow": bench_bow,
    "vo": bench_vo,
    "server": bench_server,
    "pose_graph": bench_pose_graph,
    "server_scale": bench_server_scale,
}
# Only with --only: its first run synthesises eight robots' keyframe streams (about 20 minutes,
# cached), every run replays 90 s of them in real time.
NOT_BY_DEFAULT = {"server_scale"}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--only", choices=sorted(REGISTRY), help="run one benchmark")
    p.add_argument("--out", default="bench.json", help="where to write the figures (JSON)")
    p.add_argument(
        "--run",
        help="server_scale: replay this recorded demo run (RUN/run.bag) instead of the synthetic "
        "8-robot multi streams",
    )
    p.add_argument(
        "--rate", type=float, default=1.0, help="server_scale: replay at RATE x real time"
    )
    args = p.parse_args(argv)
    if args.rate <= 0:
        p.error("--rate must be > 0")
    names = [args.only] if args.only else [n for n in REGISTRY if n not in NOT_BY_DEFAULT]
    options = {
        "server_scale": {
            "run_dir": args.run,
            "rate": args.rate,
            "out_dir": os.path.dirname(os.path.abspath(args.out)),
        }
    }
    figures = {}
    for name in names:
        t0 = time.monotonic()
        try:
            for fig, value, unit in REGISTRY[name](**options.get(name, {})):
                figures[fig] = {"value": value, "unit": unit}
                print(f"{fig} {value:.4g} {unit}", flush=True)
        except ImportError as exc:
            print(f"# {name}: skipped ({exc})", flush=True)
        print(f"# {name}: {time.monotonic() - t0:.1f} s", file=sys.stderr, flush=True)
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump(figures, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
