"""Common representation of an image sequence with ground truth, whatever it was read from.

A :class:`Sequence` lists frames (paths, timestamps) and loads images lazily, so a reader never
holds a whole dataset in memory. Ground truth is always ``T_world_cam`` (camera optical frame in the
dataset's world frame), as an (N, 4, 4) array.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import cv2
import numpy as np
import yaml

from ..camera import CameraError, CameraModel
from ..errors import CoopSlamError
from ..geometry import invert
from ..timestamps import associate


class DatasetError(CoopSlamError):
    """A dataset folder or file is missing or malformed."""


@dataclass(frozen=True)
class Frame:
    """One frame of a sequence: timestamp and image paths (depth for RGB-D, right for stereo)."""

    index: int  # index in the original sequence (kept through splits)
    stamp_s: float
    color_path: str
    depth_path: str | None = None
    right_path: str | None = None


@dataclass
class Sequence:
    """Frames, camera and ground truth of one camera's recording."""

    name: str
    camera: CameraModel
    frames: list[Frame]
    gt_stamps_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gt_poses_se3: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # T_world_cam
    gt_max_dt_s: float = 0.02  # largest stamp difference accepted when associating ground truth
    # Raw images with lens distortion: loading maps them onto ``camera`` (= undistort.camera).
    undistort: Undistortion | None = field(default=None, repr=False)
    # A raw stereo pair: loading rectifies left and right images onto ``camera``.
    rectify: StereoRectification | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def stamps_s(self) -> np.ndarray:
        return np.array([f.stamp_s for f in self.frames], dtype=float)

    def frame_poses(self) -> np.ndarray:
        """Ground-truth ``T_world_cam`` for every frame (nearest stamp; NaN where none is close)."""
        out = np.full((len(self.frames), 4, 4), np.nan)
        i_frame, i_gt = associate(self.stamps_s, self.gt_stamps_s, self.gt_max_dt_s)
        out[i_frame] = self.gt_poses_se3[i_gt]
        return out

    def slice(self, start: int, stop: int, name: str | None = None) -> "Sequence":
        """Frames ``start..stop-1`` (positions in this sequence) as a new sequence."""
        if not 0 <= start < stop <= len(self.frames):
            raise DatasetError(
                f"frame range {start}-{stop - 1} is outside {self.name} (0-{len(self.frames) - 1})"
            )
        return dataclasses.replace(self, name=name or self.name, frames=self.frames[start:stop])

    # --- image loading -------------------------------------------------------------------------
    def load_color(self, frame: Frame) -> np.ndarray:
        """Colour image as BGR uint8 (grey images are returned as single-channel uint8)."""
        img = _imread(frame.color_path, cv2.IMREAD_UNCHANGED)
        if self.rectify is not None:
            return self.rectify.left(img)
        return self.undistort.color(img, frame.color_path) if self.undistort is not None else img

    def load_right(self, frame: Frame) -> np.ndarray:
        if frame.right_path is None:
            raise DatasetError(f"{self.name}: frame {frame.index} has no right image (not stereo)")
        img = _imread(frame.right_path, cv2.IMREAD_UNCHANGED)
        return self.rectify.right(img) if self.rectify is not None else img

    def load_frame(self, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """(image, second) as the odometry takes a frame: the second image is the depth [m] of
        an RGB-D camera, the right image of a stereo pair."""
        if self.camera.sensor == "stereo":
            return self.load_color(frame), self.load_right(frame)
        return self.load_color(frame), self.load_depth_m(frame)

    def load_depth_m(self, frame: Frame) -> np.ndarray:
        """Depth in metres as float32, 0 where there is no measurement."""
        if frame.depth_path is None:
            raise DatasetError(f"{self.name}: frame {frame.index} has no depth image")
        raw = _imread(frame.depth_path, cv2.IMREAD_UNCHANGED)
        if raw.ndim != 2:
            raise DatasetError(
                f"depth image {frame.depth_path} has {raw.shape[2]} channels, expected 1"
            )
        if self.undistort is not None:
            raw = self.undistort.depth(raw, frame.depth_path)
        if raw.dtype == np.uint16:
            return raw.astype(np.float32) / np.float32(self.camera.depth_scale)
        depth = raw.astype(np.float32)
        depth[~np.isfinite(depth)] = 0.0
        return depth


def _imread(path: str, flags: int) -> np.ndarray:
    if not os.path.isfile(path):
        raise DatasetError(f"image file not found: {path}")
    img = cv2.imread(path, flags)
    if img is None or img.size == 0:
        raise DatasetError(f"cannot decode image file {path} (corrupt or unsupported format)")
    return img


def _camera_yaml_data(path: str) -> dict:
    if not os.path.isfile(path):
        raise DatasetError(f"camera file not found: {path}")
    with open(path, encoding="utf-8") as fh:
        try:
            data = yaml.safe_load(fh) or {}
        except yaml.YAMLError as exc:
            raise DatasetError(f"camera file {path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"camera file {path} must be a mapping of keys to values")
    return data


def read_camera_yaml(path: str, sensor: str = "rgbd") -> CameraModel:
    """Camera model from a flat YAML file
    (width, height, fx, fy, cx, cy[, depth_scale, baseline_m]); see also
    :func:`read_camera_distortion`."""
    return _camera_from(_camera_yaml_data(path), path, sensor)


def read_camera_file(path: str, sensor: str = "rgbd") -> tuple[CameraModel, np.ndarray]:
    """(camera model, lens distortion) of one camera file, read once."""
    data = _camera_yaml_data(path)
    return _camera_from(data, path, sensor), _distortion_from(data, path)


def dataset_camera(where: str, **kwargs) -> CameraModel:
    """A camera model read from a dataset (``where``); DatasetError naming it if the values do
    not describe a camera."""
    try:
        return CameraModel(**kwargs)
    except CameraError as exc:
        raise DatasetError(f"{where}: {exc}") from None


def _camera_from(data: dict, path: str, sensor: str) -> CameraModel:
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise DatasetError(f"camera file {path} lacks {', '.join(missing)}")
    known = {f.name for f in dataclasses.fields(CameraModel)}
    kwargs = {k: v for k, v in data.items() if k in known}
    kwargs.setdefault("sensor", sensor)
    return dataset_camera(f"camera file {path}", **kwargs)


# OpenCV's order of the lens distortion coefficients; TUM's calibration tables call them d0..d4.
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")


def read_camera_distortion(path: str) -> np.ndarray:
    """Lens distortion (k1, k2, p1, p2, k3) of a camera file's raw images: keys k1..k3, TUM's
    d0..d4 or a list ``distortion: [k1, k2, p1, p2(, k3)]``; zeros when it gives none."""
    return _distortion_from(_camera_yaml_data(path), path)


def _distortion_from(data: dict, path: str) -> np.ndarray:
    coeffs = np.zeros(len(DISTORTION_KEYS))
    styles = [
        ("distortion",) if "distortion" in data else (),
        tuple(k for k in DISTORTION_KEYS if k in data),
        tuple(f"d{i}" for i in range(5) if f"d{i}" in data),
    ]
    given = [keys for keys in styles if keys]
    if len(given) > 1:
        raise DatasetError(
            f"camera file {path} gives the distortion twice ({' and '.join(map(str, given))}): "
            "use one of 'distortion: [...]', k1..k3 or d0..d4"
        )
    if "distortion" in data:
        values = data["distortion"]
        if not isinstance(values, list) or len(values) not in (4, 5):
            raise DatasetError(
                f"camera file {path}: distortion must be a YAML list of 4 or 5 numbers "
                f"[k1, k2, p1, p2(, k3)], got {values!r}"
            )
    else:
        values = [data.get(k, data.get(f"d{i}", 0.0)) for i, k in enumerate(DISTORTION_KEYS)]
    for i, v in enumerate(values):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise DatasetError(
                f"camera file {path}: distortion coefficient {DISTORTION_KEYS[i]} must be a "
                f"number, got {v!r}"
            )
        coeffs[i] = float(v)
    if not np.isfinite(coeffs).all():
        raise DatasetError(f"camera file {path}: distortion coefficients must be finite")
    return coeffs


@dataclass
class Undistortion:
    """Maps raw images of a camera with lens distortion onto a pinhole camera (``camera``) that
    keeps only pixels the raw image saw, so no black border enters feature detection."""

    camera: CameraModel  # pinhole model of the undistorted images
    map_x: np.ndarray
    map_y: np.ndarray

    @classmethod
    def create(cls, raw: CameraModel, coeffs) -> Undistortion | None:
        """None when ``coeffs`` are all zero (the images are rectified already)."""
        coeffs = np.asarray(coeffs, float)
        if not coeffs.any():
            return None
        size = (raw.width, raw.height)
        K_new, _ = cv2.getOptimalNewCameraMatrix(raw.K, coeffs, size, 0.0, size)
        if not np.isfinite(K_new).all() or K_new[0, 0] <= 0 or K_new[1, 1] <= 0:
            raise DatasetError(
                f"lens distortion {coeffs.tolist()} gives no usable undistorted view"
            )
        camera = dataclasses.replace(
            raw, fx=K_new[0, 0], fy=K_new[1, 1], cx=K_new[0, 2], cy=K_new[1, 2]
        )
        map_x, map_y = cv2.initUndistortRectifyMap(raw.K, coeffs, None, K_new, size, cv2.CV_32FC1)
        return cls(camera, map_x, map_y)

    def color(self, img: np.ndarray, path: str) -> np.ndarray:
        self._check(img, path)
        return cv2.remap(img, self.map_x, self.map_y, cv2.INTER_LINEAR)

    def depth(self, depth: np.ndarray, path: str) -> np.ndarray:
        # Nearest: interpolating across a depth edge would invent surfaces between the two.
        self._check(depth, path)
        return cv2.remap(depth, self.map_x, self.map_y, cv2.INTER_NEAREST)

    def _check(self, img: np.ndarray, path: str) -> None:
        if img.shape[:2] != self.map_x.shape:
            raise DatasetError(
                f"image {path} is {img.shape[1]}x{img.shape[0]}, but the camera model (camera.yaml "
                f"or a built-in TUM freiburg calibration) is {self.map_x.shape[1]}x"
                f"{self.map_x.shape[0]}"
            )


@dataclass
class RawCamera:
    """A camera as calibrated, before rectification: intrinsics, lens distortion (OpenCV order),
    image size and its pose in the body frame."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]  # (width, height)
    T_body_cam: np.ndarray


@dataclass
class StereoRectification:
    """Maps raw left / right images onto the rectified pair (rows of one point agree)."""

    camera: CameraModel  # the rectified left camera, with the pair's baseline
    T_camraw_rect: np.ndarray  # rectified left camera in the raw left camera
    maps: tuple  # (left map_x, left map_y, right map_x, right map_y)

    @classmethod
    def create(cls, left: RawCamera, right: RawCamera) -> StereoRectification:
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
        camera = dataset_camera(
            "stereo rectification",
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


def write_camera_yaml(path: str, camera: CameraModel) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        yaml.safe_dump(camera.to_dict(), fh, sort_keys=False)
