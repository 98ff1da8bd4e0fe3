"""What the camera contributes to a frame beyond its image: the one place of the odometry that
depends on the sensor.

Tracking, local BA and keyframes use one measurement model for every keypoint: its pixel (u, v)
and, where the sensor measured its depth, a right-image coordinate ``u_right = u - bf / z`` (a
stereo pair's, with ``bf`` = fx * baseline) and the 3D point in the camera frame. An RGB-D camera
measures the depth and its ``u_right`` belongs to a *virtual* stereo pair of
``vo.virtual_baseline_m`` (ORB-SLAM2's RGB-D model); a stereo camera would measure ``u_right`` and
get the depth from it; a monocular one measures neither.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..datasets.base import CameraModel
from .config import VoConfig
from .features import FrameFeatures, OrbKeypoints
from .types import VoError


class RgbdSensor:
    """A colour image with a depth image (registered to it, or with the depth camera's own
    intrinsics and offset, see ``vo.depth_*``)."""

    kind = "rgbd"

    def __init__(self, config: VoConfig, camera: CameraModel):
        self.config = config
        self.camera = camera
        self.bf = camera.fx * config.virtual_baseline_m  # [px * m]

    # --- input ------------------------------------------------------------------------------------
    def check_input(self, image, depth_m) -> tuple[np.ndarray, np.ndarray]:
        """(grey uint8 image, depth [m] float) of one frame; raises VoError naming what is wrong
        with the input."""
        cam = self.camera
        if not isinstance(image, np.ndarray) or image.size == 0:
            raise VoError("empty image: expected a BGR or grey uint8 array")
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise VoError(
                f"image must be uint8 grey or BGR, got dtype {image.dtype} shape {image.shape}"
            )
        if image.shape[:2] != (cam.height, cam.width):
            raise VoError(
                f"image is {image.shape[1]}x{image.shape[0]} "
                f"but the camera model is {cam.width}x{cam.height}"
            )
        if image.ndim == 3:
            if image.shape[2] == 3:
                gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            elif image.shape[2] == 4:
                gray = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
            elif image.shape[2] == 1:
                gray = image[:, :, 0]
            else:
                raise VoError(f"image has {image.shape[2]} channels, expected 1, 3 or 4")
        else:
            gray = image
        if depth_m is None or not isinstance(depth_m, np.ndarray) or depth_m.size == 0:
            raise VoError("no depth image: RGB-D odometry needs a depth image in metres")
        if depth_m.ndim != 2 or depth_m.shape != gray.shape:
            raise VoError(f"depth image has shape {depth_m.shape}, expected {gray.shape}")
        if depth_m.dtype == np.uint16:
            depth = depth_m.astype(np.float32) / np.float32(cam.depth_scale)
        elif np.issubdtype(depth_m.dtype, np.floating):
            depth = depth_m
        else:
            raise VoError(f"depth image must be float metres or uint16, got {depth_m.dtype}")
        return np.ascontiguousarray(gray), depth

    # --- measurements -----------------------------------------------------------------------------
    def features(self, kps: OrbKeypoints, depth_m: np.ndarray | None) -> FrameFeatures:
        """The frame's keypoints with their depth (outside [min_depth_m, max_depth_m]: none),
        3D point and right-image coordinate."""
        cfg, cam = self.config, self.camera
        uv = kps.uv_px
        n = len(uv)
        depth = np.zeros(n, np.float32)
        if depth_m is not None and n:
            depth = self._lookup_depth(uv, depth_m)
            depth[~np.isfinite(depth) | (depth < cfg.min_depth_m) | (depth > cfg.max_depth_m)] = 0.0
        z = np.where(depth > 0, depth, np.nan).astype(np.float64)
        points_cam = np.stack(
            [(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], axis=1
        )
        return FrameFeatures(
            uv_px=uv,
            size_px=kps.size_px,
            angle_deg=kps.angle_deg,
            octaves=kps.octaves,
            descriptors=kps.descriptors,
            depths_m=depth,
            points_cam=points_cam,
            u_right_px=self.u_right(uv[:, 0], z),
        )

    def u_right(self, u_px: np.ndarray, depths_m: np.ndarray) -> np.ndarray:
        """Right-image u [px] of keypoints at u_px with depths (0 or NaN = none); NaN where there
        is none or it is beyond close_depth_m: far depth is too noisy for the stereo-like term,
        those keypoints count as monocular."""
        d = np.asarray(depths_m)
        close = (d > 0) & (d <= self.config.close_depth_m)
        return np.where(close, u_px - self.bf / np.where(close, d, 1.0), np.nan)

    def _lookup_depth(self, uv: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """Depth along the colour optical axis at colour pixels uv (0 = none).

        Registered depth: the pixel itself. Unregistered: the depth pixel seeing the same point
        depends on that point's depth (parallax of the colour/depth baseline), so iterate: guess z,
        project the colour ray point into the depth camera, read the depth there, repeat; keypoints
        whose depth does not settle (they sit on a depth edge) get none.
        """
        cfg, cam = self.config, self.camera
        h, w = depth_m.shape

        def read(u, v):
            ui = np.clip(np.rint(u).astype(int), 0, w - 1)
            vi = np.clip(np.rint(v).astype(int), 0, h - 1)
            inside = (u > -0.5) & (u < w - 0.5) & (v > -0.5) & (v < h - 0.5)
            z = depth_m[vi, ui].astype(np.float64)
            return np.where(inside & np.isfinite(z), z, 0.0)

        if cfg.depth_registered:
            z = read(uv[:, 0], uv[:, 1])
            r = cfg.depth_edge_px
            if r > 0:
                # Corners often sit on depth edges, where a slightly misregistered or noisy depth
                # image gives the other surface's depth: no depth unless the neighbourhood agrees.
                offsets = ((-r, 0), (r, 0), (0, -r), (0, r), (-r, -r), (r, r), (-r, r), (r, -r))
                ring = np.stack([read(uv[:, 0] + du, uv[:, 1] + dv) for du, dv in offsets], 1)
                spread = np.abs(ring - z[:, None]).max(1)
                z = np.where((ring > 0).all(1) & (spread <= cfg.depth_edge_ratio * z), z, 0.0)
            return z.astype(np.float32)
        tx, ty, tz = (float(v) for v in cfg.depth_in_color_m)
        xn = (uv[:, 0] - cam.cx) / cam.fx
        yn = (uv[:, 1] - cam.cy) / cam.fy
        valid = depth_m[depth_m > 0]
        z = np.full(len(uv), float(np.median(valid)) if valid.size else 2.0)
        z_prev = z
        for _ in range(3):
            zd = np.maximum(z - tz, 1e-3)
            u_d = cfg.depth_fx * (z * xn - tx) / zd + cfg.depth_cx
            v_d = cfg.depth_fy * (z * yn - ty) / zd + cfg.depth_cy
            z_read = read(u_d, v_d)
            z_prev, z = z, np.where(z_read > 0, z_read + tz, 0.0)
            if not (z > 0).any():
                break
            z = np.where(
                z > 0, z, z_prev
            )  # keep iterating from the last guess where there was a hole
        settled = (z_read > 0) & (np.abs(z - z_prev) <= 0.02 * z)
        return np.where(settled, z, 0.0).astype(np.float32)
