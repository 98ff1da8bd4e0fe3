"""Scale drift of a monocular map in the team pose graph.

A monocular client's map has one scale only approximately: it drifts along the path (ORB-SLAM's
reason for Sim(3) pose graphs). GTSAM 4.2's Python wrapper has ``Similarity3`` but no factors on
it, so a monocular map's keyframes keep their ``Pose3`` variables and each gets one more: ``s``,
the log of its map's local scale against the map's current one (0: as the client measured).

Its client factors (odometry and covisible, see :mod:`.pose_graph`) then measure
``T_cami_camj`` with the translation times ``exp((s_i + s_j) / 2)``, and carry one more row: the
random walk ``s_j - s_i`` (the drift between the keyframes, sigma growing with their distance).
Loops and links measured by a similarity (:func:`scaled_link_factor`) carry its scale as a row
``s_j - s_i - log s_ab``: a loop of a monocular map measures how far its scale drifted around
the loop (ORB-SLAM's Sim(3) loop), a link to another map the two maps' local scales, a link to a
metric map (s = 0) the scale in metres. The random walk carries them along the path; one weak
prior on the map's first keyframe holds the scale where nothing measures it (a map joined by one
merge alone; in a group of monocular maps only, the group's one free scale).
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


def pose_sigmas(rot_sigma: float, trans_sigma: float, *more: float) -> np.ndarray:
    """A factor's sigmas in GTSAM's Pose3 order (rotation, then translation), and of any rows
    after them (a scale row)."""
    r, t = rot_sigma, trans_sigma
    return np.array([r, r, r, t, t, t, *more], dtype=float)


def _error(
    T_meas: np.ndarray,
    w_i: float,
    w_j: float,
    log_s_ab: float | None,
    has_i: bool,
    has_j: bool,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    H,
) -> np.ndarray:
    """``[Logmap(Z^-1 X_i^-1 X_j), s_j - s_i - log_s_ab]`` with ``Z`` the measurement whose
    translation is times ``exp(w_i s_i + w_j s_j)``, the last row only when ``log_s_ab`` is
    given; a keyframe without a scale variable (a metric map's) has ``s = 0``. Keys: the two
    poses, then the scale variables present."""
    keys = this.keys()
    X_i, X_j = values.atPose3(keys[0]), values.atPose3(keys[1])
    s_i = values.atDouble(keys[2]) if has_i else 0.0
    s_j = values.atDouble(keys[2 + has_i]) if has_j else 0.0
    scale = float(np.exp(w_i * s_i + w_j * s_j))
    R = T_meas[:3, :3]
    Z = gtsam.Pose3(gtsam.Rot3(R), scale * T_meas[:3, 3])
    H_i, H_j = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    hx = X_i.between(X_j, H_i, H_j)
    H_Z, H_hx = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    E = Z.between(hx, H_Z, H_hx)
    H_log = np.zeros((6, 6), order="F")
    e_pose = gtsam.Pose3.Logmap(E, H_log)
    rows = 6 if log_s_ab is None else 7
    error = e_pose if log_s_ab is None else np.concatenate([e_pose, [s_j - s_i - log_s_ab]])
    if H is not None:
        A = H_log @ H_hx
        # d Z / d u for Z's translation scale exp(u): the translation moves by Z.t du, which is
        # R^T Z.t in Z's tangent space (translation rows last).
        dZ = np.zeros(6)
        dZ[3:] = R.T @ (scale * T_meas[:3, 3])
        d_pose_du = H_log @ H_Z @ dZ
        J_i = np.zeros((rows, 6))
        J_j = np.zeros((rows, 6))
        J_i[:6] = A @ H_i
        J_j[:6] = A @ H_j
        H[0], H[1] = J_i, J_j
        slot = 2
        for present, w, sign in ((has_i, w_i, -1.0), (has_j, w_j, 1.0)):
            if present:
                J_s = np.zeros((rows, 1))
                J_s[:6, 0] = w * d_pose_du
                if rows == 7:
                    J_s[6, 0] = sign
                H[slot] = J_s
                slot += 1
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
    noise = gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas(rot_sigma, trans_sigma, drift_sigma))
    error = partial(_error, np.asarray(T_meas, float), 0.5, 0.5, 0.0, True, True)
    return gtsam.CustomFactor(noise, [key_i, key_j, skey_i, skey_j], error)


def scaled_link_factor(
    key_i: int,
    key_j: int,
    skey_i: int | None,
    skey_j: int | None,
    T_meas: np.ndarray,
    log_s_ab: float | None,
    rot_sigma: float,
    trans_sigma: float,
    scale_sigma: float | None,
    robust=None,
) -> gtsam.CustomFactor:
    """A loop or link ``T_meas`` between keyframe i (map a) and j (map b) of which at least one
    has a log-scale variable (``skey_*``; None for a metric map's keyframe): its translation is in
    a's lengths at i (times ``exp(s_i)`` in the graph); measured by a similarity, its scale
    ``log_s_ab`` (b's lengths in a's) measures the local scales, ``s_j - s_i``, with
    ``scale_sigma`` (both None: a rigid measurement, no scale row). ``robust``: an mEstimator
    kernel, or None."""
    if skey_i is None and skey_j is None:
        raise ValueError("a scaled link needs a scale variable on at least one end")
    extra = () if log_s_ab is None else (scale_sigma,)
    noise = gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas(rot_sigma, trans_sigma, *extra))
    if robust is not None:
        noise = gtsam.noiseModel.Robust.Create(robust, noise)
    keys = [key_i, key_j] + [k for k in (skey_i, skey_j) if k is not None]
    error = partial(
        _error,
        np.asarray(T_meas, float),
        1.0,
        0.0,
        None if log_s_ab is None else float(log_s_ab),
        skey_i is not None,
        skey_j is not None,
    )
    return gtsam.CustomFactor(noise, keys, error)


def scale_prior_factor(skey: int, sigma: float) -> gtsam.PriorFactorDouble:
    """The map's scale as the client measured it (log scale 0), with ``sigma``."""
    return gtsam.PriorFactorDouble(skey, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, sigma))
