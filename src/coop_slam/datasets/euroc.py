"""EuRoC MAV (ASL) stereo folders: ``mav0/cam0``, ``mav0/cam1`` (``data.csv``, ``data/*.png``,
``sensor.yaml`` with pinhole intrinsics, radial-tangential distortion and ``T_BS``) and
``mav0/state_groundtruth_estimate0/data.csv`` (body pose ``p_RS_R``, ``q_RS`` w x y z in the world).

The pair is rectified as it loads (OpenCV ``stereoRectify``, cropped to pixels both cameras saw):
the sequence's camera is the rectified left camera, its baseline the rectified pair's, and ground
truth ``T_world_cam`` the rectified left camera's pose.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass

import cv2
import numpy as np
import yaml

from ..errors import GeometryError
from ..geometry import check_se3, invert, se3_from_quat
from .base import CameraModel, DatasetError, Frame, Sequence


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


@dataclass
class _Camera:
    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]  # (width, height)
    T_body_cam: np.ndarray


def _camera(path: str) -> _Camera:
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
    return _Camera(K, dist, (width, height), T_body_cam)


@dataclass
class StereoRectification:
    """Maps raw left / right images onto the rectified pair (rows of one point agree)."""

    camera: CameraModel  # the rectified left camera, with the pair's baseline
    T_camraw_rect: np.ndarray  # rectified left camera in the raw left camera
    maps: tuple  # (left map_x, left map_y, right map_x, right map_y)

    @classmethod
    def create(cls, left: _Camera, right: _Camera) -> StereoRectification:
        if left.size != right.size:
            raise DatasetError(
                f"the stereo cameras differ in size: {left.size} and {right.size} px"
            )
        T_right_left = invert(right.T_body_cam) @ left.T_body_cam  # left points -> right camera
        R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
            left.K,
            left.dist,
            right.K,
            right.dist,
            left.size,
            T_right_left[:3, :3],
            T_right_left[:3, 3],
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=0.0,
        )
        baseline_m = -P2[0, 3] / P2[0, 0]
        if not np.isfinite(baseline_m) or baseline_m <= 0:
            raise DatasetError(
                f"stereo rectification gives baseline {baseline_m:.4f} m: is cam1 the right "
                "camera of the pair?"
            )
        width, height = left.size
        camera = CameraModel(
            width=width,
            height=height,
            fx=P1[0, 0],
            fy=P1[1, 1],
            cx=P1[0, 2],
            cy=P1[1, 2],
            sensor="stereo",
            baseline_m=float(baseline_m),
        )
        maps = (
            *cv2.initUndistortRectifyMap(left.K, left.dist, R1, P1[:, :3], left.size, cv2.CV_32FC1),
            *cv2.initUndistortRectifyMap(
                right.K, right.dist, R2, P2[:, :3], right.size, cv2.CV_32FC1
            ),
        )
        T_camraw_rect = np.eye(4)
        T_camraw_rect[:3, :3] = R1.T  # rectified = R1 @ raw
        return cls(camera, T_camraw_rect, maps)

    def left(self, img: np.ndarray) -> np.ndarray:
        return cv2.remap(img, self.maps[0], self.maps[1], cv2.INTER_LINEAR)

    def right(self, img: np.ndarray) -> np.ndarray:
        return cv2.remap(img, self.maps[2], self.maps[3], cv2.INTER_LINEAR)


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
