"""A keyframe's depth image at a radio's price: decimated by an integer factor (the median of
each block's valid pixels, so an edge keeps one side's depth rather than a mix of both) and
quantized in steps of ``step_m``, then PNG-compressed, with a small header so the blob says how
to read it. The blob is what crosses the wire and what the map file keeps."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import CameraModel
from ..errors import CoopSlamError

_MAGIC = b"D1"
_HEADER = struct.Struct("<2sBf")  # magic, decimation factor, quantization step [m]
_MAX_CODE = 65535


class DepthImageError(CoopSlamError):
    """A depth image or depth blob that cannot be decimated, encoded or decoded."""


@dataclass(frozen=True)
class DepthImage:
    """A decimated depth image [m] (0 = no depth) and the factor it was decimated by."""

    depth_m: np.ndarray  # (h, w) float32
    decimation: int

    def camera(self, full: CameraModel) -> CameraModel:
        """The pinhole model of this decimated image, from the full image's."""
        f = self.decimation
        h, w = self.depth_m.shape
        return CameraModel(
            width=w,
            height=h,
            fx=full.fx / f,
            fy=full.fy / f,
            # Pixel centres: block (i) covers full pixels f*i .. f*i+f-1, centred at f*i+(f-1)/2.
            cx=(full.cx - (f - 1) / 2.0) / f,
            cy=(full.cy - (f - 1) / 2.0) / f,
            sensor=full.sensor,
            baseline_m=full.baseline_m,
        )


def decimation_for(width_px: int, target_width_px: int) -> int:
    """The integer factor that brings an image ``width_px`` wide to about ``target_width_px``."""
    if target_width_px <= 0:
        raise DepthImageError(f"target depth width must be > 0 px, got {target_width_px}")
    return max(1, int(round(width_px / target_width_px)))


def decimate(depth_m: np.ndarray, factor: int) -> DepthImage:
    """Median of the valid (finite, > 0) depths of each ``factor`` x ``factor`` block; a block
    with less than half its pixels valid has none (its median would be one stray pixel's)."""
    depth = np.asarray(depth_m)
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise DepthImageError(
            f"depth image must be a 2D float image in metres, got {depth.dtype} {depth.shape}"
        )
    if factor < 1:
        raise DepthImageError(f"decimation factor must be >= 1, got {factor}")
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    if h == 0 or w == 0:
        raise DepthImageError(f"depth image {depth.shape} is smaller than one {factor}px block")
    blocks = depth[: h * factor, : w * factor].reshape(h, factor, w, factor)
    blocks = blocks.transpose(0, 2, 1, 3).reshape(h, w, factor * factor).astype(np.float32)
    valid = np.isfinite(blocks) & (blocks > 0)
    n_valid = valid.sum(axis=2)
    # Invalid pixels sort last; the median of the valid ones is at index n_valid // 2.
    ordered = np.sort(np.where(valid, blocks, np.inf), axis=2)
    median = np.take_along_axis(ordered, (n_valid // 2)[..., None], axis=2)[..., 0]
    out = np.where(2 * n_valid >= factor * factor, median, 0.0).astype(np.float32)
    return DepthImage(np.where(np.isfinite(out), out, 0.0).astype(np.float32), factor)


def encode(image: DepthImage, step_m: float) -> bytes:
    """The blob of a decimated depth image quantized to ``step_m`` (depths beyond 65535 steps
    are dropped: no camera of a robot team measures that far with a useful accuracy)."""
    if not (np.isfinite(step_m) and step_m > 0):
        raise DepthImageError(f"depth quantization step must be > 0 m, got {step_m}")
    if not 1 <= image.decimation <= 255:
        raise DepthImageError(f"decimation factor must be 1..255, got {image.decimation}")
    codes = np.rint(np.nan_to_num(image.depth_m, nan=0.0) / step_m)
    codes = np.where((codes > 0) & (codes <= _MAX_CODE), codes, 0).astype(np.uint16)
    ok, png = cv2.imencode(".png", codes, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise DepthImageError(f"PNG encoding of a {codes.shape} depth image failed")
    return _HEADER.pack(_MAGIC, image.decimation, step_m) + png.tobytes()


def decode(blob: bytes) -> DepthImage:
    """The decimated depth image [m] of a blob made by :func:`encode`."""
    raw = bytes(blob)
    if len(raw) <= _HEADER.size:
        raise DepthImageError(f"depth blob of {len(raw)} bytes is too short to hold an image")
    magic, decimation, step_m = _HEADER.unpack_from(raw)
    if magic != _MAGIC:
        raise DepthImageError(f"depth blob starts with {magic!r}, not {_MAGIC!r}: not a depth blob")
    if decimation < 1 or not (np.isfinite(step_m) and step_m > 0):
        raise DepthImageError(
            f"depth blob header is invalid: decimation {decimation}, step {step_m}"
        )
    codes = cv2.imdecode(np.frombuffer(raw, np.uint8, offset=_HEADER.size), cv2.IMREAD_UNCHANGED)
    if codes is None or codes.ndim != 2 or codes.dtype != np.uint16:
        raise DepthImageError("depth blob does not hold a 16-bit single-channel PNG")
    return DepthImage((codes.astype(np.float32) * np.float32(step_m)), int(decimation))
