"""Render a scenario into a dataset folder: one TUM RGB-D folder per robot plus ``world.yaml``.

Layout of the output folder::

    world.yaml            scenario, seed, parameters, robots, T_base_cam, markers, overlap events
    robot_<id>/           TUM RGB-D: rgb/*.jpg, depth/*.png (16 bit, 5000 per metre), rgb.txt,
                          depth.txt, groundtruth.txt (T_world_cam of the optical frame in the shared
                          world frame), groundtruth_base.txt (T_world_base), camera.yaml; with a
                          stereo baseline also right/*.jpg and right.txt (the right camera of a
                          rectified pair, ``camera.baseline_m`` along the optical x axis)
    .complete             written last: the folder is whole

Outputs are cached under ``${COOP_SLAM_CACHE:-~/.cache/coop_slam}/worlds/<scenario>-<hash>``, the
hash covering every parameter, the routes, the scenario's sensor noise profile and the generator
version; a complete folder is returned as is. The folder is written under a temporary name and
renamed at the end, so readers never see half a world.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

import cv2
import numpy as np
import yaml

from ..camera import CameraModel
from ..datasets import write_camera_yaml, write_tum_trajectory
from ..errors import CoopSlamError
from ..geometry import se3
from .bodies import BODY_SIZE_M, body_model
from .overlap import OverlapConfig, compute_overlap
from .render import DEFAULT_CAMERA, DynamicObject, NoiseConfig, Renderer, exposure_gains
from .scenarios import Scenario, make_scenario
from .world import WALL_HEIGHT_M, build_world

GENERATOR_VERSION = 3
COMPLETE_MARKER = ".complete"
WORLD_FILE = "world.yaml"
_CHUNK_FRAMES = 40


class GenerateError(CoopSlamError):
    """The output folder cannot be written or is in the way."""


def cache_root() -> str:
    root = os.environ.get("COOP_SLAM_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "coop_slam"
    )
    return os.path.join(root, "worlds")


def _params(scenario: Scenario, noise: bool, camera: CameraModel) -> dict:
    params = {  # the camera's baseline_m > 0 (a right camera) gives another world
        "scenario": scenario.name,
        "seed": scenario.seed,
        "robots": len(scenario.trajectories),
        "duration_s": scenario.duration_s,
        "rate_hz": scenario.rate_hz,
        "noise": bool(noise),
        "marker_size_m": scenario.marker_size_m,
        "camera": camera.to_dict(),
        "generator_version": GENERATOR_VERSION,
        # The routes themselves: a changed scenario never reuses an old world from the cache.
        "routes_sha1": _routes_digest(scenario),
        "layout": scenario.layout,
    }
    if scenario.mounts:  # robots' own camera mounts: another world (others keep their keys)
        params["mounts"] = {
            str(r): np.round(T, 6).tolist() for r, T in sorted(scenario.mounts.items())
        }
    if scenario.meta.get("dark"):  # frames of a covered camera: another world
        params["dark"] = scenario.meta["dark"]
    if scenario.noise != NoiseConfig():
        # A scenario's own sensor profile (all of it): worlds with the default profile keep the
        # keys they had before profiles existed, so their cached folders stay valid.
        params["noise_profile"] = dataclasses.asdict(scenario.noise)
    return params


def _routes_digest(scenario: Scenario) -> str:
    h = hashlib.sha1()
    for traj in scenario.trajectories:
        # Rounded, so that last-bit float differences between machines keep the same key.
        h.update(np.round(traj.poses_se3, 6).astype(np.float64).tobytes())
    return h.hexdigest()[:12]


def params_hash(params: dict) -> str:
    return hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:10]


def is_complete(folder: str) -> bool:
    return os.path.isfile(os.path.join(folder, COMPLETE_MARKER)) and os.path.isfile(
        os.path.join(folder, WORLD_FILE)
    )


def _frame_name(stamp_s: float, kind: str = "depth") -> str:
    # Colour as high-quality JPEG, like real RGB-D recordings: 5x smaller and faster to write than
    # PNG of a noisy image; depth stays lossless 16-bit PNG.
    return f"{stamp_s:.6f}.{'png' if kind == 'depth' else 'jpg'}"


def _frame_seed(seed: int, robot_id: int, frame: int) -> int:
    return int(np.random.SeedSequence([seed, robot_id, frame, 11]).generate_state(1)[0])


def _noise_config(scenario: Scenario, noise: bool) -> NoiseConfig:
    """The scenario's sensor profile, or an ideal sensor when ``noise`` is off."""
    return dataclasses.replace(scenario.noise, enabled=bool(noise))


# Rendering state of a worker process (built once per process, textures shared between chunks).
_WORKER: dict = {}


def _render_chunk(job) -> int:
    """Render frames ``frames`` of robot ``robot_id`` and write their PNGs; returns the count."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # one core per worker: the parallelism is across workers
    try:
        return _render_frames(*job)
    finally:
        cv2.setNumThreads(threads)  # workers=1 runs in the caller's process: leave it as it was


def _render_frames(scenario, noise, camera, out_dir, robot_id, frames) -> int:
    cfg = _noise_config(scenario, noise)
    key = (scenario.layout, scenario.seed, tuple(camera.to_dict().values()), repr(cfg))
    if _WORKER.get("key") != key:
        world = build_world(scenario.layout, scenario.seed)
        _WORKER.update(key=key, renderer=Renderer(world, camera, cfg), bodies={})
    renderer, bodies = _WORKER["renderer"], _WORKER["bodies"]
    for t in scenario.trajectories:
        if (t.robot_id, scenario.marker_size_m) not in bodies:
            bodies[t.robot_id, scenario.marker_size_m] = body_model(
                t.robot_id, scenario.marker_size_m
            )
    trajs = {t.robot_id: t for t in scenario.trajectories}
    me = trajs[robot_id]
    # Auto-exposure gain of this camera over the whole sequence (a frame's gain depends on its
    # time only, so chunks agree).
    gain_seed = int(np.random.SeedSequence([scenario.seed, robot_id, 13]).generate_state(1)[0])
    gains = exposure_gains(cfg, gain_seed, me.stamps_s - me.stamps_s[0])
    folder = os.path.join(out_dir, me.name)
    # Fast PNG: level 1 with Huffman-only coding (sensor noise leaves little for LZ77 to find).
    png = [
        cv2.IMWRITE_PNG_COMPRESSION,
        1,
        cv2.IMWRITE_PNG_STRATEGY,
        cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
    ]
    scale = camera.depth_scale
    dark = (scenario.meta.get("dark") or {}).get(str(robot_id))
    T_base_cam = scenario.mount(robot_id)
    for k in frames:
        T_world_cam = me.poses_se3[k] @ T_base_cam
        others = [  # hand-held cameras have no robot body for the others to see
            DynamicObject(t.poses_se3[k], bodies[rid, scenario.marker_size_m])
            for rid, t in trajs.items()
            if rid != robot_id and not scenario.hand_held
        ]
        seed = _frame_seed(scenario.seed, robot_id, k)
        pose_at = None
        if cfg.enabled and cfg.needs_motion:

            def pose_at(dt_s, stamp_s=me.stamps_s[k]):  # sub-frame camera poses
                return me.poses_at(stamp_s + np.asarray(dt_s, float)) @ T_base_cam

        bgr, depth = renderer.render(
            T_world_cam, others, noise_seed=seed, pose_at=pose_at, gain=float(gains[k])
        )
        if dark and dark[0] <= me.stamps_s[k] <= dark[1]:  # the camera is covered
            bgr, depth = np.zeros_like(bgr), np.zeros_like(depth)
        raw = np.round(depth * scale)
        raw[raw > 65535] = 0  # out of the 16-bit range: no measurement rather than a wrong one
        name = _frame_name(me.stamps_s[k])
        rgb_name = _frame_name(me.stamps_s[k], "rgb")
        if not cv2.imwrite(
            os.path.join(folder, "rgb", rgb_name), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95]
        ):
            raise GenerateError(f"cannot write {os.path.join(folder, 'rgb', rgb_name)}")
        if not cv2.imwrite(os.path.join(folder, "depth", name), raw.astype(np.uint16), png):
            raise GenerateError(f"cannot write {os.path.join(folder, 'depth', name)}")
        if camera.baseline_m > 0:
            T_cam_right = se3(t=[camera.baseline_m, 0.0, 0.0])
            right, _ = renderer.render(
                T_world_cam @ T_cam_right, others, noise_seed=seed + 1, gain=float(gains[k])
            )
            path = os.path.join(folder, "right", rgb_name)
            if not cv2.imwrite(path, right, [cv2.IMWRITE_JPEG_QUALITY, 95]):
                raise GenerateError(f"cannot write {path}")
    return len(frames)


def _write_lists(folder: str, stamps_s, stereo: bool) -> None:
    for kind in ("rgb", "depth", "right") if stereo else ("rgb", "depth"):
        with open(os.path.join(folder, f"{kind}.txt"), "w", encoding="utf-8") as fh:
            fh.write(f"# {kind} images of a coop_slam synthetic world\n# timestamp filename\n")
            fh.writelines(f"{s:.6f} {kind}/{_frame_name(s, kind)}\n" for s in stamps_s)


def _world_yaml(
    scenario: Scenario, params: dict, camera: CameraModel, noise: bool, events, ocfg
) -> dict:
    frames = (
        {"world": "z up (REP-103)", "base_link": "the camera carrier: x forward, y left, z up"}
        if scenario.hand_held
        else {"world": "z up (REP-103)", "base_link": "x forward, y left, z up"}
    )
    return {
        "generator_version": GENERATOR_VERSION,
        "scenario": scenario.name,
        "description": " ".join((scenario.description or "").split()),
        "seed": scenario.seed,
        "params": params,
        "params_hash": params_hash(params),
        "world": {
            "layout": scenario.layout,
            "building_origins_xy": [
                [float(v) for v in o]
                for o in build_world(scenario.layout, scenario.seed).building_origins_xy
            ],
            "wall_height_m": WALL_HEIGHT_M,
            "frames": {**frames, "camera": "optical: z forward, x right, y down"},
        },
        # Hand-held: 6-DoF cameras carried by people (no robot bodies or markers, not level).
        "hand_held": bool(scenario.hand_held),
        "start_stamp_s": float(scenario.trajectories[0].stamps_s[0]),
        "frame_count": len(scenario.trajectories[0].stamps_s),
        "rate_hz": scenario.rate_hz,
        "robots": [
            {
                "id": t.robot_id,
                "name": t.name,
                "folder": t.name,
                "marker_id": t.robot_id,
                "T_base_cam": np.asarray(scenario.mount(t.robot_id), float).round(12).tolist(),
            }
            for t in scenario.trajectories
        ],
        "T_base_cam": np.asarray(scenario.T_base_cam, float).round(12).tolist(),
        "markers": {
            "dictionary": "DICT_4X4_50",
            "size_m": scenario.marker_size_m,
            "ids": "robot id",
            "body_size_m": list(BODY_SIZE_M),
        },
        "camera": camera.to_dict(),
        "noise": dataclasses.asdict(_noise_config(scenario, noise)),
        "overlap": events.to_dict(),
        "overlap_config": ocfg.__dict__,
        "meta": {
            k: (float(v) if isinstance(v, (np.floating, float)) else v)
            for k, v in scenario.meta.items()
        },
    }


def _prepare_out_dir(out_dir: str) -> None:
    """Clear a previous, incomplete or different generator output; refuse to touch anything else."""
    if not os.path.exists(out_dir):
        return
    if not os.path.isdir(out_dir):
        raise GenerateError(f"output path {out_dir} exists and is not a folder")
    entries = os.listdir(out_dir)
    if entries and WORLD_FILE not in entries and COMPLETE_MARKER not in entries:
        raise GenerateError(
            f"output folder {out_dir} is not empty and not a synthetic world: choose another one"
        )
    shutil.rmtree(out_dir)


def generate(
    scenario: str = "team",
    seed: int = 0,
    robots: int | None = None,
    duration_s: float | None = None,
    rate_hz: float | None = None,
    noise: bool = True,
    out_dir: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    workers: int = 1,
    camera: CameraModel = DEFAULT_CAMERA,
    overlap_config: OverlapConfig | None = None,
    stereo_baseline_m: float = 0.0,
) -> str:
    """Render ``scenario`` and return its folder (cached: a complete folder is not rendered again).

    ``robots``/``duration_s``/``rate_hz`` None take the scenario's defaults. ``noise`` renders with
    the scenario's sensor noise profile (off: ideal images and exact depth). ``progress(done_frames,
    total_frames)`` is called as frames are written. ``workers`` > 1 renders in that many
    processes (one core each; started with 'spawn', so a calling script needs the usual
    ``if __name__ == "__main__":`` guard). Output is identical whatever ``workers`` is.
    ``stereo_baseline_m`` > 0 also renders each robot's right camera of a stereo pair.
    """
    if stereo_baseline_m < 0 or not np.isfinite(stereo_baseline_m):
        raise GenerateError(f"stereo baseline {stereo_baseline_m} m must be >= 0")
    if stereo_baseline_m > 0:
        camera = dataclasses.replace(camera, baseline_m=float(stereo_baseline_m))
    sc = make_scenario(scenario, seed=seed, robots=robots, duration_s=duration_s, rate_hz=rate_hz)
    params = _params(sc, noise, camera)
    phash = params_hash(params)
    out_dir = os.path.abspath(out_dir or os.path.join(cache_root(), f"{sc.name}-{phash}"))
    if is_complete(out_dir):
        try:
            with open(os.path.join(out_dir, WORLD_FILE), encoding="utf-8") as fh:
                if (yaml.safe_load(fh) or {}).get("params_hash") == phash:
                    return out_dir
        except (OSError, yaml.YAMLError):
            pass  # unreadable: regenerate below
    parent = os.path.dirname(out_dir)
    try:
        os.makedirs(parent, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=os.path.basename(out_dir) + ".tmp-", dir=parent)
    except OSError as exc:
        raise GenerateError(f"cannot create the output folder under {parent}: {exc}") from None
    try:
        _generate_into(
            tmp, sc, params, noise, camera, overlap_config or OverlapConfig(), progress, workers
        )
        if is_complete(out_dir):  # another process finished the same world meanwhile
            shutil.rmtree(tmp, ignore_errors=True)
            return out_dir
        _prepare_out_dir(out_dir)
        try:
            os.rename(tmp, out_dir)
        except OSError:
            if not is_complete(out_dir):  # not a concurrent twin that got there first
                raise
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def _generate_into(tmp, sc: Scenario, params, noise, camera, ocfg, progress, workers) -> None:
    for t in sc.trajectories:
        folder = os.path.join(tmp, t.name)
        os.makedirs(os.path.join(folder, "rgb"))
        os.makedirs(os.path.join(folder, "depth"))
        if camera.baseline_m > 0:
            os.makedirs(os.path.join(folder, "right"))
        _write_lists(folder, t.stamps_s, camera.baseline_m > 0)
        write_tum_trajectory(
            os.path.join(folder, "groundtruth.txt"), t.stamps_s, t.poses_se3 @ sc.mount(t.robot_id)
        )
        write_tum_trajectory(os.path.join(folder, "groundtruth_base.txt"), t.stamps_s, t.poses_se3)
        write_camera_yaml(os.path.join(folder, "camera.yaml"), camera)
    n = len(sc.trajectories[0].stamps_s)
    jobs = [
        (sc, noise, camera, tmp, t.robot_id, range(k, min(n, k + _CHUNK_FRAMES)))
        for t in sc.trajectories
        for k in range(0, n, _CHUNK_FRAMES)
    ]
    total, done = n * len(sc.trajectories), 0
    if progress:
        progress(0, total)
    if workers <= 1:
        for job in jobs:
            done += _render_chunk(job)
            if progress:
                progress(done, total)
    else:
        # 'spawn': no fork of a process that may run ROS or OpenCV threads.
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            for count in pool.map(_render_chunk, jobs):
                done += count
                if progress:
                    progress(done, total)
    world = build_world(sc.layout, sc.seed)
    if noise:  # nothing to match beyond the sensor's depth range
        ocfg = dataclasses.replace(ocfg, max_range_m=min(ocfg.max_range_m, sc.noise.depth_max_m))
    events = compute_overlap(sc, world, camera, ocfg)
    with open(os.path.join(tmp, WORLD_FILE), "w", encoding="utf-8") as fh:
        yaml.safe_dump(_world_yaml(sc, params, camera, noise, events, ocfg), fh, sort_keys=False)
    with open(os.path.join(tmp, COMPLETE_MARKER), "w", encoding="utf-8") as fh:
        fh.write(f"{time.time():.3f}\n")
