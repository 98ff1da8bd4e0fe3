"""Data sources: readers for TUM RGB-D, KITTI odometry, the synthetic world, and a splitter."""

from .base import CameraModel, DatasetError, Frame, Sequence, read_camera_yaml, write_camera_yaml
from .tum import read_tum, read_tum_trajectory, write_tum_trajectory

__all__ = [
    "CameraModel",
    "DatasetError",
    "Frame",
    "Sequence",
    "read_camera_yaml",
    "write_camera_yaml",
    "read_tum",
    "read_tum_trajectory",
    "write_tum_trajectory",
]
