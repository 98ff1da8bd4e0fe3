"""TUM RGB-D format: reader for sequence folders and reader/writer for trajectory files.

Folder layout: ``rgb.txt`` and ``depth.txt`` (``stamp path`` lines), optional ``groundtruth.txt``
(``stamp tx ty tz qx qy qz qw``, camera-to-world), and the camera in ``camera.yaml`` beside them.
Colour and depth are associated by nearest timestamp, as TUM's ``associate.py`` does.
"""

from __future__ import annotations

import os

import numpy as np

from ..geometry import quat_from_se3, se3_from_quat
from .base import CameraModel, DatasetError, Frame, Sequence, read_camera_yaml


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


def _associate(a: list[tuple[float, str]], b: list[tuple[float, str]], max_dt: float):
    """Pairs (ia, ib) of nearest stamps within max_dt, each entry used once (greedy by time gap)."""
    if not a or not b:
        return []
    tb = np.array([s for s, _ in b])
    pairs = []
    used = set()
    for ia, (ta, _) in enumerate(a):
        ib = int(np.argmin(np.abs(tb - ta)))
        if abs(tb[ib] - ta) <= max_dt and ib not in used:
            used.add(ib)
            pairs.append((ia, ib))
    return pairs


def read_tum(
    folder: str,
    camera: CameraModel | None = None,
    camera_file: str | None = None,
    name: str | None = None,
    max_dt_s: float = 0.02,
) -> Sequence:
    """Read a TUM RGB-D folder. The camera comes from ``camera``, ``camera_file`` or
    ``folder/camera.yaml`` (in that order)."""
    if not os.path.isdir(folder):
        raise DatasetError(f"dataset folder not found: {folder}")
    if camera is None:
        camera_file = camera_file or os.path.join(folder, "camera.yaml")
        if not os.path.isfile(camera_file):
            raise DatasetError(
                f"no camera intrinsics for {folder}: put a camera.yaml (width, height, fx, fy, cx, "
                "cy, depth_scale) beside rgb.txt or pass a camera file"
            )
        camera = read_camera_yaml(camera_file)
    rgb = _read_list(os.path.join(folder, "rgb.txt"))
    has_depth = os.path.isfile(os.path.join(folder, "depth.txt"))
    if has_depth:
        depth = _read_list(os.path.join(folder, "depth.txt"))
        pairs = _associate(rgb, depth, max_dt_s)
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
    )
