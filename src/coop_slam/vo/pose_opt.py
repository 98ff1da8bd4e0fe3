"""Motion-only pose optimization (ORB-SLAM's ``PoseOptimization``) in numpy.

Residuals are (u, v) for keypoints without depth and (u, v, u_right) for keypoints with depth, where
``u_right = u - bf / z`` is the column in a virtual right camera (``bf`` = fx * virtual baseline),
so depth enters as a pixel-like residual with the same octave-dependent weight. A Huber kernel in
the first rounds, then outliers are classified by a chi-square gate after each round and left out of
the next one (they can come back). A few hundred correspondences take well under a millisecond per
Gauss-Newton iteration because the normal equations are built with one einsum.
"""

from __future__ import annotations

import numpy as np


def _rodrigues(phi: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(phi))
    if theta < 1e-12:
        return np.eye(3)
    k = phi / theta
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * Kx + (1.0 - np.cos(theta)) * (Kx @ Kx)


def optimize_pose(
    T_cam_map: np.ndarray,
    points_map: np.ndarray,
    uv_px: np.ndarray,
    u_right_px: np.ndarray,
    info: np.ndarray,
    K: np.ndarray,
    bf: float,
    rounds: int = 4,
    iterations: int = 10,
    chi2_mono: float = 5.991,
    chi2_stereo: float = 7.815,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine ``T_cam_map`` from 3D map points and their keypoints; returns
    (T_cam_map, inlier mask).

    ``u_right_px`` is NaN for keypoints without depth; ``info`` is 1/sigma^2 per keypoint [1/px^2].
    """
    n = len(points_map)
    T = np.array(T_cam_map, dtype=float)
    if n < 3:
        return T, np.zeros(n, bool)
    P = np.asarray(points_map, dtype=float)
    mu, mv = uv_px[:, 0].astype(float), uv_px[:, 1].astype(float)
    stereo = np.isfinite(u_right_px)
    s3 = stereo.astype(float)
    mur = np.where(stereo, u_right_px, 0.0)
    chi2 = np.where(stereo, chi2_stereo, chi2_mono)
    delta = np.sqrt(chi2)
    inlier = np.ones(n, bool)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    def residuals(T):
        pc = P @ T[:3, :3].T + T[:3, 3]
        front = pc[:, 2] > 1e-6
        iz = 1.0 / np.where(front, pc[:, 2], 1e-6)
        u = fx * pc[:, 0] * iz + cx
        v = fy * pc[:, 1] * iz + cy
        r0, r1 = u - mu, v - mv
        r2 = (u - bf * iz - mur) * s3
        return pc, iz, r0, r1, r2, front

    for rnd in range(rounds):
        robust = rnd < 2
        for _ in range(iterations):
            pc, iz, r0, r1, r2, front = residuals(T)
            w = info * (inlier & front)
            if robust:
                e = np.sqrt(np.maximum(info * (r0 * r0 + r1 * r1 + r2 * r2), 1e-12))
                w = w * np.where(e <= delta, 1.0, delta / e)
            x, y = pc[:, 0], pc[:, 1]
            iz2 = iz * iz
            # Rows of d(u, v, u_right) / d xi for T_cam_map <- Exp(xi) T_cam_map, xi = (rho, phi).
            J0 = np.column_stack(
                [
                    fx * iz,
                    np.zeros(n),
                    -fx * x * iz2,
                    -fx * x * y * iz2,
                    fx + fx * x * x * iz2,
                    -fx * y * iz,
                ]
            )
            J1 = np.column_stack(
                [
                    np.zeros(n),
                    fy * iz,
                    -fy * y * iz2,
                    -fy - fy * y * y * iz2,
                    fy * x * y * iz2,
                    fy * x * iz,
                ]
            )
            bz = bf * iz2
            J2 = J0.copy()
            J2[:, 2] += bz
            J2[:, 3] += bz * y
            J2[:, 4] -= bz * x
            w2 = w * s3
            H = (J0.T * w) @ J0 + (J1.T * w) @ J1 + (J2.T * w2) @ J2
            g = J0.T @ (w * r0) + J1.T @ (w * r1) + J2.T @ (w2 * r2)
            H[np.diag_indices(6)] += 1e-9 + 1e-6 * np.diag(H)
            try:
                dx = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                break
            if not np.all(np.isfinite(dx)):
                break
            dT = np.eye(4)
            dT[:3, :3] = _rodrigues(dx[3:])
            dT[:3, 3] = dx[:3]
            T = dT @ T
            if np.abs(dx).max() < 1e-6:
                break
        _, _, r0, r1, r2, front = residuals(T)
        inlier = (info * (r0 * r0 + r1 * r1 + r2 * r2) <= chi2) & front
        if inlier.sum() < 3:
            break
    # Re-orthonormalize against round-off accumulated over the updates.
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    return T, inlier
