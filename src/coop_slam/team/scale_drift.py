"""Scale drift of a monocular map in the team pose graph.

A monocular client's map has one scale only approximately: it drifts along the path (ORB-SLAM's
reason for Sim(3) pose graphs). GTSAM 4.2's Python wrapper has ``Similarity3`` but no factors on
it, so a monocular map's keyframes keep their ``Pose3`` variables and each gets one more: ``s``,
the log of its map's local scale against the map's current one (0: as the client measured).

Its client factors (odometry and covisible, see :mod:`.pose_graph`) then measure
``T_cami_camj`` with the translation times ``exp((s_i + s_j) / 2)``, and carry one more row: the
random walk ``s_j - s_i`` (the drift between the keyframes, sigma growing with their distance).
Links and merges to robots with depth, which are metric, measure the scale where they are; the
random walk carries it along the path; one weak prior on the map's first keyframe holds the
scale where nothing measures it (a map joined by one merge alone).
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

# A scale variable shares its keyframe's symbol character; its index carries this bit (keyframe
# ids stay below it, see pose_graph).
SCALE_BIT = 1 << 55


def scale_key(robot_id: int, keyframe_id: int) -> int:
    """Graph key of a keyframe's log-scale variable."""
    return gtsam.Symbol(chr(ord("a") + robot_id), SCALE_BIT | keyframe_id).key()


def is_scale_key(gkey: int) -> bool:
    return bool(gtsam.Symbol(gkey).index() & SCALE_BIT)


def _error(T_meas: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
    ki, kj, si_key, sj_key = this.keys()
    X_i, X_j = values.atPose3(ki), values.atPose3(kj)
    s_i, s_j = values.atDouble(si_key), values.atDouble(sj_key)
    scale = float(np.exp(0.5 * (s_i + s_j)))
    R = T_meas[:3, :3]
    Z = gtsam.Pose3(gtsam.Rot3(R), scale * T_meas[:3, 3])
    H_i, H_j = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    hx = X_i.between(X_j, H_i, H_j)
    H_Z, H_hx = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    E = Z.between(hx, H_Z, H_hx)
    H_log = np.zeros((6, 6), order="F")
    e_pose = gtsam.Pose3.Logmap(E, H_log)
    error = np.concatenate([e_pose, [s_j - s_i]])
    if H is not None:
        A = H_log @ H_hx
        # d Z / d u for Z's translation scale exp(u): the translation moves by Z.t du, which is
        # R^T Z.t in Z's tangent space (translation rows last).
        dZ = np.zeros(6)
        dZ[3:] = R.T @ (scale * T_meas[:3, 3])
        d_pose_ds = 0.5 * (H_log @ H_Z @ dZ)
        J_i = np.zeros((7, 6))
        J_j = np.zeros((7, 6))
        J_i[:6] = A @ H_i
        J_j[:6] = A @ H_j
        J_si = np.zeros((7, 1))
        J_sj = np.zeros((7, 1))
        J_si[:6, 0] = d_pose_ds
        J_sj[:6, 0] = d_pose_ds
        J_si[6, 0] = -1.0
        J_sj[6, 0] = 1.0
        H[0], H[1], H[2], H[3] = J_i, J_j, J_si, J_sj
    return error


def scaled_between_factor(
    key_i: int,
    key_j: int,
    skey_i: int,
    skey_j: int,
    T_meas: np.ndarray,
    rot_sigma: float,
    trans_sigma: float,
    drift_sigma: float,
) -> gtsam.CustomFactor:
    """A client factor between two keyframes of a monocular map with their log-scale variables
    (see the module docstring); sigmas: the pose rows' and the drift between them."""
    r, t = rot_sigma, trans_sigma
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, t, t, t, drift_sigma]))
    return gtsam.CustomFactor(
        noise, [key_i, key_j, skey_i, skey_j], partial(_error, np.asarray(T_meas, float))
    )


def scale_prior_factor(skey: int, sigma: float) -> gtsam.PriorFactorDouble:
    """The map's scale as the client measured it (log scale 0), with ``sigma``."""
    return gtsam.PriorFactorDouble(skey, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, sigma))
