"""Motion-only pose optimization (ORB-SLAM's ``PoseOptimization``) in numpy.

Residuals are (u, v) for keypoints without depth and (u, v, u_right) for keypoints with depth, where
``u_right = u - bf / z`` is the column in a virtual right camera (``bf`` = fx * virtual baseline),
so depth enters as a pixel-like residual with the same octave-dependent weight. A Huber kernel in
the first rounds, then outliers are classified by a chi-square gate after each round and left out of
the next one (they can come back). Each round is :func:`coop_slam.optim.lm.least_squares` in its
Gauss-Newton configuration (every step taken, no cost evaluated). Tracking calls it twice per
frame, so the linearization is built for the interpreter's sake: all residual rows (u of every
keypoint, v of every keypoint, u_right of those with depth) in one array, the Jacobian rows filled
in place into one preallocated matrix, and the normal equations from one weighted product.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..optim.lm import GAUSS_NEWTON, damp, least_squares


class _PoseProblem:
    """The reprojection residuals of one frame's matches as a problem for ``least_squares``; the
    state is (R, t) of ``T_cam_map``, a step xi = (rho, phi) moves it as T <- Exp(xi) T."""

    def __init__(self, points_map, uv, u_right, info, K, bf, chi2):
        n = len(points_map)
        self.n, self.P, self.info, self.bf = n, points_map, info, bf
        self.st = st = np.flatnonzero(np.isfinite(u_right))  # keypoints with depth: a third row
        self.measured = np.concatenate([uv[:, 0], uv[:, 1], u_right[st]])
        self.delta = np.sqrt(chi2)
        self.fx, self.fy, self.cx, self.cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        rows = 2 * n + len(st)
        self.J = np.zeros((rows, 6))  # d(u; v; u_right) / d xi
        self.predicted = np.empty(rows)
        self.w_rows = np.empty(rows)
        # set per round by optimize_pose: which keypoints count, and whether under Huber
        self.inlier = np.ones(n, bool)
        self.robust = True

    def residuals(self, R, t):
        """(x/z, y/z, 1/z, residual rows, info-weighted squared error per keypoint, in front)."""
        n, st, predicted = self.n, self.st, self.predicted
        pc = self.P @ R.T
        pc += t
        front = pc[:, 2] > 1e-6
        iz = 1.0 / np.where(front, pc[:, 2], 1e-6)
        xn, yn = pc[:, 0] * iz, pc[:, 1] * iz
        np.multiply(xn, self.fx, out=predicted[:n])
        predicted[:n] += self.cx
        np.multiply(yn, self.fy, out=predicted[n : 2 * n])
        predicted[n : 2 * n] += self.cy
        predicted[2 * n :] = predicted[st] - self.bf * iz[st]
        r = predicted - self.measured
        e2 = r[:n] ** 2 + r[n : 2 * n] ** 2
        e2[st] += r[2 * n :] ** 2
        e2 *= self.info
        return xn, yn, iz, r, e2, front

    def linearize(self, state):
        """(H, g) of the weighted normal equations at ``state``."""
        n, st, fx, fy, J, w_rows = self.n, self.st, self.fx, self.fy, self.J, self.w_rows
        xn, yn, iz, r, e2, front = self.residuals(*state)
        w = self.info * (self.inlier & front)
        if self.robust:  # Huber
            w *= np.minimum(1.0, self.delta / np.sqrt(np.maximum(e2, 1e-12)))
        Ju, Jv, Jr = J[:n], J[n : 2 * n], J[2 * n :]
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
            bz = self.bf * iz[st]
            Jr[:] = Ju[st]
            Jr[:, 2] += bz * iz[st]
            Jr[:, 3] += bz * yn[st]
            Jr[:, 4] -= bz * xn[st]
            w_rows[2 * n :] = w[st]
        Jw = J.T * w_rows
        return Jw @ J, Jw @ r

    @staticmethod
    def solve(linearization, lam):
        H, g = linearization  # fresh each linearization: damped in place
        return -np.linalg.solve(damp(H, lam, in_place=True), g)

    @staticmethod
    def retract(state, step):
        R, t = state
        dR = cv2.Rodrigues(step[3:])[0]
        return dR @ R, dR @ t + step[:3]


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
    u_right = np.asarray(u_right_px, dtype=float)
    chi2 = np.full(n, chi2_mono)
    chi2[np.isfinite(u_right)] = chi2_stereo
    problem = _PoseProblem(
        np.asarray(points_map, dtype=float),
        np.asarray(uv_px, dtype=float),
        u_right,
        np.asarray(info, dtype=float),
        K,
        bf,
        chi2,
    )
    rules = GAUSS_NEWTON
    if iterations != rules.max_iterations:
        rules = dataclasses.replace(rules, max_iterations=iterations)
    state = (T[:3, :3].copy(), T[:3, 3].copy())
    inlier = None  # the inliers the last round solved with
    for rnd in range(rounds):
        robust = rnd < 2
        if (
            robust == problem.robust
            and inlier is not None
            and np.array_equal(inlier, problem.inlier)
        ):
            # The same problem from its own solution: the round would not move (8 % of
            # tracking's rounds on RedKitchen).
            continue
        problem.robust = robust
        state = least_squares(problem, state, rules).state
        *_, e2, front = problem.residuals(*state)
        inlier = problem.inlier
        problem.inlier = (e2 <= chi2) & front
        if problem.inlier.sum() < 3:
            break
    # Re-orthonormalize against round-off accumulated over the updates.
    R, t = state
    U, _, Vt = np.linalg.svd(R)
    T[:3, :3] = U @ Vt
    T[:3, 3] = t
    return T, problem.inlier
