"""Data sources: readers for TUM RGB-D, KITTI odometry, the synthetic world, and a splitter."""

from .base import (
    DatasetError,
    Frame,
    Sequence,
    read_camera_distortion,
    read_camera_yaml,
    write_camera_yaml,
)
from .euroc import is_euroc, read_euroc
from .kitti import read_kitti, read_kitti_poses
from .split import parse_ranges, split_equal, split_ranges
from .synthetic import SyntheticWorld, read_synthetic
from .tum import read_tum, read_tum_trajectory, tum_benchmark_camera, write_tum_trajectory

__all__ = [
    "DatasetError",
    "Frame",
    "Sequence",
    "read_camera_distortion",
    "read_camera_yaml",
    "write_camera_yaml",
    "is_euroc",
    "read_euroc",
    "read_kitti",
    "read_kitti_poses",
    "parse_ranges",
    "split_equal",
    "split_ranges",
    "SyntheticWorld",
    "read_synthetic",
    "read_tum",
    "read_tum_trajectory",
    "tum_benchmark_camera",
    "write_tum_trajectory",
]
