"""Rotations in compiled code (numba), for the solvers that step a pose inside their kernels
(:mod:`coop_slam.vo.pose_opt`, :mod:`.schur_ba`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def exp_so3(w):
    """The rotation of rotation vector ``w`` (as cv2.Rodrigues)."""
    theta = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    R = np.eye(3)
    if theta < 2.220446049250313e-16:
        return R
    c, s = math.cos(theta), math.sin(theta)
    c1 = 1.0 - c
    x, y, z = w[0] / theta, w[1] / theta, w[2] / theta
    R[0, 0], R[0, 1], R[0, 2] = c + c1 * x * x, c1 * x * y - s * z, c1 * x * z + s * y
    R[1, 0], R[1, 1], R[1, 2] = c1 * x * y + s * z, c + c1 * y * y, c1 * y * z - s * x
    R[2, 0], R[2, 1], R[2, 2] = c1 * x * z - s * y, c1 * y * z + s * x, c + c1 * z * z
    return R
