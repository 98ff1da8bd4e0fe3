"""Software renderer of the synthetic world: colour and exact metric depth through a pinhole camera.

Per visible quad: clip to the view frustum in the camera frame, project, rasterize its inverse
depth analytically from the plane equation (1/z is linear in pixel coordinates), z-test against the
frame's inverse-depth buffer on the quad's bounding box only, and warp the texture (the plane ->
image homography, one ``cv2.warpPerspective``) only where the quad won the z-test. Quads are drawn
front to back so hidden ones are rejected by the cheap z-test before any texture work. Each quad
samples the mip level that matches its projected texel size, which keeps distant textures from
aliasing (ORB features then stay stable across frames). Depth is exact: ``z = 1 / w`` of the plane.

Sensor noise (optional, seeded per frame) mimics an RGB-D camera: slight blur, Gaussian image
noise, Kinect-like range-dependent depth noise, dropout blobs and a limited depth range. A noise
profile can add what makes hand-held structured-light data hard (all off by default, so worlds
rendered without them stay bit-identical): depth quantised on the disparity lattice, projector
shadows, missing depth along depth edges and at grazing angles, a depth camera slightly offset from
the colour camera in space and time (registration error), motion blur over the colour exposure and
auto-exposure gain changes (``exposure_gains``). Effects that need the camera's motion take a
``pose_at`` callable (sub-frame ``T_world_cam``) in ``Renderer.render``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from collections.abc import Sequence as Seq
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import CameraModel
from ..errors import CoopSlamError
from ..geometry import check_se3, invert, se3
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
    # --- structured-light depth (off by default) ---
    # Depth from disparity d = fx * b / z, reported in steps of disparity_step_px (Kinect: 1/8 px
    # at fx 525 px, b 7.5 cm): depth comes in steps that grow with z^2 (3 mm at 1 m, 3 cm at 3 m).
    disparity_step_px: float = 0.0  # 0: not quantised
    disparity_fx_px: float = 525.0  # the depth sensor's own focal length, whatever the images'
    disparity_baseline_m: float = 0.075  # camera -> projector, along the depth camera's +x
    projector_shadow: bool = False  # no depth where the projector cannot see (left of objects)
    edge_hole_px: float = 0.0  # ragged band of missing depth along depth discontinuities
    edge_jump_rel: float = 0.03  # a discontinuity: neighbours' depths differ by this share of z
    grazing_start_deg: float = 90.0  # incidence angle from which depth drops out at random ...
    grazing_max_deg: float = 90.0  # ... rising to none at all at this angle
    # Registration error: the depth camera sits this far from the colour camera (colour optical
    # frame) and exposes depth_lag_s earlier; its depth image is used as if it were registered.
    depth_offset_x_m: float = 0.0
    depth_offset_y_m: float = 0.0
    depth_offset_z_m: float = 0.0
    depth_lag_s: float = 0.0
    # --- colour camera (off by default) ---
    exposure_s: float = 0.0  # motion blur over an exposure this long, centred on the frame time
    gain_drift: float = 0.0  # auto-exposure: slow gain drift up to +-this share ...
    gain_step: float = 0.0  # ... plus gain steps of up to +-this share ...
    gain_step_rate_hz: float = 0.0  # ... this often on average (each held for 1-4 s)

    def validate(self):
        if self.image_sigma < 0 or self.blur_sigma_px < 0 or not 0 <= self.hole_fraction < 0.5:
            raise RenderError("noise sigmas must be >= 0 and hole_fraction in [0, 0.5)")
        if not 0 <= self.depth_min_m < self.depth_max_m:
            raise RenderError(f"depth range {self.depth_min_m}-{self.depth_max_m} m is empty")
        if (
            self.disparity_step_px < 0
            or self.disparity_fx_px <= 0
            or self.disparity_baseline_m <= 0
        ):
            raise RenderError("disparity step must be >= 0, its focal length and baseline > 0")
        if self.edge_hole_px < 0 or self.edge_jump_rel <= 0:
            raise RenderError("edge_hole_px must be >= 0 and edge_jump_rel > 0")
        if not 0 <= self.grazing_start_deg <= self.grazing_max_deg <= 90:
            raise RenderError("grazing angles must satisfy 0 <= start <= max <= 90 deg")
        if self.depth_lag_s < 0 or self.exposure_s < 0 or not 0 <= self.gain_step_rate_hz < 10:
            raise RenderError("depth lag and exposure must be >= 0 s, gain step rate in [0, 10) Hz")
        if not (0 <= self.gain_drift < 0.5 and 0 <= self.gain_step < 0.5):
            raise RenderError("gain drift and steps must be in [0, 0.5)")

    @property
    def depth_offset_m(self) -> np.ndarray:
        return np.array([self.depth_offset_x_m, self.depth_offset_y_m, self.depth_offset_z_m])

    @property
    def needs_motion(self) -> bool:
        """Whether rendering a frame needs the camera's sub-frame poses (``pose_at``)."""
        return self.exposure_s > 0 or self.depth_lag_s > 0

    def depth_sigma_m(self, z_m):
        return (
            self.depth_sigma_base_m + self.depth_sigma_quad * (z_m - self.depth_sigma_offset_m) ** 2
        )


def kinect_noise() -> NoiseConfig:
    """A Kinect v1 carried by hand (RGB-D SLAM benchmarks such as TUM RGB-D, 7-Scenes): depth
    0.5-4.5 m on the 1/8-px disparity lattice with projector shadows, ragged holes along depth edges
    and at grazing angles and dropout blobs; depth registered to colour with a few mm and 6 ms of
    error; 16 ms colour exposure (motion blur), auto-exposure drift and steps; a little more image
    noise and optics blur than the default."""
    return NoiseConfig(
        image_sigma=2.5,
        blur_sigma_px=0.8,
        hole_fraction=0.01,
        depth_min_m=0.5,
        depth_max_m=4.5,
        disparity_step_px=0.125,
        disparity_fx_px=525.0,
        disparity_baseline_m=0.075,
        projector_shadow=True,
        edge_hole_px=2.0,
        grazing_start_deg=75.0,
        grazing_max_deg=88.0,
        depth_offset_x_m=0.004,
        depth_offset_y_m=-0.002,
        depth_offset_z_m=0.001,
        depth_lag_s=0.006,
        exposure_s=0.016,
        gain_drift=0.2,
        gain_step=0.12,
        gain_step_rate_hz=0.12,
    )


# Sub-frame camera poses: times relative to the frame [s] (K,) -> T_world_cam (K, 4, 4).
PoseAt = Callable[[np.ndarray], np.ndarray]


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
        self,
        T_world_cam: np.ndarray,
        dynamic: Seq[DynamicObject] = (),
        noise_seed: int = 0,
        pose_at: PoseAt | None = None,
        gain: float = 1.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(bgr uint8 HxWx3, depth float32 [m], 0 = no measurement) seen from ``T_world_cam``.

        ``pose_at`` (the camera's poses around the frame time, ``pose_at([0])`` = ``T_world_cam``)
        lets the noise model blur colour over the exposure and expose depth earlier; without it the
        camera is taken as still. ``gain`` is the colour camera's exposure gain of this frame
        (see :func:`exposure_gains`).
        """
        bgr, inv_depth = self._rasterize(T_world_cam, dynamic, colour=True)
        depth = _inverse_to_depth(inv_depth)
        if not self.noise.enabled:
            return bgr, depth
        cfg = self.noise
        if cfg.exposure_s > 0 and pose_at is not None:
            shutter = np.array([-0.5, 0.5]) * cfg.exposure_s  # centred on the frame time
            T_cam_shutter = invert(T_world_cam)[None] @ np.asarray(pose_at(shutter), float)
            bgr = motion_blur(bgr, depth, self.camera, T_cam_shutter[0], T_cam_shutter[1])
        T_world_depth = T_world_cam
        if cfg.depth_lag_s > 0 and pose_at is not None:
            T_world_depth = np.asarray(pose_at(np.array([-cfg.depth_lag_s])), float)[0]
        if np.any(cfg.depth_offset_m != 0) or T_world_depth is not T_world_cam:
            T_world_depth = T_world_depth @ se3(t=cfg.depth_offset_m)
            depth = self.render_depth(T_world_depth, dynamic)
        shadow = None
        if cfg.projector_shadow:
            shadow = projector_shadow(depth, self.camera, cfg.disparity_baseline_m)
        return apply_noise(bgr, depth, cfg, noise_seed, self.camera, gain, shadow)

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


_RAYS: dict[tuple, np.ndarray] = {}


def _pixel_rays(camera: CameraModel) -> np.ndarray:
    """(3, H, W) float32 rays K^-1 [u v 1] of all pixels (cached per camera; do not modify)."""
    key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
    rays = _RAYS.get(key)
    if rays is None:
        x = (np.arange(camera.width, dtype=np.float32) - camera.cx) / camera.fx
        y = (np.arange(camera.height, dtype=np.float32) - camera.cy) / camera.fy
        rays = np.empty((3, camera.height, camera.width), np.float32)
        rays[0], rays[1], rays[2] = x[None, :], y[:, None], 1.0
        rays = _RAYS[key] = rays
    return rays


def motion_blur(
    bgr: np.ndarray,
    depth_m: np.ndarray,
    camera: CameraModel,
    T_cam_open: np.ndarray,
    T_cam_close: np.ndarray,
    px_per_sample: float = 1.5,
    max_samples: int = 12,
) -> np.ndarray:
    """Colour integrated over an exposure: the mean of the sharp frame warped along each pixel's
    image motion while the shutter is open. ``T_cam_open``/``T_cam_close`` are the camera's poses
    at the shutter's opening and closing in the frame's camera; a pixel keeps its (exact) depth
    over those few milliseconds and moves linearly between its two ends. Samples are about
    ``px_per_sample`` apart along the longest motion; a still camera returns ``bgr`` itself."""
    rays = _pixel_rays(camera).reshape(3, -1)
    z = np.where(depth_m > 0, depth_m, 10.0).astype(np.float32).reshape(1, -1)  # sky: far away
    points = rays * z
    ends = []
    for T in (T_cam_open, T_cam_close):
        # Where the pixel's point, seen at this moment, is in the sharp (frame-time) image.
        moved = T[:3, :3].astype(np.float32) @ points + T[:3, 3:4].astype(np.float32)
        zc = np.maximum(moved[2], 1e-3)
        ends.append(
            (
                (camera.fx * moved[0] / zc + camera.cx).reshape(depth_m.shape),
                (camera.fy * moved[1] / zc + camera.cy).reshape(depth_m.shape),
            )
        )
    (u0, v0), (u1, v1) = ends
    travel_px = float(np.sqrt(np.max((u1 - u0)[::8, ::8] ** 2 + (v1 - v0)[::8, ::8] ** 2)))
    if travel_px < 0.5:
        return bgr
    count = int(np.clip(math.ceil(travel_px / px_per_sample) + 1, 2, max_samples))
    acc = np.zeros(bgr.shape, np.float32)
    for s in np.linspace(0.0, 1.0, count):
        map_u = cv2.addWeighted(u0, 1.0 - s, u1, s, 0.0)
        map_v = cv2.addWeighted(v0, 1.0 - s, v1, s, 0.0)
        view = cv2.remap(bgr, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        cv2.accumulate(view, acc)
    return cv2.convertScaleAbs(acc, alpha=1.0 / count)


def projector_shadow(depth_m: np.ndarray, camera: CameraModel, baseline_m: float) -> np.ndarray:
    """(H, W) bool: pixels whose surface a structured-light projector ``baseline_m`` along the
    depth camera's +x cannot see (no pattern, no depth): the bands left of foreground objects.

    A point at (u, v, z) lies on the projector's ray u_p = u - fx b / z (same row); points further
    right on the row with a smaller u_p are on that ray between it and the projector, hiding it.
    """
    u_p = np.full(depth_m.shape, np.inf, np.float32)
    valid = depth_m > 0
    cols = np.broadcast_to(np.arange(depth_m.shape[1], dtype=np.float32), depth_m.shape)
    u_p[valid] = cols[valid] - camera.fx * baseline_m / depth_m[valid]
    # Smallest u_p strictly right of each pixel (running minimum from the right).
    right_min = np.full(depth_m.shape, np.inf, np.float32)
    right_min[:, :-1] = np.minimum.accumulate(u_p[:, :0:-1], axis=1)[:, ::-1]
    return valid & (u_p > right_min + 0.5)  # half a pixel: sampling of slanted surfaces


def exposure_gains(cfg: NoiseConfig, seed: int, times_s: np.ndarray) -> np.ndarray:
    """Per-frame gain of the colour camera's auto-exposure at ``times_s`` (seconds from the
    sequence start): a slow drift of up to +-``gain_drift`` times occasional steps to another level
    (up to +-``gain_step``, held 1-4 s, each settling within ~0.1 s). Ones when both are off.
    A frame's gain depends on its time only, not on how many frames are asked for."""
    times_s = np.asarray(times_s, float)
    gains = np.ones(len(times_s))
    if cfg.gain_drift <= 0 and (cfg.gain_step <= 0 or cfg.gain_step_rate_hz <= 0):
        return gains
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 23]))
    periods = rng.uniform(4.0, 16.0, 3)
    amps = rng.uniform(0.5, 1.0, 3)
    phases = rng.uniform(0.0, 2 * np.pi, 3)
    drift = (amps * np.sin(2 * np.pi * times_s[:, None] / periods + phases)).sum(axis=1)
    gains *= 1.0 + cfg.gain_drift * drift / amps.sum()
    if cfg.gain_step > 0 and cfg.gain_step_rate_hz > 0 and len(times_s):
        t, end = 0.0, float(times_s.max())
        while True:  # events in time order: the same seed gives the same prefix of steps
            t += rng.exponential(1.0 / cfg.gain_step_rate_hz)
            hold, size = rng.uniform(1.0, 4.0), cfg.gain_step * rng.uniform(-1.0, 1.0)
            if t > end:
                break
            on = np.clip((times_s - t) / 0.1, 0, 1) * np.clip((t + hold - times_s) / 0.1, 0, 1)
            gains *= 1.0 + size * on * on * (3 - 2 * on)  # smoothstep in and out
    return gains


def _depth_edges(depth_m: np.ndarray, rel: float) -> np.ndarray:
    """(H, W) bool: pixels next to a neighbour whose depth differs by more than ``rel`` * z (or
    that has no depth)."""
    edge = np.zeros(depth_m.shape, bool)
    for a, b in (
        (depth_m[:, 1:], depth_m[:, :-1]),
        (depth_m[1:, :], depth_m[:-1, :]),
    ):
        jump = (np.abs(a - b) > rel * np.maximum(a, b)) & ((a > 0) | (b > 0))
        if a.shape[1] < depth_m.shape[1]:
            edge[:, 1:] |= jump
            edge[:, :-1] |= jump
        else:
            edge[1:, :] |= jump
            edge[:-1, :] |= jump
    return edge


def _incidence_cos(depth_m: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(H, W) cosine of the angle between each pixel's viewing ray and its surface normal.

    With depth z(u, v) and ray r = K^-1 [u v 1], the normal of the surface P = z r is along
    (-fx z_u, -fy z_v, z + fx x z_u + fy y z_v) (x, y: the ray's first two components), whose dot
    product with r is z: cos = z / (|n| |r|). Derivatives are central differences, so pixels next
    to a depth edge look grazing (they lose depth anyway)."""
    rays = _pixel_rays(camera)
    kernel = np.array([[-0.5, 0.0, 0.5]], np.float32)
    z = depth_m.astype(np.float32)
    a = cv2.filter2D(z, -1, kernel, borderType=cv2.BORDER_REPLICATE) * -camera.fx
    b = cv2.filter2D(z, -1, kernel.T, borderType=cv2.BORDER_REPLICATE) * -camera.fy
    c = z - rays[0] * a - rays[1] * b
    norm = np.sqrt((a * a + b * b + c * c) * (rays[0] ** 2 + rays[1] ** 2 + 1.0))
    cos = np.ones(z.shape, np.float32)
    np.divide(z, norm, out=cos, where=norm > 0)
    return cos


def _smooth_field(rng: np.random.Generator, shape, cell_px: float) -> np.ndarray:
    """(H, W) float32 smooth random field in [0, 1] with features ~``cell_px`` wide."""
    h, w = shape
    gh, gw = max(2, math.ceil(h / cell_px) + 1), max(2, math.ceil(w / cell_px) + 1)
    grid = rng.random((gh, gw)).astype(np.float32)
    return np.clip(cv2.resize(grid, (w, h), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


def _structured_light_holes(depth_m, cfg: NoiseConfig, camera, shadow, seed) -> np.ndarray:
    """(H, W) bool: pixels a structured-light sensor loses, from the exact depth: projector shadow,
    a ragged band along depth edges and dropouts at grazing angles."""
    # Own random stream: the default model's draws stay exactly as they were.
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 8]))
    holes = np.zeros(depth_m.shape, bool) if shadow is None else shadow.copy()
    scale = camera.width / 640.0 if camera is not None else 1.0
    if cfg.edge_hole_px > 0:
        edges = _depth_edges(depth_m, cfg.edge_jump_rel)
        if edges.any():
            dist = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 3)
            width = cfg.edge_hole_px * scale * (0.3 + 1.4 * _smooth_field(rng, depth_m.shape, 12))
            holes |= dist < width
    if cfg.grazing_start_deg < 90:
        if camera is None:
            raise RenderError("grazing-angle dropouts need the camera model")
        # Dropout probability rises linearly in the cosine from start to max angle.
        cos = _incidence_cos(depth_m, camera)
        c0, c1 = math.cos(math.radians(cfg.grazing_start_deg)), math.cos(
            math.radians(cfg.grazing_max_deg)
        )
        p_drop = np.clip((c0 - cos) / max(c0 - c1, 1e-6), 0.0, 1.0)
        holes |= rng.random(depth_m.shape, dtype=np.float32) < p_drop
    return holes


def _quantize_disparity(depth_m: np.ndarray, cfg: NoiseConfig) -> np.ndarray:
    """Depth as a structured-light sensor reports it: disparity fx b / z rounded to the step."""
    fb = cfg.disparity_fx_px * cfg.disparity_baseline_m
    out = np.zeros_like(depth_m)
    valid = depth_m > 0
    steps = np.round(fb / depth_m[valid] / cfg.disparity_step_px)
    steps = np.maximum(steps, 1.0)  # beyond the last step: the farthest depth it can report
    out[valid] = (fb / (steps * cfg.disparity_step_px)).astype(np.float32)
    return out


def apply_noise(
    bgr: np.ndarray,
    depth_m: np.ndarray,
    cfg: NoiseConfig,
    seed: int,
    camera: CameraModel | None = None,
    gain: float = 1.0,
    shadow: np.ndarray | None = None,
):
    """Seeded sensor noise on a rendered frame; returns new (bgr, depth_m) arrays.

    ``gain`` scales the colour image (auto-exposure) before blur and noise; ``shadow`` marks the
    pixels the depth projector cannot see (see :func:`projector_shadow`); ``camera`` is needed for
    grazing-angle dropouts.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 7]))
    # OpenCV's RNG makes the Gaussian fields faster than numpy's; seed it per frame so frames
    # do not depend on each other or on the order they are rendered in.
    cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
    out = bgr
    if gain != 1.0:
        out = cv2.convertScaleAbs(out, alpha=float(gain))  # saturates like an over-exposed pixel
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
    structured_holes = None
    if shadow is not None or cfg.edge_hole_px > 0 or cfg.grazing_start_deg < 90:
        structured_holes = _structured_light_holes(depth_m, cfg, camera, shadow, seed)
    gauss = np.empty(depth.shape, np.float32)
    cv2.randn(gauss, 0.0, 1.0)
    depth += cfg.depth_sigma_m(depth).astype(np.float32) * gauss
    depth[~valid] = 0.0
    if cfg.disparity_step_px > 0:
        depth = _quantize_disparity(depth, cfg)
    if structured_holes is not None:
        depth[structured_holes] = 0.0
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
