"""Rigid-body transform helpers on 4x4 numpy matrices.

Convention: ``T_a_b`` maps points from frame b into frame a (``p_a = T_a_b @ p_b``).
Quaternions are ``(qx, qy, qz, qw)`` (TUM and ROS order).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import GeometryError


def se3(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """4x4 transform from a rotation matrix and a translation (identity for missing parts)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def se3_from_quat(t_xyz, q_xyzw) -> np.ndarray:
    """4x4 transform from a translation and a (qx, qy, qz, qw) quaternion (normalized here)."""
    q = np.asarray(q_xyzw, dtype=float).reshape(4)
    n = np.linalg.norm(q)
    if not np.all(np.isfinite(q)) or n < 1e-9:
        raise GeometryError(f"invalid quaternion {q.tolist()}: must be finite and non-zero")
    return se3(Rotation.from_quat(q / n).as_matrix(), t_xyz)


# REP-103 body axes (x forward, y left, z up) from a camera's optical axes (z forward, x right,
# y down): the rotation of a level camera looking ahead.
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def T_base_cam_of(base_cam) -> np.ndarray:
    """A camera mount from the clients' ``T_base_cam`` parameter ([x y z qx qy qz qw]; empty: a
    level camera looking ahead at base_link's origin)."""
    if base_cam is None or len(base_cam) == 0:
        T = np.eye(4)
        T[:3, :3] = R_BASE_OPTICAL
        return T
    return se3_from_quat(base_cam[:3], base_cam[3:])


def quat_from_se3(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t_xyz, q_xyzw) of a 4x4 transform, with qw >= 0."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return T[:3, 3].copy(), q


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (no general matrix inverse)."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]_x, (..., 3, 3), of (..., 3) vectors: [v]_x w = v x w."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` [rad] (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w)
    W = skew(w)
    if theta < 1e-10:
        return np.eye(3) + W
    return np.eye(3) + np.sin(theta) / theta * W + (1 - np.cos(theta)) / theta**2 * W @ W


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` to an (N, 3) array of points given in frame b."""
    points_b = np.asarray(points_b, dtype=float).reshape(-1, 3)
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (robust near 0 and 180)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error [m], rotation error [deg]) of an estimated transform against the truth."""
    E = invert(T_true) @ T_est
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])


def check_se3(T: np.ndarray, name: str = "transform", tol: float = 1e-4) -> np.ndarray:
    """Return ``T`` as a float 4x4 array, or raise GeometryError if it is not a rigid transform."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise GeometryError(f"{name} has shape {T.shape}, expected (4, 4)")
    if not np.all(np.isfinite(T)):
        raise GeometryError(f"{name} contains NaN or inf")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1.0) > tol:
        raise GeometryError(f"{name} has a rotation part that is not orthonormal")
    if np.abs(T[3] - [0, 0, 0, 1]).max() > tol:
        raise GeometryError(f"{name} has a last row {T[3].tolist()}, expected [0, 0, 0, 1]")
    return T


def path_length(poses_se3: np.ndarray) -> float:
    """Length [m] of the polyline through the translations of an (N, 4, 4) pose array."""
    poses_se3 = np.asarray(poses_se3)
    if len(poses_se3) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(poses_se3[:, :3, 3], axis=0), axis=1).sum())
