"""TUM RGB-D format: reader for sequence folders and reader/writer for trajectory files.

Folder layout: ``rgb.txt`` and ``depth.txt`` (``stamp path`` lines), optional ``groundtruth.txt``
(``stamp tx ty tz qx qy qz qw``, camera-to-world), and the camera in ``camera.yaml`` beside them.
Colour and depth are associated by nearest timestamp, as TUM's ``associate.py`` does. A camera
file may give lens distortion (``base.read_camera_distortion``): images are then undistorted as
they load. The TUM RGB-D benchmark's own folders (``rgbd_dataset_freiburgN_*``) need no camera
file: their published calibration is built in.
"""

from __future__ import annotations

import dataclasses
import os
import re

import numpy as np

from ..camera import CameraModel
from ..geometry import quat_from_se3, se3_from_quat
from ..timestamps import associate
from .base import DatasetError, Frame, Sequence, Undistortion, dataset_camera, read_camera_file

# The TUM RGB-D benchmark's published colour calibration per Kinect (fx, fy, cx, cy, distortion
# k1 k2 p1 p2 k3, depth units per metre); its depth images are registered to the colour camera.
# freiburg3's images are undistorted already; freiburg2's depth PNGs hold 5208 units per metre
# (the scale correction ORB-SLAM2's TUM2 settings carry), the others 5000.
TUM_BENCHMARK_CAMERAS = {
    "1": (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633), 5000.0),
    "2": (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172), 5208.0),
    "3": (535.4, 539.2, 320.1, 247.6, (0.0, 0.0, 0.0, 0.0, 0.0), 5000.0),
}


def tum_benchmark_camera(folder: str) -> tuple[CameraModel, np.ndarray] | None:
    """(raw camera, distortion) of a TUM benchmark folder (``rgbd_dataset_freiburgN_*``, as the
    benchmark names them), else None."""
    m = re.fullmatch(r"rgbd_dataset_freiburg([123])_.+", os.path.basename(os.path.normpath(folder)))
    if m is None:
        return None
    fx, fy, cx, cy, dist, depth_scale = TUM_BENCHMARK_CAMERAS[m.group(1)]
    camera = dataset_camera(
        "TUM benchmark camera",
        width=640,
        height=480,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        depth_scale=depth_scale,
    )
    return camera, np.array(dist)


def _read_list(path: str) -> list[tuple[float, str]]:
    if not os.path.isfile(path):
        raise DatasetError(f"TUM list file not found: {path}")
    rows = []
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            try:
                rows.append((float(parts[0]), parts[1]))
            except (ValueError, IndexError) as exc:
                raise DatasetError(
                    f"{path}:{lineno}: expected 'timestamp filename', got {line!r}"
                ) from exc
    return rows


def read_tum_trajectory(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s (N,), poses_se3 (N, 4, 4)) from a TUM trajectory file, sorted by time."""
    if not os.path.isfile(path):
        raise DatasetError(f"trajectory file not found: {path}")
    stamps, poses = [], []
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                vals = [float(v) for v in line.replace(",", " ").split()]
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: non-numeric value in {line!r}") from None
            if len(vals) != 8 or not np.all(np.isfinite(vals)):
                raise DatasetError(
                    f"{path}:{lineno}: expected 8 finite numbers 'stamp tx ty tz qx qy qz qw'"
                )
            stamps.append(vals[0])
            poses.append(se3_from_quat(vals[1:4], vals[4:8]))
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps)[order], np.asarray(poses).reshape(-1, 4, 4)[order]


def write_tum_trajectory(path: str, stamps_s, poses_se3) -> None:
    """Write poses (N, 4, 4) with stamps (N,) as a TUM trajectory file."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for stamp, T in zip(stamps_s, poses_se3):
            t, q = quat_from_se3(np.asarray(T))
            fh.write(f"{stamp:.6f} " + " ".join(f"{v:.7f}" for v in (*t, *q)) + "\n")


def read_tum(
    folder: str,
    camera: CameraModel | None = None,
    camera_file: str | None = None,
    name: str | None = None,
    max_dt_s: float = 0.02,
) -> Sequence:
    """Read a TUM RGB-D folder. The camera comes from ``camera`` (rectified images),
    ``camera_file``, ``folder/camera.yaml`` or a TUM benchmark folder's name (in that order)."""
    if not os.path.isdir(folder):
        raise DatasetError(f"dataset folder not found: {folder}")
    undistort = None
    if camera is None:
        camera, undistort = _folder_camera(folder, camera_file)
    rgb = _read_list(os.path.join(folder, "rgb.txt"))
    has_depth = os.path.isfile(os.path.join(folder, "depth.txt"))
    if has_depth:
        depth = _read_list(os.path.join(folder, "depth.txt"))
        pairs = list(
            zip(*associate([t for t, _ in rgb], [t for t, _ in depth], max_dt_s, one_to_one=True))
        )
        if not pairs:
            raise DatasetError(f"{folder}: no colour/depth pair within {max_dt_s} s of each other")
        frames = [
            Frame(
                index=k,
                stamp_s=rgb[ia][0],
                color_path=os.path.join(folder, rgb[ia][1]),
                depth_path=os.path.join(folder, depth[ib][1]),
            )
            for k, (ia, ib) in enumerate(pairs)
        ]
    else:
        if camera.sensor == "rgbd":
            raise DatasetError(f"{folder}: depth.txt missing for an RGB-D camera")
        frames = [
            Frame(index=k, stamp_s=s, color_path=os.path.join(folder, p))
            for k, (s, p) in enumerate(rgb)
        ]
    right_list = os.path.join(folder, "right.txt")
    if os.path.isfile(right_list):  # a coop_slam synthetic world's right camera (rectified pair)
        right = _read_list(right_list)
        i_frame, i_right = associate([f.stamp_s for f in frames], [t for t, _ in right], max_dt_s)
        if len(i_frame) != len(frames) or camera.baseline_m <= 0:
            raise DatasetError(
                f"{folder}: right.txt needs one right image per frame and camera.yaml a "
                "baseline_m > 0"
            )
        for k, j in zip(i_frame, i_right):
            frames[k] = dataclasses.replace(frames[k], right_path=os.path.join(folder, right[j][1]))
    gt_path = os.path.join(folder, "groundtruth.txt")
    gt_stamps, gt_poses = (
        read_tum_trajectory(gt_path)
        if os.path.isfile(gt_path)
        else (np.zeros(0), np.zeros((0, 4, 4)))
    )
    return Sequence(
        name=name or os.path.basename(os.path.normpath(folder)),
        camera=camera,
        frames=frames,
        gt_stamps_s=gt_stamps,
        gt_poses_se3=gt_poses,
        gt_max_dt_s=max_dt_s,
        undistort=undistort,
    )


def _folder_camera(folder: str, camera_file: str | None) -> tuple[CameraModel, Undistortion | None]:
    """(camera of the loaded images, Undistortion or None) for a TUM folder."""
    path = camera_file or os.path.join(folder, "camera.yaml")
    if camera_file or os.path.isfile(path):
        raw, coeffs = read_camera_file(path)
    else:
        builtin = tum_benchmark_camera(folder)
        if builtin is None:
            raise DatasetError(
                f"no camera intrinsics for {folder}: put a camera.yaml (width, height, fx, fy, cx, "
                "cy, depth_scale[, k1 k2 p1 p2 k3]) beside rgb.txt or pass a camera file"
            )
        raw, coeffs = builtin
    undistort = Undistortion.create(raw, coeffs)
    return (undistort.camera if undistort else raw), undistort
