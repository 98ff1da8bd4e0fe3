"""The server's depth images: one blob per keyframe that brought one, decoded to camera-frame
points once and kept, so placing a keyframe again after the graph moved costs a matrix product."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import CameraModel
from . import depth_image
from .keyframe_points import points_cam


@dataclass
class _Entry:
    blob: bytes
    points_cam: np.ndarray


class KeyframeDepths:
    """Depth blobs by (robot id, keyframe id) with their points in [min_m, max_m]."""

    def __init__(self, min_m: float = 0.1, max_m: float = 4.0) -> None:
        self.min_m = min_m
        self.max_m = max_m
        self._entries: dict[tuple[int, int], _Entry] = {}

    def add(self, key: tuple[int, int], blob: bytes, camera: CameraModel) -> None:
        """Keep a keyframe's blob; raises depth_image.DepthImageError if it cannot be read
        (the caller names the keyframe)."""
        image = depth_image.decode(blob)
        self._entries[key] = _Entry(bytes(blob), points_cam(image, camera, self.min_m, self.max_m))

    def remove(self, key: tuple[int, int]) -> None:
        self._entries.pop(key, None)

    def __contains__(self, key) -> bool:
        return key in self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def keys(self) -> list[tuple[int, int]]:
        return list(self._entries)

    def blob(self, key: tuple[int, int]) -> bytes:
        return self._entries[key].blob

    def points(self, key: tuple[int, int]) -> np.ndarray:
        return self._entries[key].points_cam

    def total_bytes(self) -> int:
        return sum(len(e.blob) for e in self._entries.values())
