"""KITTI odometry format: ``sequences/NN/{image_0,image_1,calib.txt,times.txt}`` and
``poses/NN.txt``.

Images are rectified greyscale stereo pairs; ``calib.txt`` holds the projection matrices P0..P3,
from which the left camera's intrinsics and the stereo baseline follow. Poses (when present) are 3x4
row-major ``T_world_cam0`` with the world being the first left-camera frame.
"""

from __future__ import annotations

import glob
import os

import cv2
import numpy as np

from .base import DatasetError, Frame, Sequence, dataset_camera


def _read_calib(path: str) -> dict[str, np.ndarray]:
    if not os.path.isfile(path):
        raise DatasetError(f"KITTI calibration file not found: {path}")
    mats = {}
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, 1):
            if ":" not in line:
                continue
            key, vals = line.split(":", 1)
            try:
                nums = np.array([float(v) for v in vals.split()])
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: non-numeric calibration values") from None
            if nums.size == 12:
                mats[key.strip()] = nums.reshape(3, 4)
    for key in ("P0", "P1"):
        if key not in mats:
            raise DatasetError(f"{path}: projection matrix {key} (12 numbers) missing")
    return mats


def read_kitti_poses(path: str) -> np.ndarray:
    """(N, 4, 4) poses from a KITTI pose file (12 numbers per line, 3x4 row-major)."""
    if not os.path.isfile(path):
        raise DatasetError(f"KITTI pose file not found: {path}")
    try:
        rows = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"{path}: malformed KITTI poses ({exc})") from None
    if rows.shape[1] != 12 or not np.all(np.isfinite(rows)):
        raise DatasetError(f"{path}: expected 12 finite numbers per line, got {rows.shape[1]}")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def read_kitti(
    sequence_dir: str, poses_file: str | None = None, name: str | None = None
) -> Sequence:
    """Read a KITTI odometry sequence folder as a stereo :class:`Sequence` (left camera frames)."""
    if not os.path.isdir(sequence_dir):
        raise DatasetError(f"KITTI sequence folder not found: {sequence_dir}")
    calib = _read_calib(os.path.join(sequence_dir, "calib.txt"))
    P0, P1 = calib["P0"], calib["P1"]
    left = sorted(glob.glob(os.path.join(sequence_dir, "image_0", "*.png")))
    right = sorted(glob.glob(os.path.join(sequence_dir, "image_1", "*.png")))
    if not left:
        raise DatasetError(f"{sequence_dir}/image_0 holds no PNG images")
    if len(left) != len(right):
        raise DatasetError(
            f"{sequence_dir}: {len(left)} left but {len(right)} right images; "
            "stereo pairs must match"
        )
    times_path = os.path.join(sequence_dir, "times.txt")
    if not os.path.isfile(times_path):
        raise DatasetError(f"KITTI times file not found: {times_path}")
    times = np.loadtxt(times_path, ndmin=1)
    if len(times) != len(left):
        raise DatasetError(f"{times_path}: {len(times)} stamps for {len(left)} images")
    first = cv2.imread(left[0], cv2.IMREAD_UNCHANGED)
    if first is None:
        raise DatasetError(f"cannot decode {left[0]}")
    camera = dataset_camera(
        os.path.join(sequence_dir, "calib.txt"),
        width=first.shape[1],
        height=first.shape[0],
        fx=P0[0, 0],
        fy=P0[1, 1],
        cx=P0[0, 2],
        cy=P0[1, 2],
        sensor="stereo",
        baseline_m=float(-(P1[0, 3] - P0[0, 3]) / P1[0, 0]),
    )
    frames = [
        Frame(index=i, stamp_s=float(t), color_path=lp, right_path=rp)
        for i, (t, lp, rp) in enumerate(zip(times, left, right))
    ]
    seq_name = name or os.path.basename(os.path.normpath(sequence_dir))
    if poses_file is None:
        guess = os.path.join(
            os.path.dirname(os.path.dirname(os.path.abspath(sequence_dir))),
            "poses",
            f"{seq_name}.txt",
        )
        poses_file = guess if os.path.isfile(guess) else None
    gt_stamps, gt_poses = np.zeros(0), np.zeros((0, 4, 4))
    if poses_file is not None:
        gt_poses = read_kitti_poses(poses_file)
        if len(gt_poses) != len(times):
            raise DatasetError(f"{poses_file}: {len(gt_poses)} poses for {len(times)} frames")
        gt_stamps = times.astype(float)
    return Sequence(
        name=seq_name,
        camera=camera,
        frames=frames,
        gt_stamps_s=gt_stamps,
        gt_poses_se3=gt_poses,
        gt_max_dt_s=1e-6,
    )
