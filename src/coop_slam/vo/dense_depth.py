"""The depth image a keyframe takes along for the team's dense map, made from the frame that
became the keyframe while it is still at hand (in the tracking thread): an RGB-D camera's depth
image, or a stereo pair's disparity (semi-global matching at about 320 px wide, ~10 ms per
keyframe, then decimated), decimated and compressed by
:mod:`coop_slam.dense.depth_image`. A monocular camera measures no depth and sends none.

The image is made in a worker thread (:class:`KeyframeDepthImages`; OpenCV and numpy's sorts run
without Python's lock), so tracking does not wait for it -- a stereo pair's matching or an RGB-D
image's decimation and compression (~7 ms a RedKitchen keyframe, a twentieth of its tracking's
time, issue #50): the keyframe holds the pending image until it is first handed out
(:func:`resolved`, by the map's snapshot).
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import require
from ..dense import depth_image

log = logging.getLogger(__name__)


@dataclass
class DenseDepthConfig:
    """Section ``vo.dense``: the keyframes' depth images for the team's dense map."""

    # About this wide after decimation by an integer factor; 0 = none. 80 px (VGA / 8): ~2 kB a
    # keyframe, 5 % of its message (160 px: ~6.5 kB, which the radio budget pays for in whole
    # keyframes held back); a 5 cm grid cell still gets a depth per cell out to ~4 m.
    width_px: int = 80
    step_m: float = 0.01  # depth quantization step [m]
    max_depth_m: float = 4.0  # farther depth is left out (noisy, and it costs bytes) [m]
    # Stereo: semi-global matching down to this depth (its disparity range, at most a quarter of
    # the matched image's width) [m]
    stereo_min_depth_m: float = 0.4
    # Stereo: matched at an integer fraction of the image at least this wide [px], then
    # decimated: matched at 80 px, disparities of a few pixels come out ~5 % short
    stereo_match_width_px: int = 320
    # Stereo: depth out to at most this many baselines (its error grows with the square of the
    # range: ~4 cm at 33 baselines on the synthetic pair, 0.12 m at 4 m) [baselines]
    stereo_max_baselines: float = 25.0

    def validate(self) -> None:
        require(self.width_px >= 0, "vo.dense.width_px must be >= 0 (0 = no depth images)")
        require(self.step_m > 0, "vo.dense.step_m must be > 0 [m]")
        require(self.max_depth_m > 0, "vo.dense.max_depth_m must be > 0 [m]")
        require(self.stereo_min_depth_m > 0, "vo.dense.stereo_min_depth_m must be > 0 [m]")
        require(self.stereo_match_width_px > 0, "vo.dense.stereo_match_width_px must be > 0")
        require(self.stereo_max_baselines > 0, "vo.dense.stereo_max_baselines must be > 0")


def _stereo_depth(camera: CameraModel, left, right, factor: int, min_depth_m: float):
    """(h/f, w/f) depth [m] of a rectified grey pair, matched at 1/factor of its size."""
    h, w = (left.shape[0] // factor) * factor, (left.shape[1] // factor) * factor
    size = (w // factor, h // factor)
    small_l = cv2.resize(left[:h, :w], size, interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(right[:h, :w], size, interpolation=cv2.INTER_AREA)
    bf_px_m = camera.fx * camera.baseline_m / factor
    n_disp = int(np.ceil(bf_px_m / min_depth_m / 16.0)) * 16
    n_disp = max(16, min(n_disp, (size[0] // 4) // 16 * 16))
    block = 5
    matcher = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=n_disp,
        blockSize=block,
        P1=8 * block * block,
        P2=32 * block * block,
        uniquenessRatio=10,
        speckleWindowSize=50,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM,
    )
    disparity = matcher.compute(small_l, small_r).astype(np.float32) / 16.0
    with np.errstate(divide="ignore"):
        return np.where(disparity > 0.5, bf_px_m / disparity, 0.0).astype(np.float32)


def depth_image_blob(
    config: DenseDepthConfig, sensor: str, camera: CameraModel, gray, second, registered: bool
) -> bytes:
    """The keyframe's compressed depth image, or b"" (none configured, monocular, or depth not
    registered to the colour image, whose camera model the server would place it with)."""
    if config.width_px == 0 or second is None or sensor == "mono":
        return b""
    factor = depth_image.decimation_for(camera.width, config.width_px)
    if sensor == "stereo":
        wide = [d for d in range(1, factor + 1) if factor % d == 0]
        match = max(d for d in wide if d == 1 or camera.width / d >= config.stereo_match_width_px)
        depth = _stereo_depth(camera, gray, second, match, config.stereo_min_depth_m)
        small = depth_image.decimate(depth, factor // match)
        small = depth_image.DepthImage(small.depth_m, factor)
    elif registered:
        small = depth_image.decimate(np.asarray(second, np.float32), factor)
    else:
        return b""
    max_m = config.max_depth_m
    if sensor == "stereo":
        max_m = min(max_m, config.stereo_max_baselines * camera.baseline_m)
    depth = np.where(small.depth_m <= max_m, small.depth_m, 0.0)
    return depth_image.encode(depth_image.DepthImage(depth, factor), config.step_m)


class KeyframeDepthImages:
    """Keyframes' depth images of one camera, made in a worker thread (see the module)."""

    def __init__(
        self, config: DenseDepthConfig, sensor: str, camera: CameraModel, registered: bool
    ):
        self._args = (config, sensor, camera)
        self._registered = registered
        self._worker = None
        if config.width_px > 0 and (sensor == "stereo" or (sensor == "rgbd" and registered)):
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="kf_depth")

    def make(self, gray, second) -> bytes | Future:
        """The depth image of the frame (``gray``, its depth or right image), or its pending
        making."""
        if self._worker is None or second is None:
            return depth_image_blob(*self._args, gray, second, self._registered)
        return self._worker.submit(depth_image_blob, *self._args, gray, second, self._registered)

    def close(self) -> None:
        if self._worker is not None:
            self._worker.shutdown(wait=False, cancel_futures=True)


def resolved(image: bytes | Future) -> bytes:
    """A keyframe's depth image as bytes: a pending one waited for; one whose making failed is
    none (said in the log: the keyframe goes without it)."""
    if not isinstance(image, Future):
        return image
    try:
        return image.result()
    except Exception as exc:  # the keyframe is worth more than its depth image
        log.warning("a keyframe's depth image could not be made: %s: %s", type(exc).__name__, exc)
        return b""
