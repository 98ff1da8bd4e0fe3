"""Motion-only pose optimization (ORB-SLAM's ``PoseOptimization``) in numpy.

Residuals are (u, v) for keypoints without depth and (u, v, u_right) for keypoints with depth, where
``u_right = u - bf / z`` is the column in a virtual right camera (``bf`` = fx * virtual baseline),
so depth enters as a pixel-like residual with the same octave-dependent weight. A Huber kernel in
the first rounds, then outliers are classified by a chi-square gate after each round and left out of
the next one (they can come back). Tracking calls it twice per frame, so the Gauss-Newton step is
built for the interpreter's sake: all residual rows (u of every keypoint, v of every keypoint,
u_right of those with depth) in one array, the Jacobian rows filled in place into one
preallocated matrix, and the normal equations from one weighted product.
"""

from __future__ import annotations

import cv2
import numpy as np


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
    uv = np.asarray(uv_px, dtype=float)
    u_right = np.asarray(u_right_px, dtype=float)
    info = np.asarray(info, dtype=float)
    st = np.flatnonzero(np.isfinite(u_right))  # keypoints with depth: a third residual row
    measured = np.concatenate([uv[:, 0], uv[:, 1], u_right[st]])
    chi2 = np.full(n, chi2_mono)
    chi2[st] = chi2_stereo
    delta = np.sqrt(chi2)
    inlier = np.ones(n, bool)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rows = 2 * n + len(st)
    J = np.zeros((rows, 6))  # d(u; v; u_right) / d xi, xi = (rho, phi): T <- Exp(xi) T
    Ju, Jv, Jr = J[:n], J[n : 2 * n], J[2 * n :]
    predicted = np.empty(rows)
    w_rows = np.empty(rows)
    R, t = T[:3, :3].copy(), T[:3, 3].copy()

    def residuals(R, t):
        pc = P @ R.T
        pc += t
        front = pc[:, 2] > 1e-6
        iz = 1.0 / np.where(front, pc[:, 2], 1e-6)
        xn, yn = pc[:, 0] * iz, pc[:, 1] * iz
        np.multiply(xn, fx, out=predicted[:n])
        predicted[:n] += cx
        np.multiply(yn, fy, out=predicted[n : 2 * n])
        predicted[n : 2 * n] += cy
        predicted[2 * n :] = predicted[st] - bf * iz[st]
        r = predicted - measured
        e2 = r[:n] ** 2 + r[n : 2 * n] ** 2  # info-weighted squared error per keypoint
        e2[st] += r[2 * n :] ** 2
        e2 *= info
        return xn, yn, iz, r, e2, front

    for rnd in range(rounds):
        robust = rnd < 2
        for _ in range(iterations):
            xn, yn, iz, r, e2, front = residuals(R, t)
            w = info * (inlier & front)
            if robust:  # Huber
                w *= np.minimum(1.0, delta / np.sqrt(np.maximum(e2, 1e-12)))
            xy = xn * yn
            Ju[:, 0] = fx * iz
            Ju[:, 2] = -fx * xn * iz
            Ju[:, 3] = -fx * xy
            Ju[:, 4] = fx + fx * xn * xn
            Ju[:, 5] = -fx * yn
            Jv[:, 1] = fy * iz
            Jv[:, 2] = -fy * yn * iz
            Jv[:, 3] = -fy - fy * yn * yn
            Jv[:, 4] = fy * xy
            Jv[:, 5] = fy * xn
            w_rows[:n] = w
            w_rows[n : 2 * n] = w
            if len(st):
                # u_right = u - bf / z: the u row plus bf / z^2 times dz / d xi.
                bz = bf * iz[st]
                Jr[:] = Ju[st]
                Jr[:, 2] += bz * iz[st]
                Jr[:, 3] += bz * yn[st]
                Jr[:, 4] -= bz * xn[st]
                w_rows[2 * n :] = w[st]
            Jw = J.T * w_rows
            H = Jw @ J
            g = Jw @ r
            H[np.diag_indices(6)] += 1e-9 + 1e-6 * np.diag(H)
            try:
                dx = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                break
            if not np.all(np.isfinite(dx)):
                break
            dR = cv2.Rodrigues(dx[3:])[0]
            R = dR @ R
            t = dR @ t + dx[:3]
            if np.abs(dx).max() < 1e-6:
                break
        *_, e2, front = residuals(R, t)
        inlier = (e2 <= chi2) & front
        if inlier.sum() < 3:
            break
    # Re-orthonormalize against round-off accumulated over the updates.
    U, _, Vt = np.linalg.svd(R)
    T[:3, :3] = U @ Vt
    T[:3, 3] = t
    return T, inlier
