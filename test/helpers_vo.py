"""Small synthetic RGB-D world for the visual-odometry tests.

A few randomly textured planes (a back wall, a floor and two side walls, like a room) rendered with
``cv2.warpPerspective`` along a known trajectory, with exact per-pixel depth from ray/plane
intersection and a z-buffer. Deterministic for a given seed. Stand-in until coop_slam.synthetic
lands.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from coop_slam.camera import CameraModel
from coop_slam.geometry import invert, se3

CAMERA = CameraModel(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)


def random_texture(rng: np.random.Generator, size_px: int = 768) -> np.ndarray:
    """Grey texture with many corners: random rectangles and circles over smooth noise."""
    base = cv2.resize(rng.uniform(60, 200, (12, 12)).astype(np.float32), (size_px, size_px))
    img = base.astype(np.uint8)
    for _ in range(450):
        c = int(rng.integers(0, 256))
        x, y = rng.integers(0, size_px, 2)
        if rng.random() < 0.6:
            w, h = rng.integers(6, 50, 2)
            cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), c, -1)
        else:
            cv2.circle(img, (int(x), int(y)), int(rng.integers(4, 25)), c, -1)
    return cv2.GaussianBlur(img, (3, 3), 0.8)


@dataclass
class Plane:
    origin_w: np.ndarray  # corner of the textured rectangle [m]
    axis_u_w: np.ndarray  # unit vector along texture columns
    axis_v_w: np.ndarray  # unit vector along texture rows
    size_m: tuple[float, float]  # extent along axis_u, axis_v [m]
    texture: np.ndarray


def room(rng: np.random.Generator) -> list[Plane]:
    """Back wall at z = 4 m, floor at y = 1.2 m, side walls at x = -/+ 2 m (world = first
    camera)."""
    ex, ey, ez = np.eye(3)
    return [
        Plane(np.array([-2.0, -1.5, 4.0]), ex, ey, (4.0, 2.7), random_texture(rng)),
        Plane(np.array([-2.0, 1.2, 0.5]), ex, ez, (4.0, 3.5), random_texture(rng)),
        Plane(np.array([-2.0, -1.5, 0.5]), ez, ey, (3.5, 2.7), random_texture(rng)),
        Plane(np.array([2.0, -1.5, 0.5]), ez, ey, (3.5, 2.7), random_texture(rng)),
    ]


def render(planes: list[Plane], T_world_cam: np.ndarray, camera: CameraModel = CAMERA):
    """(BGR uint8 image, depth float32 [m]) seen from T_world_cam."""
    w, h = camera.width, camera.height
    K = camera.K
    T_cam_world = invert(T_world_cam)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    gray = np.zeros((h, w), np.uint8)
    depth = np.full((h, w), np.inf, np.float32)
    for pl in planes:
        th, tw = pl.texture.shape
        # Texture pixel (s, t) -> world origin + axis_u * s * su + axis_v * t * sv -> image
        # (homography).
        su, sv = pl.size_m[0] / tw, pl.size_m[1] / th
        A = np.column_stack([R @ pl.axis_u_w * su, R @ pl.axis_v_w * sv, R @ pl.origin_w + t])
        H = K @ A
        img = cv2.warpPerspective(pl.texture, H, (w, h), flags=cv2.INTER_LINEAR)
        mask = (
            cv2.warpPerspective(np.ones((th, tw), np.uint8), H, (w, h), flags=cv2.INTER_NEAREST) > 0
        )
        # Depth along the optical axis from the ray/plane intersection: n . (z * ray) = n . p0.
        n_c = R @ np.cross(pl.axis_u_w, pl.axis_v_w)
        p0_c = R @ pl.origin_w + t
        denom = rays @ n_c
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (n_c @ p0_c) / denom
        valid = mask & (z > 0.05) & (z < depth)
        gray[valid] = img[valid]
        depth[valid] = z[valid]
    depth[~np.isfinite(depth)] = 0.0
    return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR), depth


def trajectory(n_frames: int, step_m: float = 0.01) -> np.ndarray:
    """(n, 4, 4) T_world_cam: a sideways arc with a little forward motion, pan and tilt."""
    poses = []
    for i in range(n_frames):
        s = i * step_m
        R = Rotation.from_euler("yxz", [0.25 * s, 0.05 * np.sin(3 * s), 0.02 * s]).as_matrix()
        poses.append(se3(R, [0.8 * s, 0.05 * np.sin(4 * s), 0.3 * s]))
    return np.array(poses)


def sequence(n_frames: int = 40, seed: int = 0, step_m: float = 0.01):
    """(stamps_s, frames [(bgr, depth)], gt T_world_cam) of a synthetic room sequence at 30 Hz."""
    rng = np.random.default_rng(seed)
    planes = room(rng)
    gt = trajectory(n_frames, step_m)
    frames = [render(planes, T) for T in gt]
    stamps = 100.0 + np.arange(n_frames) / 30.0
    return stamps, frames, gt
