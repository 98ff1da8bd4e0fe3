"""Software renderer of the synthetic world: colour and exact metric depth through a pinhole camera.

Per visible quad: clip to the view frustum in the camera frame, project, rasterize its inverse
depth analytically from the plane equation (1/z is linear in pixel coordinates), z-test against the
frame's inverse-depth buffer on the quad's bounding box only, and warp the texture (the plane ->
image homography, one ``cv2.warpPerspective``) only where the quad won the z-test. Quads are drawn
front to back so hidden ones are rejected by the cheap z-test before any texture work. Each quad
samples the mip level that matches its projected texel size, which keeps distant textures from
aliasing (ORB features then stay stable across frames). Depth is exact: ``z = 1 / w`` of the plane.

Sensor noise (optional, seeded per frame) mimics an RGB-D camera: slight blur, Gaussian image
noise, Kinect-like range-dependent depth noise, dropout blobs and a limited depth range.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence as Seq
from dataclasses import dataclass

import cv2
import numpy as np

from ..datasets import CameraModel
from ..errors import CoopSlamError
from ..geometry import check_se3, invert
from .world import QuadModel, World

DEFAULT_CAMERA = CameraModel(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
NEAR_M = 0.05
_SUBPIXEL_BITS = 4


class RenderError(CoopSlamError):
    """Invalid render input (pose, camera) or noise settings."""


@dataclass
class NoiseConfig:
    """RGB-D sensor imperfections; ``enabled=False`` gives ideal images and exact, full depth."""

    enabled: bool = True
    image_sigma: float = 2.0  # grey levels, Gaussian, per channel
    blur_sigma_px: float = 0.6  # optics blur
    depth_sigma_base_m: float = 0.0012  # sigma(z) = base + quad * (z - offset)^2 (Kinect-like)
    depth_sigma_quad: float = 0.0019
    depth_sigma_offset_m: float = 0.4
    hole_fraction: float = 0.02  # share of pixels lost in random dropout blobs
    depth_min_m: float = 0.3
    depth_max_m: float = 8.0

    def validate(self):
        if self.image_sigma < 0 or self.blur_sigma_px < 0 or not 0 <= self.hole_fraction < 0.5:
            raise RenderError("noise sigmas must be >= 0 and hole_fraction in [0, 0.5)")
        if not 0 <= self.depth_min_m < self.depth_max_m:
            raise RenderError(f"depth range {self.depth_min_m}-{self.depth_max_m} m is empty")

    def depth_sigma_m(self, z_m):
        return (
            self.depth_sigma_base_m + self.depth_sigma_quad * (z_m - self.depth_sigma_offset_m) ** 2
        )


@dataclass
class DynamicObject:
    """A moving textured object: a QuadModel placed at ``T_world_obj`` for one frame."""

    T_world_obj: np.ndarray
    model: QuadModel


def _frustum_planes(camera: CameraModel, margin_px: float) -> np.ndarray:
    """(4, 3) unit normals of the side planes through the optical centre; inside: n . X >= 0."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    u0, v0 = -0.5 - margin_px, -0.5 - margin_px
    u1, v1 = camera.width - 0.5 + margin_px, camera.height - 0.5 + margin_px
    planes = np.array(
        [[fx, 0.0, cx - u0], [-fx, 0.0, u1 - cx], [0.0, fy, cy - v0], [0.0, -fy, v1 - cy]]
    )
    return planes / np.linalg.norm(planes, axis=1, keepdims=True)


def _inv3(M: np.ndarray) -> np.ndarray | None:
    """Inverse of a 3x3 matrix by the adjugate (np.linalg.inv is slow for tiny matrices under
    BLAS thread contention); None if singular."""
    (a, b, c), (d, e, f), (g, h, i) = M.tolist()
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    if abs(det) < 1e-300:
        return None
    return (
        np.array(
            [
                [A, c * h - b * i, b * f - c * e],
                [B, a * i - c * g, c * d - a * f],
                [C, b * g - a * h, a * e - b * d],
            ]
        )
        / det
    )


def _clip(poly: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of convex polygon (n, 3) with ``normal . X >= offset``."""
    d = poly @ normal - offset
    if d.min() >= 0:
        return poly
    if d.max() < 0:
        return poly[:0]
    out = []
    n = len(poly)
    for i in range(n):
        j = (i + 1) % n
        if d[i] >= 0:
            out.append(poly[i])
        if (d[i] >= 0) != (d[j] >= 0):
            out.append(poly[i] + (d[i] / (d[i] - d[j])) * (poly[j] - poly[i]))
    return np.array(out)


class Renderer:
    """Renders a World (plus dynamic objects) for a camera. Not thread-safe (texture cache)."""

    def __init__(
        self, world: World, camera: CameraModel = DEFAULT_CAMERA, noise: NoiseConfig | None = None
    ):
        self.world = world
        self.camera = camera
        self.noise = noise if noise is not None else NoiseConfig()
        self.noise.validate()
        self._planes_cam = _frustum_planes(camera, margin_px=1.0)
        self.lod_bias = 0.0

    # --- public API -----------------------------------------------------------------------------
    def render(
        self, T_world_cam: np.ndarray, dynamic: Seq[DynamicObject] = (), noise_seed: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """(bgr uint8 HxWx3, depth float32 [m], 0 = no measurement) seen from ``T_world_cam``."""
        bgr, inv_depth = self._rasterize(T_world_cam, dynamic, colour=True)
        depth = _inverse_to_depth(inv_depth)
        if self.noise.enabled:
            bgr, depth = apply_noise(bgr, depth, self.noise, noise_seed)
        return bgr, depth

    def render_depth(self, T_world_cam: np.ndarray, dynamic: Seq[DynamicObject] = ()) -> np.ndarray:
        """Exact depth [m] only (no texture work, no noise): cheap, for visibility tests."""
        _, inv_depth = self._rasterize(T_world_cam, dynamic, colour=False)
        return _inverse_to_depth(inv_depth)

    # --- rasterization --------------------------------------------------------------------------
    def _rasterize(self, T_world_cam, dynamic, colour: bool):
        T_world_cam = check_se3(T_world_cam, "T_world_cam")
        cam = self.camera
        img = np.zeros((cam.height, cam.width, 3), np.uint8) if colour else None
        inv_depth = np.zeros((cam.height, cam.width), np.float32)
        T_cam_world = invert(T_world_cam)
        jobs = self._visible(self.world.quads, T_cam_world)
        for obj in dynamic:
            jobs += self._visible(
                obj.model, T_cam_world @ check_se3(obj.T_world_obj, "T_world_obj")
            )
        jobs.sort(key=lambda job: job[0])  # front to back: hidden quads fail the z-test early
        for _, model, q, R, t in jobs:
            self._draw_quad(model, q, R, t, img, inv_depth)
        return img, inv_depth

    def _visible(self, model: QuadModel, T_cam_model: np.ndarray) -> list:
        """Quads facing the camera and in the frustum: (near depth, model, index, R, t) each."""
        R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
        centre_model = -R.T @ t  # camera centre in the model frame
        facing = np.einsum("ij,ij->i", model.normals, centre_model - model.origins) > 1e-9
        centres_cam = model.centres @ R.T + t
        r = model.radii
        ok = facing & (centres_cam[:, 2] + r > NEAR_M)
        ok &= np.all(centres_cam @ self._planes_cam.T > -r[:, None], axis=1)
        idx = np.flatnonzero(ok)
        near = centres_cam[idx, 2] - r[idx]
        return [(near[k], model, int(q), R, t) for k, q in enumerate(idx)]

    def _draw_quad(self, model: QuadModel, q: int, R, t, img, inv_depth) -> None:
        cam = self.camera
        o_cam = R @ model.origins[q] + t
        eu_cam = R @ model.edges_u[q]
        ev_cam = R @ model.edges_v[q]
        poly = np.array([o_cam, o_cam + eu_cam, o_cam + eu_cam + ev_cam, o_cam + ev_cam])
        poly = _clip(poly, np.array([0.0, 0.0, 1.0]), NEAR_M)
        for plane in self._planes_cam:
            if len(poly) < 3:
                return
            poly = _clip(poly, plane, 0.0)
        if len(poly) < 3:
            return
        uv_px = np.empty((len(poly), 2))
        uv_px[:, 0] = cam.fx * poly[:, 0] / poly[:, 2] + cam.cx
        uv_px[:, 1] = cam.fy * poly[:, 1] / poly[:, 2] + cam.cy
        x0 = max(0, math.floor(uv_px[:, 0].min()))
        y0 = max(0, math.floor(uv_px[:, 1].min()))
        x1 = min(cam.width - 1, math.ceil(uv_px[:, 0].max()))
        y1 = min(cam.height - 1, math.ceil(uv_px[:, 1].max()))
        if x1 < x0 or y1 < y0:
            return
        bw, bh = x1 - x0 + 1, y1 - y0 + 1
        # Inverse depth of the plane n . X = d:  1/z = (n . K^-1 [u v 1]) / d, linear in (u, v).
        n_cam = R @ model.normals[q]
        d = float(n_cam @ o_cam)
        if d >= -1e-9:
            return  # seen edge-on or from behind
        a = n_cam[0] / (cam.fx * d)
        b = n_cam[1] / (cam.fy * d)
        c = (n_cam[2] - n_cam[0] * cam.cx / cam.fx - n_cam[1] * cam.cy / cam.fy) / d
        row = (a * np.arange(x0, x1 + 1) + c).astype(np.float32)
        col = (b * np.arange(y0, y1 + 1)).astype(np.float32)
        w = col[:, None] + row[None, :]
        mask = np.zeros((bh, bw), np.uint8)
        pts = np.round((uv_px - (x0, y0)) * (1 << _SUBPIXEL_BITS)).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 255, cv2.LINE_8, _SUBPIXEL_BITS)
        w_roi = inv_depth[y0 : y1 + 1, x0 : x1 + 1]
        win = cv2.compare(w, w_roi, cv2.CMP_GT)
        cv2.bitwise_and(win, mask, dst=win)
        rx, ry, rw, rh = cv2.boundingRect(win)
        if rw == 0 or rh == 0:
            return
        cv2.copyTo(w, win, w_roi)
        if img is None:
            return
        win = win[ry : ry + rh, rx : rx + rw]
        levels = model.texture_levels(q)
        H_img_st = cam.K @ np.column_stack([eu_cam, ev_cam, o_cam])  # (s, t, 1) -> image
        level = self._mip_level(H_img_st, levels[0].shape, uv_px, len(levels))
        tex = levels[level]
        th, tw = tex.shape[:2]
        S = np.array([[1.0 / tw, 0.0, 0.5 / tw], [0.0, 1.0 / th, 0.5 / th], [0.0, 0.0, 1.0]])
        shift = np.array([[1.0, 0.0, -(x0 + rx)], [0.0, 1.0, -(y0 + ry)], [0.0, 0.0, 1.0]])
        M_tex_sub = _inv3(shift @ H_img_st @ S)
        if M_tex_sub is None:
            return
        warped = cv2.warpPerspective(
            tex,
            M_tex_sub,
            (rw, rh),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
        cv2.copyTo(warped, win, img[y0 + ry : y0 + ry + rh, x0 + rx : x0 + rx + rw])

    def _mip_level(self, H_img_st, shape0, uv_px, n_levels: int) -> int:
        """Pyramid level whose texels are about one pixel at the visible polygon's centroid."""
        if n_levels == 1:
            return 0
        th, tw = shape0[:2]
        S0 = np.array([[1.0 / tw, 0.0, 0.5 / tw], [0.0, 1.0 / th, 0.5 / th], [0.0, 0.0, 1.0]])
        Hinv = _inv3(H_img_st @ S0)  # image -> level-0 texels
        if Hinv is None:
            return 0
        u, v = uv_px.mean(axis=0)
        q = Hinv @ np.array([u, v, 1.0])
        if abs(q[2]) < 1e-12:
            return n_levels - 1
        J = (Hinv[:2, :2] - np.outer(q[:2] / q[2], Hinv[2, :2])) / q[2]
        a = float((J * J).sum())
        det = abs(float(J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]))
        smax = math.sqrt(max(1e-20, 0.5 * (a + math.sqrt(max(0.0, a * a - 4 * det * det)))))
        smin = max(1e-10, det / smax)
        # Lean towards the larger (foreshortened) axis, as anisotropic blur would, but not fully:
        # full max() blurs oblique floors too much, the geometric mean lets them alias.
        lam = 0.75 * math.log2(smax) + 0.25 * math.log2(smin) + self.lod_bias
        return int(min(n_levels - 1, max(0, round(lam))))


def _inverse_to_depth(inv_depth: np.ndarray) -> np.ndarray:
    depth = np.zeros_like(inv_depth)
    np.divide(1.0, inv_depth, out=depth, where=inv_depth > 0)
    return depth


def apply_noise(bgr: np.ndarray, depth_m: np.ndarray, cfg: NoiseConfig, seed: int):
    """Seeded sensor noise on a rendered frame; returns new (bgr, depth_m) arrays."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 7]))
    # OpenCV's RNG makes the Gaussian fields 3x faster than numpy's; seed it per frame so frames
    # do not depend on each other or on the order they are rendered in.
    cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
    out = bgr
    if cfg.blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), cfg.blur_sigma_px)
    if cfg.image_sigma > 0:
        noise = np.empty(out.shape, np.int16)
        cv2.randn(noise, (0.0,) * 3, (cfg.image_sigma,) * 3)  # scalars would only fill channel 0
        # Sum in int16, then clamp to [0, 255] (mixed-type cv2.add would saturate the noise itself).
        total = cv2.add(out, noise, dtype=cv2.CV_16S)
        cv2.max(total, 0, dst=total)
        out = cv2.convertScaleAbs(total)
    depth = depth_m.copy()
    valid = depth > 0
    gauss = np.empty(depth.shape, np.float32)
    cv2.randn(gauss, 0.0, 1.0)
    depth += cfg.depth_sigma_m(depth).astype(np.float32) * gauss
    depth[~valid] = 0.0
    if cfg.hole_fraction > 0:
        h, w = depth.shape
        holes = np.zeros((h, w), np.uint8)
        scale = math.sqrt(h * w / (480 * 640))
        radius_px = rng.uniform(2.0, 9.0, 4096) * scale
        mean_area = float(np.pi * np.mean(radius_px**2))
        count = int(rng.poisson(cfg.hole_fraction * h * w / mean_area))
        xs, ys = rng.integers(0, w, count), rng.integers(0, h, count)
        for k in range(count):
            cv2.circle(holes, (int(xs[k]), int(ys[k])), round(radius_px[k]), 255, -1)
        depth[holes > 0] = 0.0
    depth[(depth < cfg.depth_min_m) | (depth > cfg.depth_max_m)] = 0.0
    return out, depth


def bench_render(
    frames: int = 60, camera: CameraModel = DEFAULT_CAMERA, noise: bool = True
) -> float:
    """Frames per second of ``Renderer.render`` at the camera's size on ONE core (noise on).

    Uses the first robot's route of the 'revisit' scenario; textures are built in a warm-up pass
    first, so the figure is the steady-state rendering rate.
    """
    from .scenarios import make_scenario
    from .world import build_world

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        scenario = make_scenario("revisit", seed=0, robots=2)
        world = build_world(scenario.layout, seed=0)
        renderer = Renderer(world, camera, NoiseConfig(enabled=noise))
        traj = scenario.trajectories[0]
        idx = np.linspace(0, len(traj.stamps_s) - 1, max(1, frames)).astype(int)
        poses = [traj.poses_se3[i] @ scenario.T_base_cam for i in idx]
        for T in poses:
            renderer.render(T)  # warm-up: build the textures this route sees
        start = time.perf_counter()
        for k, T in enumerate(poses):
            renderer.render(T, noise_seed=k)
        elapsed = time.perf_counter() - start
    finally:
        cv2.setNumThreads(threads)
    return len(poses) / elapsed
