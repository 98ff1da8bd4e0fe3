"""EuRoC MAV (ASL) stereo folders: ``mav0/cam0``, ``mav0/cam1`` (``data.csv``, ``data/*.png``,
``sensor.yaml`` with pinhole intrinsics, radial-tangential distortion and ``T_BS``) and
``mav0/state_groundtruth_estimate0/data.csv`` (body pose ``p_RS_R``, ``q_RS`` w x y z in the world).

The pair is rectified as it loads (:class:`.base.StereoRectification`: OpenCV ``stereoRectify``,
cropped to pixels both cameras saw): the sequence's camera is the rectified left camera, its
baseline the rectified pair's, and ground truth ``T_world_cam`` the rectified left camera's pose.
"""

from __future__ import annotations

import csv
import os

import numpy as np
import yaml

from ..errors import GeometryError
from ..geometry import check_se3, se3_from_quat
from .base import DatasetError, Frame, RawCamera, Sequence, StereoRectification


def is_euroc(folder: str) -> bool:
    return os.path.isfile(os.path.join(folder, "mav0", "cam0", "data.csv"))


def _sensor_yaml(path: str) -> dict:
    """A Kalibr/ASL sensor.yaml (OpenCV's ``%YAML:1.0`` header is not YAML 1.1)."""
    if not os.path.isfile(path):
        raise DatasetError(f"EuRoC camera calibration not found: {path}")
    with open(path, encoding="utf-8") as fh:
        text = "".join(line for line in fh if not line.startswith("%"))
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path} is not valid YAML: {exc}") from None
    for key in ("T_BS", "resolution", "intrinsics", "distortion_coefficients"):
        if key not in data:
            raise DatasetError(f"{path}: '{key}' missing")
    if data.get("camera_model", "pinhole") != "pinhole":
        raise DatasetError(f"{path}: camera_model {data['camera_model']} (only pinhole)")
    if data.get("distortion_model", "radial-tangential") != "radial-tangential":
        raise DatasetError(
            f"{path}: distortion_model {data['distortion_model']} (only radial-tangential)"
        )
    return data


def _camera(path: str) -> RawCamera:
    data = _sensor_yaml(path)
    try:
        fu, fv, cu, cv = (float(v) for v in data["intrinsics"])
        width, height = (int(v) for v in data["resolution"])
        dist = np.array([float(v) for v in data["distortion_coefficients"]])
        T = np.array([float(v) for v in data["T_BS"]["data"]]).reshape(4, 4)
        T_body_cam = check_se3(T, "T_BS")
    except (TypeError, ValueError, KeyError, GeometryError) as exc:
        raise DatasetError(f"{path}: malformed calibration ({exc})") from None
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return RawCamera(K, dist, (width, height), T_body_cam)


def _frames_csv(path: str) -> list[tuple[int, str]]:
    if not os.path.isfile(path):
        raise DatasetError(f"EuRoC image list not found: {path}")
    rows = []
    with open(path, encoding="utf-8") as fh:
        for lineno, row in enumerate(csv.reader(fh), 1):
            if not row or row[0].startswith("#"):
                continue
            try:
                rows.append((int(row[0]), row[1].strip()))
            except (ValueError, IndexError):
                raise DatasetError(f"{path}:{lineno}: expected 'timestamp [ns],filename'") from None
    return rows


def _ground_truth(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s, T_world_body) of the ground-truth file (empty when missing)."""
    if not os.path.isfile(path):
        return np.zeros(0), np.zeros((0, 4, 4))
    try:
        rows = np.loadtxt(path, delimiter=",", comments="#", ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"{path}: malformed ground truth ({exc})") from None
    if rows.shape[1] < 8:
        raise DatasetError(f"{path}: expected timestamp, p xyz, q wxyz per row")
    poses = np.array([se3_from_quat(r[1:4], [r[5], r[6], r[7], r[4]]) for r in rows])
    return rows[:, 0] * 1e-9, poses.reshape(-1, 4, 4)


def read_euroc(folder: str, name: str | None = None) -> Sequence:
    """Read an EuRoC MAV (ASL) folder as a rectified stereo :class:`Sequence`."""
    mav = os.path.join(folder, "mav0")
    if not os.path.isdir(mav):
        raise DatasetError(f"{folder} is not an EuRoC (ASL) folder: mav0/ is missing")
    cam0 = _camera(os.path.join(mav, "cam0", "sensor.yaml"))
    cam1 = _camera(os.path.join(mav, "cam1", "sensor.yaml"))
    rect = StereoRectification.create(cam0, cam1)
    left = _frames_csv(os.path.join(mav, "cam0", "data.csv"))
    right = dict(_frames_csv(os.path.join(mav, "cam1", "data.csv")))
    frames = []
    for stamp_ns, fname in left:
        if stamp_ns not in right:
            continue  # a left image without its right one is not a stereo frame
        frames.append(
            Frame(
                index=len(frames),
                stamp_s=stamp_ns * 1e-9,
                color_path=os.path.join(mav, "cam0", "data", fname),
                right_path=os.path.join(mav, "cam1", "data", right[stamp_ns]),
            )
        )
    if not frames:
        raise DatasetError(f"{folder}: no stereo frames (cam0 and cam1 share no timestamp)")
    gt_stamps, T_world_body = _ground_truth(
        os.path.join(mav, "state_groundtruth_estimate0", "data.csv")
    )
    T_body_rect = cam0.T_body_cam @ rect.T_camraw_rect
    return Sequence(
        name=name or os.path.basename(os.path.normpath(folder)),
        camera=rect.camera,
        frames=frames,
        gt_stamps_s=gt_stamps,
        gt_poses_se3=T_world_body @ T_body_rect if len(gt_stamps) else T_world_body,
        gt_max_dt_s=0.005,
        rectify=rect,
    )
