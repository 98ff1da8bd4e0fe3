"""Robot sightings: detect other robots' ArUco markers and estimate where their bodies are.

Each robot carries its id as an ArUco marker (DICT_4X4_50) on the four sides of its body. Because
all four sides carry the same id, one sighting fixes the observed body's position but its heading
only up to quarter turns: :func:`body_hypotheses` returns all four, and the server uses a sighting
only as an initial guess / weak prior for feature-based registration, never as the sole evidence of
a merge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .config import require
from .errors import CoopSlamError
from .geometry import invert, se3, se3_from_quat

# Marker frame (OpenCV): x right, y up, z out of the marker towards the viewer. On the front face of
# a body (facing base_link +x): marker x = base +y, marker y = base +z, marker z = base +x.
R_BASE_MARKER_FRONT = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


class MarkerError(CoopSlamError):
    """Marker configuration or input image the detector cannot use."""


@dataclass
class MarkerConfig:
    dictionary: str = "DICT_4X4_50"  # ArUco dictionary; a robot's marker id is its robot id
    marker_size_m: float = 0.25  # side of the black square [m]
    # Front-face marker centre in base_link: [x, y, z, qx, qy, qz, qw]; empty = the synthetic
    # robots' body (0.4 m cube side, marker centre 0.38 m up).
    T_base_marker: list[float] = field(default_factory=list)
    max_reprojection_px: float = 2.0  # RMS corner error above which a detection is dropped [px]
    min_side_px: float = 20.0  # smaller markers give poses too noisy to use [px]
    # The robot body: a box (x, y, z) centred on base_link, which is on the floor [m]. Another
    # robot is a moving object, not a landmark: keypoints on a sighted body are ignored by the
    # odometry for mask_s seconds, the box grown by mask_grow_m for its motion meanwhile.
    body_size_m: list[float] = field(default_factory=lambda: [0.4, 0.4, 0.6])
    mask_s: float = 0.5  # [s]; 0 = keypoints on other robots are used like any other
    mask_grow_m: float = 0.15  # [m]

    def validate(self) -> None:
        require(hasattr(cv2.aruco, self.dictionary), f"unknown ArUco dictionary {self.dictionary}")
        require(self.marker_size_m > 0, "marker_size_m must be > 0")
        require(
            len(self.T_base_marker) in (0, 7), "T_base_marker needs 7 numbers (x y z qx qy qz qw)"
        )
        require(self.max_reprojection_px > 0, "max_reprojection_px must be > 0")
        require(
            len(self.body_size_m) == 3 and all(v > 0 for v in self.body_size_m),
            "body_size_m needs 3 sizes > 0 (x y z) [m]",
        )
        require(self.mask_s >= 0 and self.mask_grow_m >= 0, "mask_s and mask_grow_m must be >= 0")

    def base_marker(self) -> np.ndarray:
        if self.T_base_marker:
            return se3_from_quat(self.T_base_marker[:3], self.T_base_marker[3:])
        return se3(R_BASE_MARKER_FRONT, [0.2, 0.0, 0.38])


@dataclass
class MarkerSighting:
    marker_id: int
    T_cam_marker: np.ndarray  # (4, 4) marker frame in the camera optical frame
    T_cam_body: np.ndarray  # (4, 4) observed base_link, assuming the front face was seen
    reprojection_error_px: float
    corners_px: np.ndarray  # (4, 2)


class MarkerDetector:
    def __init__(self, config: MarkerConfig | None = None):
        self.config = config or MarkerConfig()
        self.config.validate()
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.config.dictionary))
        if hasattr(cv2.aruco, "ArucoDetector"):
            params = cv2.aruco.DetectorParameters()
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            self._detector = cv2.aruco.ArucoDetector(dictionary, params)
            self._detect = self._detector.detectMarkers
        else:
            params = cv2.aruco.DetectorParameters_create()
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            self._detect = lambda img: cv2.aruco.detectMarkers(img, dictionary, parameters=params)
        s = self.config.marker_size_m / 2.0
        self._object_pts = np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]], np.float64)
        self._T_marker_base = invert(self.config.base_marker())

    def detect(self, image: np.ndarray, K: np.ndarray) -> list[MarkerSighting]:
        """All markers in a BGR or grey image with their poses (pinhole K, no distortion)."""
        if image is None or image.size == 0:
            raise MarkerError("empty image")
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        corners, ids, _ = self._detect(gray)
        out = []
        if ids is None:
            return out
        for c, marker_id in zip(corners, ids.ravel()):
            uv = c.reshape(4, 2).astype(np.float64)
            if (
                np.min(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1))
                < self.config.min_side_px
            ):
                continue
            ok, rvec, tvec = cv2.solvePnP(
                self._object_pts, uv, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
            if not ok:
                continue
            proj, _ = cv2.projectPoints(self._object_pts, rvec, tvec, K, None)
            err = float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - uv) ** 2, axis=1))))
            if err > self.config.max_reprojection_px:
                continue
            T_cam_marker = se3(cv2.Rodrigues(rvec)[0], tvec.ravel())
            out.append(
                MarkerSighting(
                    int(marker_id), T_cam_marker, T_cam_marker @ self._T_marker_base, err, uv
                )
            )
        return out


def body_hypotheses(T_cam_body_front: np.ndarray) -> list[np.ndarray]:
    """The four body poses consistent with a sighting (any of the four identical faces seen)."""
    out = []
    for k in range(4):
        c, s = np.cos(k * np.pi / 2), np.sin(k * np.pi / 2)
        R_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        # Seeing face k instead of the front means the body is turned by -k quarter turns.
        out.append(T_cam_body_front @ se3(R_z.T))
    return out


def body_box_cam(config: MarkerConfig, T_cam_body_front: np.ndarray) -> np.ndarray:
    """(32, 3) corners of a sighted robot's body box (grown by ``mask_grow_m``) in the camera
    frame, for each of the four headings a sighting allows: what the odometry should not take for
    landmarks."""
    size_x, size_y, size_z = config.body_size_m
    grow = config.mask_grow_m
    hx, hy, top = size_x / 2.0 + grow, size_y / 2.0 + grow, size_z + grow  # it stands on the floor
    corners = np.array([[x, y, z, 1.0] for x in (-hx, hx) for y in (-hy, hy) for z in (0.0, top)]).T
    return np.concatenate([(T @ corners)[:3].T for T in body_hypotheses(T_cam_body_front)])
