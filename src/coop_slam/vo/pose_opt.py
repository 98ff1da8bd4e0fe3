"""Motion-only pose optimization (ORB-SLAM's ``PoseOptimization``), compiled with numba.

Residuals are (u, v) for keypoints without depth and (u, v, u_right) for keypoints with depth, where
``u_right = u - bf / z`` is the column in a virtual right camera (``bf`` = fx * virtual baseline),
so depth enters as a pixel-like residual with the same octave-dependent weight. A Huber kernel in
the first rounds, then outliers are classified by a chi-square gate after each round and left out of
the next one (they can come back). Each round is Gauss-Newton with the fixed damping of
:data:`coop_slam.optim.lm.GAUSS_NEWTON` (every step taken, no cost evaluated, stop on a step below
its ``min_step``); a step xi = (rho, phi) moves (R, t) of ``T_cam_map`` as T <- Exp(xi) T.

Tracking calls it twice per frame: one loop over the keypoints per iteration, compiled (and
cached on disk by numba), instead of the dozen numpy calls on a few thousand rows each whose call
overhead dominated (issue #50: 4 ms of a RedKitchen frame's 21).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..optim.lm import DAMPING_FLOOR, GAUSS_NEWTON
from ..optim.rotation import exp_so3


@njit(cache=True, nogil=True)
def _residuals(R, t, P, uv, u_right, K, bf, i):
    """Keypoint i: (in front, x/z, y/z, 1/z, u, v and u_right residuals [px], has u_right); the
    residuals of a point not in front are not computed."""
    x = R[0, 0] * P[i, 0] + R[0, 1] * P[i, 1] + R[0, 2] * P[i, 2] + t[0]
    y = R[1, 0] * P[i, 0] + R[1, 1] * P[i, 1] + R[1, 2] * P[i, 2] + t[1]
    z = R[2, 0] * P[i, 0] + R[2, 1] * P[i, 1] + R[2, 2] * P[i, 2] + t[2]
    if not z > 1e-6:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False
    iz = 1.0 / z
    xn, yn = x * iz, y * iz
    ru = K[0, 0] * xn + K[0, 2] - uv[i, 0]
    rv = K[1, 1] * yn + K[1, 2] - uv[i, 1]
    stereo = math.isfinite(u_right[i])
    rr = K[0, 0] * xn + K[0, 2] - bf * iz - u_right[i] if stereo else 0.0
    return True, xn, yn, iz, ru, rv, rr, stereo


@njit(cache=True, nogil=True)
def _normal_equations(R, t, P, uv, u_right, info, inlier, robust, delta, K, bf, H, g):
    """(H, g) of the weighted normal equations at (R, t), in place."""
    fx, fy = K[0, 0], K[1, 1]
    H[:] = 0.0
    g[:] = 0.0
    ju = np.empty(6)
    jv = np.empty(6)
    jr = np.empty(6)
    for i in range(P.shape[0]):
        if not inlier[i]:
            continue
        front, xn, yn, iz, ru, rv, rr, stereo = _residuals(R, t, P, uv, u_right, K, bf, i)
        if not front:
            continue
        w = info[i]
        if robust:  # Huber
            e = math.sqrt(max((ru * ru + rv * rv + rr * rr) * info[i], 1e-12))
            w *= min(1.0, delta[i] / e)
        xy = xn * yn
        ju[0], ju[1], ju[2] = fx * iz, 0.0, -fx * xn * iz
        ju[3], ju[4], ju[5] = -fx * xy, fx + fx * xn * xn, -fx * yn
        jv[0], jv[1], jv[2] = 0.0, fy * iz, -fy * yn * iz
        jv[3], jv[4], jv[5] = -fy - fy * yn * yn, fy * xy, fy * xn
        for a in range(6):
            g[a] += w * (ju[a] * ru + jv[a] * rv)
            for b in range(a, 6):
                H[a, b] += w * (ju[a] * ju[b] + jv[a] * jv[b])
        if stereo:  # u_right = u - bf / z: the u row plus bf / z^2 times dz / d xi
            bz = bf * iz
            for a in range(6):
                jr[a] = ju[a]
            jr[2] += bz * iz
            jr[3] += bz * yn
            jr[4] -= bz * xn
            for a in range(6):
                g[a] += w * jr[a] * rr
                for b in range(a, 6):
                    H[a, b] += w * jr[a] * jr[b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]


@njit(cache=True, nogil=True)
def _solve_spd(H, g, step) -> bool:
    """step = -H^-1 g by Cholesky (H symmetric, damped); False when H is not positive definite."""
    L = np.zeros((6, 6))
    for i in range(6):
        for j in range(i + 1):
            s = H[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 0.0:
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    y = np.empty(6)
    for i in range(6):
        s = -g[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * step[k]
        step[i] = s / L[i, i]
    return True


@njit(cache=True, nogil=True)
def _errors(R, t, P, uv, u_right, info, K, bf, e2):
    """Info-weighted squared reprojection error per keypoint (inf behind the camera)."""
    for i in range(P.shape[0]):
        front, _, _, _, ru, rv, rr, _ = _residuals(R, t, P, uv, u_right, K, bf, i)
        e2[i] = (ru * ru + rv * rv + rr * rr) * info[i] if front else np.inf


@njit(cache=True, nogil=True)
def _optimize(R, t, P, uv, u_right, info, K, bf, chi2, rounds, iterations, lam, floor, min_step):
    """The rounds of :func:`optimize_pose` on (R, t) in place; returns the inlier mask."""
    n = P.shape[0]
    delta = np.sqrt(chi2)
    inlier = np.ones(n, np.bool_)
    solved = np.zeros(n, np.bool_)  # the inliers the last round solved with
    e2 = np.empty(n)
    H, g, step = np.empty((6, 6)), np.empty(6), np.empty(6)
    last_robust, converged = True, False
    for rnd in range(rounds):
        robust = rnd < 2
        if rnd > 0 and converged and robust == last_robust and np.array_equal(solved, inlier):
            continue  # the same problem from its own (converged) solution: it would not move
        last_robust, converged = robust, False
        for _ in range(iterations):
            _normal_equations(R, t, P, uv, u_right, info, inlier, robust, delta, K, bf, H, g)
            for a in range(6):
                H[a, a] += floor + lam * H[a, a]
            if not _solve_spd(H, g, step):
                break
            finite, largest = True, 0.0
            for a in range(6):
                finite = finite and math.isfinite(step[a])
                largest = max(largest, abs(step[a]))
            if not finite:
                break
            dR = exp_so3(step[3:])
            R[:] = dR @ R
            t[:] = dR @ t + step[:3]
            if largest < min_step:
                converged = True
                break
        _errors(R, t, P, uv, u_right, info, K, bf, e2)
        solved[:] = inlier
        count = 0
        for i in range(n):
            inlier[i] = e2[i] <= chi2[i]
            count += inlier[i]
        if count < 3:
            break
    return inlier


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
    u_right = np.ascontiguousarray(u_right_px, dtype=float)
    chi2 = np.where(np.isfinite(u_right), float(chi2_stereo), float(chi2_mono))
    R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
    inlier = _optimize(
        R,
        t,
        np.ascontiguousarray(points_map, dtype=float),
        np.ascontiguousarray(uv_px, dtype=float),
        u_right,
        np.ascontiguousarray(info, dtype=float),
        np.ascontiguousarray(K, dtype=float),
        float(bf),
        chi2,
        int(rounds),
        int(iterations),
        GAUSS_NEWTON.lambda_initial,
        DAMPING_FLOOR,
        GAUSS_NEWTON.min_step,
    )
    # Re-orthonormalize against round-off accumulated over the updates.
    U, _, Vt = np.linalg.svd(R)
    T[:3, :3] = U @ Vt
    T[:3, 3] = t
    return T, inlier
