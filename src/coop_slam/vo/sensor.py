"""What the camera contributes to a frame beyond its image: the one place of the odometry that
depends on the sensor.

Tracking, local BA and keyframes use one measurement model for every keypoint: its pixel (u, v)
and, where the sensor measured its depth, a right-image coordinate ``u_right = u - bf / z`` (a
stereo pair's, with ``bf`` = fx * baseline) and the 3D point in the camera frame. An RGB-D camera
measures the depth and its ``u_right`` belongs to a *virtual* stereo pair of
``vo.virtual_baseline_m`` (ORB-SLAM2's RGB-D model); a stereo camera measures ``u_right`` and gets
the depth from it; a monocular one (:class:`MonoSensor`) measures neither: all its observations
are (u, v), its map points come from triangulation, and its map has no metric scale.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..camera import CameraModel
from .config import VoConfig
from .features import FrameFeatures, OrbExtractor, OrbKeypoints, level_scales
from .shared_work import shared_worker
from .stereo_matching import match_stereo
from .types import VoError


def gray_image(image, camera: CameraModel, what: str = "image") -> np.ndarray:
    """The grey uint8 image of a grey, BGR or BGRA frame of the camera's size; VoError naming
    what is wrong otherwise."""
    if not isinstance(image, np.ndarray) or image.size == 0:
        raise VoError(f"empty {what}: expected a BGR or grey uint8 array")
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise VoError(
            f"{what} must be uint8 grey or BGR, got dtype {image.dtype} shape {image.shape}"
        )
    if image.shape[:2] != (camera.height, camera.width):
        raise VoError(
            f"{what} is {image.shape[1]}x{image.shape[0]} "
            f"but the camera model is {camera.width}x{camera.height}"
        )
    if image.ndim == 2:
        return image
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.shape[2] == 1:
        return image[:, :, 0]
    raise VoError(f"{what} has {image.shape[2]} channels, expected 1, 3 or 4")


def make_sensor(config: VoConfig, camera: CameraModel) -> "Sensor":
    """The sensor model of ``camera.sensor``."""
    if camera.sensor == "rgbd":
        return RgbdSensor(config, camera)
    if camera.sensor == "stereo":
        return StereoSensor(config, camera)
    if camera.sensor == "mono":
        return MonoSensor(config, camera)
    raise VoError(f"the odometry has no model of a '{camera.sensor}' camera (rgbd, stereo, mono)")


def _frame_features(kps: OrbKeypoints, depth, u_right, camera: CameraModel) -> FrameFeatures:
    z = np.where(depth > 0, depth, np.nan).astype(np.float64)
    uv = kps.uv_px
    points_cam = np.stack(
        [(uv[:, 0] - camera.cx) / camera.fx * z, (uv[:, 1] - camera.cy) / camera.fy * z, z], axis=1
    )
    return FrameFeatures(
        uv_px=uv,
        size_px=kps.size_px,
        angle_deg=kps.angle_deg,
        octaves=kps.octaves,
        descriptors=kps.descriptors,
        depths_m=depth,
        points_cam=points_cam,
        u_right_px=u_right,
    )


class Sensor:
    """What the sensors share: the stereo model ``bf`` = fx * baseline, the depth up to which a
    keypoint's depth enters that model, and a warning about the input for the odometry to pass
    on (then cleared). ``monocular``: the sensor measures no depth (the map has no metric scale,
    its points come from triangulation)."""

    kind = ""
    monocular = False
    extracts_second = False  # the frame's second image has keypoints too (a stereo pair's right)

    def __init__(self, config: VoConfig, camera: CameraModel, baseline_m: float, close_m: float):
        self.config = config
        self.camera = camera
        self.baseline_m = baseline_m
        self.bf = camera.fx * baseline_m  # [px * m]
        self.close_depth_m = close_m
        self.warning: str | None = None

    def u_right(self, u_px: np.ndarray, depths_m: np.ndarray) -> np.ndarray:
        """Right-image u = u - fx b / z [px] of keypoints at u_px with depths (0 or NaN = none);
        NaN where there is none or it is beyond close_depth_m: far depth is too noisy for the
        stereo model, those keypoints count as monocular."""
        d = np.asarray(depths_m)
        close = (d > 0) & (d <= self.close_depth_m)
        return np.where(close, u_px - self.bf / np.where(close, d, 1.0), np.nan)


class RgbdSensor(Sensor):
    """A colour image with a depth image (registered to it, or with the depth camera's own
    intrinsics and offset, see ``vo.depth_*``). Its right-image coordinate belongs to a virtual
    stereo pair of ``vo.virtual_baseline_m``."""

    kind = "rgbd"

    def __init__(self, config: VoConfig, camera: CameraModel):
        super().__init__(
            config, camera, config.depth.virtual_baseline_m, config.depth.close_depth_m
        )

    # --- input ------------------------------------------------------------------------------------
    def check_input(self, image, depth_m) -> tuple[np.ndarray, np.ndarray]:
        """(grey uint8 image, depth [m] float) of one frame; raises VoError naming what is wrong
        with the input."""
        cam = self.camera
        gray = gray_image(image, cam)
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
    def features(
        self, kps: OrbKeypoints, gray: np.ndarray, depth_m, levels=None, extracted=None
    ) -> FrameFeatures:
        """The frame's keypoints with their depth (outside [min_depth_m, max_depth_m]: none),
        3D point and right-image coordinate. ``levels``, ``extracted``: unused here (see
        :meth:`StereoSensor.features`)."""
        cfg = self.config
        uv = kps.uv_px
        n = len(uv)
        depth = np.zeros(n, np.float32)
        if depth_m is not None and n:
            depth = self._lookup_depth(uv, depth_m)
            depth[
                ~np.isfinite(depth)
                | (depth < cfg.depth.min_depth_m)
                | (depth > cfg.depth.max_depth_m)
            ] = 0.0
        u_right = self.u_right(uv[:, 0], depth.astype(np.float64))
        return _frame_features(kps, depth, u_right, self.camera)

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

        if cfg.calibration.depth_registered:
            z = read(uv[:, 0], uv[:, 1])
            r = cfg.depth.edge_px
            if r > 0:
                # Corners often sit on depth edges, where a slightly misregistered or noisy depth
                # image gives the other surface's depth: no depth unless the neighbourhood agrees.
                offsets = ((-r, 0), (r, 0), (0, -r), (0, r), (-r, -r), (r, r), (-r, r), (r, -r))
                ring = np.stack([read(uv[:, 0] + du, uv[:, 1] + dv) for du, dv in offsets], 1)
                spread = np.abs(ring - z[:, None]).max(1)
                z = np.where((ring > 0).all(1) & (spread <= cfg.depth.edge_ratio * z), z, 0.0)
            return z.astype(np.float32)
        tx, ty, tz = (float(v) for v in cfg.calibration.depth_in_color_m)
        xn = (uv[:, 0] - cam.cx) / cam.fx
        yn = (uv[:, 1] - cam.cy) / cam.fy
        valid = depth_m[depth_m > 0]
        z = np.full(len(uv), float(np.median(valid)) if valid.size else 2.0)
        z_prev = z
        for _ in range(3):
            zd = np.maximum(z - tz, 1e-3)
            u_d = cfg.calibration.depth_fx * (z * xn - tx) / zd + cfg.calibration.depth_cx
            v_d = cfg.calibration.depth_fy * (z * yn - ty) / zd + cfg.calibration.depth_cy
            z_read = read(u_d, v_d)
            z_prev, z = z, np.where(z_read > 0, z_read + tz, 0.0)
            if not (z > 0).any():
                break
            z = np.where(
                z > 0, z, z_prev
            )  # keep iterating from the last guess where there was a hole
        settled = (z_read > 0) & (np.abs(z - z_prev) <= 0.02 * z)
        return np.where(settled, z, 0.0).astype(np.float32)


class StereoSensor(Sensor):
    """A rectified stereo pair (left image = the camera model's, right image on the same rows,
    ``camera.baseline_m`` to the right). The right-image coordinate is measured by matching the
    left keypoints in the right image (:mod:`.stereo_matching`); depth = fx * baseline /
    disparity, up to ``stereo_close_baselines`` baselines."""

    kind = "stereo"
    extracts_second = True

    def __init__(self, config: VoConfig, camera: CameraModel):
        if camera.baseline_m <= 0:
            raise VoError(f"a stereo camera needs a baseline > 0, got {camera.baseline_m} m")
        close_m = config.stereo.close_baselines * camera.baseline_m
        super().__init__(config, camera, camera.baseline_m, close_m)
        self._scales = level_scales(config)
        self._extractor = None  # for pairs given without the images' extraction (made on use)
        self._frames_since_check = None  # frames since the last rectification check

    def check_input(self, image, right) -> tuple[np.ndarray, np.ndarray]:
        """(left grey, right grey) uint8 of one pair; raises VoError naming what is wrong."""
        left = gray_image(image, self.camera, "left image")
        if right is None:
            raise VoError("no right image: stereo odometry needs the rectified right image")
        return left, np.ascontiguousarray(gray_image(right, self.camera, "right image"))

    def features(
        self, kps: OrbKeypoints, gray: np.ndarray, right: np.ndarray, levels=None, extracted=None
    ) -> FrameFeatures:
        """The left keypoints with their measured right-image coordinate and depth (none beyond
        ``close_depth_m``, nor without a match). ``levels``: the left pyramid; ``extracted``:
        the right image's (keypoints, pyramid), as the frame's extraction made them (else made
        here)."""
        if levels is None or extracted is None:
            if self._extractor is None:
                self._extractor = OrbExtractor(self.config, self.camera)
            both = self._extractor.extract_images([gray, right])
            levels = both[0][1] if levels is None else levels
            extracted = both[1] if extracted is None else extracted
        right_kps, right_levels = extracted
        u_right = match_stereo(
            kps,
            right_kps,
            levels,
            right_levels,
            self._scales,
            self.camera.fx,
            self.config,
            # both halves side by side when the extraction has a second thread too
            worker=shared_worker() if self.config.features.threads > 1 else None,
        )
        self._check_rectified(kps, right_kps, np.isfinite(u_right).mean() if len(kps) else 1.0)
        u_right = u_right - self.config.stereo.disparity_offset_px
        disparity = kps.uv_px[:, 0] - u_right
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = self.bf / disparity
        close = np.isfinite(depth) & (depth > 0) & (depth <= self.close_depth_m)
        depth = np.where(close, depth, 0.0).astype(np.float32)
        return _frame_features(kps, depth, np.where(close, u_right, np.nan), self.camera)

    def _check_rectified(self, left: OrbKeypoints, right: OrbKeypoints, matched: float) -> None:
        """On the first pair, and when few left keypoints find a right match (at most once per 300
        frames), say whether the pair's rows disagree (an unrectified pair) or left and right are
        swapped."""
        if self._frames_since_check is not None:
            self._frames_since_check += 1
            if self._frames_since_check < 300 or matched >= 0.2:
                return
        if len(left) < 50 or len(right) < 50:
            return
        self._frames_since_check = 0
        # Sure matches of precise (level 0) keypoints; repeated texture still leaves a few wrong.
        # Only level 0 is matched: all levels against all cost ~90 ms on a KITTI pair.
        li, ri = np.flatnonzero(left.octaves == 0), np.flatnonzero(right.octaves == 0)
        if len(li) < 20 or len(ri) < 20:
            return
        pairs = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(
            left.descriptors[li], right.descriptors[ri]
        )
        good = np.array([(li[m.queryIdx], ri[m.trainIdx]) for m in pairs if m.distance < 30])
        if len(good) < 20:
            return
        dv = left.uv_px[good[:, 0], 1] - right.uv_px[good[:, 1], 1]
        du = left.uv_px[good[:, 0], 0] - right.uv_px[good[:, 1], 0]
        if np.median(np.abs(dv)) > 1.0:
            self.warning = (
                f"only {100 * matched:.0f} % of the left keypoints found a stereo match: the "
                f"pair's rows differ by {np.median(np.abs(dv)):.1f} px (median of {len(good)} "
                "matches); is the pair rectified (image_rect topics)?"
            )
        elif np.median(du) < 0:
            self.warning = (
                f"only {100 * matched:.0f} % of the left keypoints found a stereo match: points "
                "appear farther right in the right image; are left and right swapped?"
            )


class MonoSensor(Sensor):
    """One camera: no depth, no right-image coordinate. Every keypoint is a monocular (u, v)
    observation; map points come from two-view initialization and triangulation between
    keyframes, and the map has no metric scale."""

    kind = "mono"
    monocular = True

    def __init__(self, config: VoConfig, camera: CameraModel):
        super().__init__(config, camera, 0.0, 0.0)

    def check_input(self, image, second=None) -> tuple[np.ndarray, None]:
        """(grey uint8 image, None) of one frame; a second image (e.g. the depth of an RGB-D
        recording played as a monocular camera) is ignored. Raises VoError naming what is wrong
        with the image."""
        return np.ascontiguousarray(gray_image(image, self.camera)), None

    def features(
        self, kps: OrbKeypoints, gray: np.ndarray, second=None, levels=None, extracted=None
    ) -> FrameFeatures:
        """The frame's keypoints without depth (depth 0, u_right and 3D point NaN)."""
        n = len(kps)
        return _frame_features(kps, np.zeros(n, np.float32), np.full(n, np.nan), self.camera)
