"""Shared fakes for the tests: small datasets written on the fly and well-formed keyframes."""

from __future__ import annotations

import os
import time

import cv2
import numpy as np

from coop_slam.camera import CameraModel
from coop_slam.geometry import se3_from_quat
from coop_slam.wire.record import KeyframeRecord

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REDKITCHEN = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "redkitchen_0000_0599"))
TINY_TUM = os.path.join(REPO, "test", "fixtures", "tiny_tum")


def evaluate_again(out) -> dict:
    """scripts/evaluate re-derives the report of a demo results folder (``out``, a Path) from
    what it recorded; the new report."""
    import json
    import subprocess

    (out / "report.json").unlink()
    proc = subprocess.run(
        [os.path.join(REPO, "scripts", "evaluate"), str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with open(out / "report.json") as fh:
        return json.load(fh)


def wait_until(condition, timeout_s: float, what: str) -> None:
    """Wait for ``condition()`` (rostests: what another node publishes); fail naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.05)


def camera(width=640, height=480, f=525.0) -> CameraModel:
    return CameraModel(
        width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2
    )


def make_keyframe(n=50, robot_id=1, keyframe_id=1, seed=0, with_map_points=True) -> KeyframeRecord:
    """A well-formed keyframe with ``n`` random keypoints, depths and (every other) map points."""
    rng = np.random.default_rng(seed)
    cam = camera()
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (n, 2))
    keypoints = np.column_stack([uv, rng.uniform(7, 30, n), rng.uniform(0, 360, n)]).astype(
        np.float32
    )
    ids = np.where(np.arange(n) % 2 == 0, np.arange(1, n + 1), 0).astype(np.uint32)
    if not with_map_points:
        ids[:] = 0
    m = int(np.count_nonzero(ids))
    return KeyframeRecord(
        robot_id=robot_id,
        keyframe_id=keyframe_id,
        stamp_s=12.5,
        camera=cam,
        T_map_cam=np.eye(4),
        keypoints=keypoints,
        octaves=rng.integers(0, 8, n).astype(np.uint8),
        descriptors=rng.integers(0, 256, (n, 32)).astype(np.uint8),
        depths_m=rng.uniform(0.5, 4.0, n).astype(np.float32),
        map_point_ids=ids,
        map_points=rng.uniform(-2, 2, (m, 3)).astype(np.float32),
        covisible_ids=np.array([3, 4], np.uint32),
        covisible_weights=np.array([20, 15], np.uint16),
    )


def map_keyframe(rec: KeyframeRecord, dx: float = 0.0):
    """The odometry's keyframe a record is made of (see ``uplink.records.keyframe_record``), its
    pose and map points moved by ``dx`` m along x (local BA's update)."""
    from coop_slam.vo.map import MapKeyframe

    T = rec.T_map_cam.copy()
    T[0, 3] += dx
    return MapKeyframe(
        keyframe_id=rec.keyframe_id,
        stamp_s=rec.stamp_s,
        map_segment=rec.map_segment,
        T_map_cam=T,
        uv_px=rec.keypoints[:, :2],
        size_px=rec.keypoints[:, 2],
        angle_deg=rec.keypoints[:, 3],
        octaves=rec.octaves,
        descriptors=rec.descriptors,
        depths_m=rec.depths_m,
        map_point_ids=rec.map_point_ids,
        covisible_ids=rec.covisible_ids,
        covisible_weights=rec.covisible_weights,
        map_points_xyz=rec.map_points + np.float32(dx),
    )


def write_kitti(folder: str, n=5, width=64, height=32) -> str:
    """A minimal KITTI odometry layout: sequences/00 with stereo images, calib, times;
    poses/00.txt."""
    seq = os.path.join(folder, "sequences", "00")
    for sub in ("image_0", "image_1"):
        os.makedirs(os.path.join(seq, sub), exist_ok=True)
        for i in range(n):
            cv2.imwrite(
                os.path.join(seq, sub, f"{i:06d}.png"), np.full((height, width), 10 * i, np.uint8)
            )
    P0 = "700 0 32 0 0 700 16 0 0 0 1 0"
    P1 = "700 0 32 -378 0 700 16 0 0 0 1 0"  # baseline 0.54 m, as KITTI
    with open(os.path.join(seq, "calib.txt"), "w") as fh:
        fh.write(f"P0: {P0}\nP1: {P1}\nP2: {P0}\nP3: {P1}\n")
    np.savetxt(os.path.join(seq, "times.txt"), np.arange(n) * 0.1)
    os.makedirs(os.path.join(folder, "poses"), exist_ok=True)
    poses = np.tile(np.eye(4)[:3].ravel(), (n, 1))
    poses[:, 11] = np.arange(n) * 0.5  # driving forward along z
    np.savetxt(os.path.join(folder, "poses", "00.txt"), poses)
    return seq


def cylinder_world(n_points=4000, radius=5.0, seed=0):
    """Points on a cylinder wall around the origin (z up), each with its own ORB-like descriptor."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, n_points)
    points_world = np.column_stack(
        [radius * np.cos(a), radius * np.sin(a), rng.uniform(0, 2.5, n_points)]
    )
    return points_world, rng.integers(0, 256, (n_points, 32), dtype=np.uint8)


def looking_out_pose(yaw, center=(0.0, 0.0), height=1.2):
    """T_world_cam of an optical camera at ``center`` looking horizontally along ``yaw``."""
    from coop_slam.geometry import se3

    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    left = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    R = np.column_stack([-left, [0.0, 0.0, -1.0], fwd])  # x right, y down, z forward
    return se3(R, [center[0], center[1], height])


def observe(
    points_world,
    descriptors,
    T_world_cam,
    T_world_map,
    robot_id,
    keyframe_id,
    cam=None,
    seed=0,
    px_noise=0.5,
    bit_flips=3,
    stamp_s=None,
):
    """A KeyframeRecord of the points a camera sees (noisy pixels, depth and descriptors)."""
    from coop_slam.geometry import invert, transform_points

    cam = cam or camera()
    rng = np.random.default_rng(seed)
    p_cam = transform_points(invert(T_world_cam), points_world)
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.column_stack([cam.fx * p_cam[:, 0] / z + cam.cx, cam.fy * p_cam[:, 1] / z + cam.cy])
    vis = (
        (z > 0.3)
        & (uv[:, 0] >= 2)
        & (uv[:, 0] < cam.width - 2)
        & (uv[:, 1] >= 2)
        & (uv[:, 1] < cam.height - 2)
    )
    idx = np.nonzero(vis)[0]
    n = len(idx)
    uv = uv[idx] + rng.normal(0, px_noise, (n, 2))
    desc = descriptors[idx].copy()
    bits = np.unpackbits(desc, axis=1)
    for _ in range(bit_flips):
        j = rng.integers(0, 256, n)
        bits[np.arange(n), j] ^= 1
    desc = np.packbits(bits, axis=1)
    depth = z[idx] * (1 + rng.normal(0, 0.003, n))
    T_map_cam = invert(T_world_map) @ T_world_cam
    return KeyframeRecord(
        robot_id=robot_id,
        keyframe_id=keyframe_id,
        stamp_s=float(keyframe_id if stamp_s is None else stamp_s),
        camera=cam,
        T_map_cam=T_map_cam,
        keypoints=np.column_stack([uv, np.full(n, 10.0), np.zeros(n)]).astype(np.float32),
        octaves=np.zeros(n, np.uint8),
        descriptors=desc,
        depths_m=depth.astype(np.float32),
        map_point_ids=(idx + 1).astype(np.uint32),
        map_points=transform_points(invert(T_world_map), points_world[idx]).astype(np.float32),
    )


# --- a team of robots in the cylinder world (server tests and the server rostest) -----------------
TEAM_T_WORLD_MAP = {
    1: se3_from_quat([0.3, -0.2, 0.0], [0, 0, 0.1, 1.0]),
    2: se3_from_quat([-1.0, 0.5, 0.1], [0, 0, -0.4, 1.0]),
    3: se3_from_quat([0.5, 1.5, -0.1], [0, 0, 0.7, 1.0]),
}


def team_keyframes(robot_id, yaws, points, desc, kid0=1, offset=(0.0, 0.0), seed=0, t0=0.0):
    """Keyframes of a robot turning on the spot (looking out at the cylinder world), each covisible
    with its two predecessors; map frames from TEAM_T_WORLD_MAP, one keyframe per second."""
    out = []
    for k, yaw in enumerate(yaws):
        kf = observe(
            points,
            desc,
            looking_out_pose(yaw, center=offset),
            TEAM_T_WORLD_MAP[robot_id],
            robot_id,
            kid0 + k,
            seed=seed + k,
            stamp_s=t0 + k,
        )
        kf.covisible_ids = np.array(
            [i for i in (kid0 + k - 1, kid0 + k - 2) if i >= kid0], np.uint32
        )
        kf.covisible_weights = np.full(len(kf.covisible_ids), 100, np.uint16)
        out.append(kf)
    return out


def team_vocabulary(keyframes):
    """A small vocabulary trained on the keyframes' descriptors (the cylinder world's words)."""
    from coop_slam.bow import Vocabulary

    return Vocabulary.train([kf.descriptors for kf in keyframes], k=8, levels=3, seed=0)


def as_monocular(kf: KeyframeRecord, units_per_m: float) -> KeyframeRecord:
    """The keyframe as a monocular client sends it: no depth, its map in its own units
    (``units_per_m`` of them per metre)."""
    import dataclasses

    c = kf.camera
    T = np.array(kf.T_map_cam, dtype=float, copy=True)
    T[:3, 3] *= units_per_m
    return dataclasses.replace(
        kf,
        camera=CameraModel(c.width, c.height, c.fx, c.fy, c.cx, c.cy, sensor="mono"),
        T_map_cam=T,
        depths_m=np.zeros_like(kf.depths_m),
        map_points=(kf.map_points * units_per_m).astype(np.float32),
    )


def team_world(n_keyframes: int = 36):
    """The cylinder world (points, descriptors), robot 1 turning once round in it
    (``n_keyframes`` keyframes) and a vocabulary of its words: the server tests' team."""
    points, desc = cylinder_world(seed=3)
    a = team_keyframes(1, np.linspace(0, 2 * np.pi, n_keyframes, endpoint=False), points, desc)
    return points, desc, a, team_vocabulary(a)


def team_server_config(robots=(1, 2)):
    """A server configuration for the team helpers' keyframes."""
    from coop_slam.team.config import ServerConfig

    cfg = ServerConfig(robots=list(robots))
    cfg.global_ba.disparity_sigma_px = 0.05  # the helpers' depth is near exact (0.3 % noise)
    return cfg


ROOM_LO_M = np.array([0.0, 0.0, 0.0])  # a 5 x 4 x 2.5 m room, z up ...
ROOM_HI_M = np.array([5.0, 4.0, 2.5])
TABLE_LO_M, TABLE_HI_M = np.array([2.1, 0.2, 0.0]), np.array([2.9, 0.8, 0.75])  # ... with a table


def room_hit_distance(origin_group, dirs_group):
    """Ray parameter of the first surface hit from inside the room (dirs need not be unit): a
    5 x 4 x 2.5 m room, z up from its floor, with a 0.75 m high table."""
    with np.errstate(divide="ignore", invalid="ignore"):
        to_lo, to_hi = (ROOM_LO_M - origin_group) / dirs_group, (
            ROOM_HI_M - origin_group
        ) / dirs_group
        t_room = np.where(dirs_group > 0, to_hi, np.where(dirs_group < 0, to_lo, np.inf)).min(
            axis=1
        )
        a, b = (TABLE_LO_M - origin_group) / dirs_group, (TABLE_HI_M - origin_group) / dirs_group
    t_near = np.nanmax(np.minimum(a, b), axis=1)
    t_far = np.nanmin(np.maximum(a, b), axis=1)
    hits_table = (t_near <= t_far) & (t_near > 0)
    return np.where(hits_table, np.minimum(t_room, t_near), t_room)


def room_depth_image(T_room_cam, cam: CameraModel, noise_m: float = 0.0, seed: int = 0):
    """The depth image [m] (float32) a camera at ``T_room_cam`` sees in the room above."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    rays_cam = np.stack(
        [(u.ravel() - cam.cx) / cam.fx, (v.ravel() - cam.cy) / cam.fy, np.ones(u.size)], axis=1
    )
    depth = room_hit_distance(T_room_cam[:3, 3], rays_cam @ T_room_cam[:3, :3].T)
    depth = depth + np.random.default_rng(seed).normal(0.0, noise_m, depth.shape)
    return depth.reshape(cam.height, cam.width).astype(np.float32)


def depth_blob(seed: int = 0) -> np.ndarray:
    """A keyframe's depth image blob (dense.depth_image) as a record carries it: uint8 array."""
    from coop_slam.dense import depth_image

    rng = np.random.default_rng(seed)
    depth = (2.0 + 0.01 * rng.standard_normal((48, 64))).astype(np.float32)
    return np.frombuffer(depth_image.encode(depth_image.DepthImage(depth, 4), 0.01), np.uint8)


def cylinder_depth_blob(rec: KeyframeRecord, radius_m: float = 5.0) -> np.ndarray:
    """The depth image blob (dense.depth_image, 80 x 60) of a team_keyframes keyframe looking out
    at the cylinder world's wall (radius ``radius_m`` about the world's z axis)."""
    from coop_slam.dense import depth_image

    cam = rec.camera
    T = TEAM_T_WORLD_MAP[rec.robot_id] @ rec.T_map_cam
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(u.shape)], -1)
    d = rays.reshape(-1, 3) @ T[:3, :3].T  # z = 1 along the optical axis: t is the depth
    c = T[:3, 3]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (c[0] * d[:, 0] + c[1] * d[:, 1])
    disc = b**2 - 4 * a * (c[0] ** 2 + c[1] ** 2 - radius_m**2)
    depth = ((-b + np.sqrt(np.maximum(disc, 0))) / (2 * np.maximum(a, 1e-12))).reshape(u.shape)
    small = depth_image.decimate(depth.astype(np.float32), 8)
    return np.frombuffer(depth_image.encode(small, 0.01), np.uint8)
