"""Local bundle adjustment compiled with numba: the problem of :mod:`.bundle` -- (u, v) and
stereo-like (u, v, u_right) reprojection residuals under a Huber kernel with sigma = scale**octave
px, fixed keyframes, a ground robot's planar priors, a monocular map's scale anchor -- solved by
:func:`coop_slam.optim.lm.least_squares` with the points eliminated (Schur complement): each step
is one dense 6F x 6F system for the F free keyframes.

Why not GTSAM here: the client's local BA (16 keyframes, ~1,000 points, ~5,000 observations on
RedKitchen) took ~115 ms of CPU in GTSAM for every keyframe -- ~20 ms building its factors in
Python, the rest its generic factor graph's linearization and elimination, most of that memory
allocation -- in the process beside the odometry, on the robot's two cores (issue #50). The
server's global BA, which holds keyframes to their odometry with relative-pose priors, stays on
GTSAM (:func:`.bundle.run_local_ba` chooses).

Conventions: a keyframe is held as ``T_cam_map`` (R, t) and a step xi = (rho, phi) moves it as
T <- Exp(xi) T, as :mod:`coop_slam.vo.pose_opt`; the planar prior's information is given in
GTSAM's tangent of ``T_map_cam`` (rotation, translation; T <- T Exp(delta)), which is
delta = -(phi, rho) of that step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .lm import DAMPING_FLOOR, LmRules, least_squares
from .rotation import exp_so3


@dataclass
class SchurProblem:
    """Arrays of one local BA (see :func:`solve`); observations are the usable ones only."""

    obs_kf: np.ndarray  # (O,) int64 keyframe index
    obs_pt: np.ndarray  # (O,) int64 point index
    obs_uv: np.ndarray  # (O, 2)
    obs_u_right: np.ndarray  # (O,) NaN: a (u, v) residual
    obs_level: np.ndarray  # (O,) int64 pyramid level
    whiten_mono: np.ndarray  # (L,) 1 / sigma of a level [1/px]
    whiten_stereo: np.ndarray  # (L, 3, 3) upper-triangular W, W^T W = information of (u, v, ur)
    huber: np.ndarray  # (2,) Huber threshold of mono, stereo residuals [whitened px]
    K: np.ndarray  # (3, 3)
    bf: float  # fx * baseline [px m]
    free: np.ndarray  # (K,) int64: index among the free keyframes, -1 = fixed
    pt_start: np.ndarray  # (P + 1,) observations of point j: by_pt[pt_start[j]:pt_start[j+1]]
    by_pt: np.ndarray  # (O,) observation indices sorted by point
    prior_kf: np.ndarray  # (N,) int64 keyframes with a pose prior
    prior_T_map_cam: np.ndarray  # (N, 4, 4) the prior's mean
    prior_info: np.ndarray  # (N, 6, 6) information in GTSAM's tangent order
    anchor: np.ndarray  # (4,) fixed kf, free kf, distance [map units], sigma; kf -1: none


@njit(cache=True, nogil=True)
def _log_se3(R, t):
    """GTSAM's Pose3::Logmap of (R, t): (rotation vector, V^-1 t)."""
    out = np.zeros(6)
    cos_theta = max(-1.0, min(1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    theta = math.acos(cos_theta)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-8:
        w *= 0.5
    elif math.pi - theta < 1e-6:  # near pi: from the symmetric part
        B = 0.5 * (R + R.T) - cos_theta * np.eye(3)
        k = np.argmax(np.array([B[0, 0], B[1, 1], B[2, 2]]))
        axis = B[:, k] / max(math.sqrt(B[0, k] ** 2 + B[1, k] ** 2 + B[2, k] ** 2), 1e-300)
        if axis[0] * w[0] + axis[1] * w[1] + axis[2] * w[2] < 0.0:
            axis = -axis
        w = axis * theta
    else:
        w *= theta / (2.0 * math.sin(theta))
    out[:3] = w
    th = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if th < 1e-10:
        out[3:] = t
        return out
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]) / th
    WT = W @ t
    out[3:] = t - 0.5 * th * WT + (1.0 - th / (2.0 * math.tan(0.5 * th))) * (W @ WT)
    return out


@njit(cache=True, nogil=True)
def _whiten(p, o, d, level, M, cols):
    """M[:d, :cols] <- W M[:d, :cols] in place (W: the observation's whitening, upper triangular
    for a stereo one, 1 / sigma for a mono one)."""
    if d == 2:
        w = p[5][0][level]
        for a in range(2):
            for b in range(cols):
                M[a, b] *= w
        return
    W = p[5][1][level]
    for b in range(cols):
        m0, m1, m2 = M[0, b], M[1, b], M[2, b]
        M[0, b] = W[0, 0] * m0 + W[0, 1] * m1 + W[0, 2] * m2
        M[1, b] = W[1, 0] * m0 + W[1, 1] * m1 + W[1, 2] * m2
        M[2, b] = W[2, 0] * m0 + W[2, 1] * m1 + W[2, 2] * m2


@njit(cache=True, nogil=True)
def _observation(R, t, X, p, o, r, Jx, Jp, jacobians):
    """Observation o: whitened residual r (d x 1) and, with ``jacobians``, its Jacobians on the
    step xi of its keyframe (Jx, d x 6) and on its point (Jp, d x 3); returns d (2 or 3), 0 when
    the point is behind its camera. No allocation: it runs for every observation many times."""
    k, j = p[0][o], p[1][o]
    Rk, tk = R[k], t[k]
    x = Rk[0, 0] * X[j, 0] + Rk[0, 1] * X[j, 1] + Rk[0, 2] * X[j, 2] + tk[0]
    y = Rk[1, 0] * X[j, 0] + Rk[1, 1] * X[j, 1] + Rk[1, 2] * X[j, 2] + tk[1]
    z = Rk[2, 0] * X[j, 0] + Rk[2, 1] * X[j, 1] + Rk[2, 2] * X[j, 2] + tk[2]
    if not z > 1e-6:
        return 0
    K, bf, uv, ur_meas, level = p[6], p[7], p[2], p[3], p[4][o]
    fx, fy = K[0, 0], K[1, 1]
    iz = 1.0 / z
    xn, yn = x * iz, y * iz
    d = 3 if math.isfinite(ur_meas[o]) else 2
    r[0, 0] = fx * xn + K[0, 2] - uv[o, 0]
    r[1, 0] = fy * yn + K[1, 2] - uv[o, 1]
    if d == 3:
        r[2, 0] = r[0, 0] + uv[o, 0] - bf * iz - ur_meas[o]
    _whiten(p, o, d, level, r, 1)
    if not jacobians:
        return d
    # d(u, v, ur)/d(x, y, z) rows (a0, 0, a2), (0, b1, b2), (a0, 0, c2); d(x, y, z)/d xi =
    # [I, -[pc]x]; d(x, y, z)/d point = R.
    a0, a2 = fx * iz, -fx * xn * iz
    b1, b2 = fy * iz, -fy * yn * iz
    c2 = a2 + bf * iz * iz
    Jx[0, 0], Jx[0, 1], Jx[0, 2] = a0, 0.0, a2
    Jx[0, 3], Jx[0, 4], Jx[0, 5] = a2 * y, a0 * z - a2 * x, -a0 * y
    Jx[1, 0], Jx[1, 1], Jx[1, 2] = 0.0, b1, b2
    Jx[1, 3], Jx[1, 4], Jx[1, 5] = -b1 * z + b2 * y, -b2 * x, b1 * x
    for c in range(3):
        Jp[0, c] = a0 * Rk[0, c] + a2 * Rk[2, c]
        Jp[1, c] = b1 * Rk[1, c] + b2 * Rk[2, c]
    if d == 3:
        Jx[2, 0], Jx[2, 1], Jx[2, 2] = a0, 0.0, c2
        Jx[2, 3], Jx[2, 4], Jx[2, 5] = c2 * y, a0 * z - c2 * x, -a0 * y
        for c in range(3):
            Jp[2, c] = a0 * Rk[0, c] + c2 * Rk[2, c]
    _whiten(p, o, d, level, Jx, 6)
    _whiten(p, o, d, level, Jp, 3)
    return d


@njit(cache=True, nogil=True)
def _huber(e2, k):
    """(cost, weight) of a whitened squared error under GTSAM's Huber kernel."""
    e = math.sqrt(e2)
    if e <= k:
        return 0.5 * e2, 1.0
    return k * e - 0.5 * k * k, k / e


@njit(cache=True, nogil=True)
def _prior_residual(R, t, prior_T, info, i, k):
    """The prior i on keyframe k: (residual in GTSAM's tangent, its cost)."""
    # T_map_cam = (R^T, -R^T t); residual Log(T_prior^-1 T_map_cam).
    Rm = np.ascontiguousarray(R[k].T)
    tm = -(Rm @ t[k])
    RpT = np.ascontiguousarray(prior_T[i, :3, :3].T)
    r = _log_se3(RpT @ Rm, RpT @ (tm - prior_T[i, :3, 3]))
    return r, 0.5 * (r @ (info[i] @ r))


@njit(cache=True, nogil=True)
def _anchor_residual(R, t, anchor):
    """(whitened residual, n = unit vector between the camera centres, centre of the free kf)."""
    f, k = int(anchor[0]), int(anchor[1])
    cf = -(R[f].T @ t[f])
    ck = -(R[k].T @ t[k])
    diff = ck - cf
    dist = math.sqrt(diff @ diff)
    return (dist - anchor[2]) / anchor[3], diff / max(dist, 1e-300)


@njit(cache=True, nogil=True)
def _cost(R, t, X, p, pri):
    total = 0.0
    r, Jx, Jp = np.empty((3, 1)), np.empty((3, 6)), np.empty((3, 3))
    for o in range(p[0].shape[0]):
        stereo = math.isfinite(p[3][o])
        k = p[8][1] if stereo else p[8][0]
        d = _observation(R, t, X, p, o, r, Jx, Jp, False)
        if d == 0:  # behind its camera: GTSAM's error there, 2 fx px a row (whitened)
            d = 3 if stereo else 2
            r[0, 0] = r[1, 0] = r[2, 0] = 2.0 * p[6][0, 0]
            _whiten(p, o, d, p[4][o], r, 1)
        e2 = r[0, 0] ** 2 + r[1, 0] ** 2 + (r[2, 0] ** 2 if d == 3 else 0.0)
        total += _huber(e2, k)[0]
    for i in range(pri[0].shape[0]):
        total += _prior_residual(R, t, pri[1], pri[2], i, pri[0][i])[1]
    if pri[3][0] >= 0:
        total += 0.5 * _anchor_residual(R, t, pri[3])[0] ** 2
    return total


@njit(cache=True, nogil=True)
def _linearize(R, t, X, p, pri, free, n_free):
    """Normal equations: (Hpp (F, 6, 6), gp (F, 6), Hll (P, 3, 3), gl (P, 3), Hpl (O, 6, 3)); Hpp
    holds the free poses' diagonal blocks, the only ones an observation or a prior touches."""
    n_obs, n_pts = p[0].shape[0], X.shape[0]
    Hpp, gp = np.zeros((n_free, 6, 6)), np.zeros((n_free, 6))
    Hll, gl = np.zeros((n_pts, 3, 3)), np.zeros((n_pts, 3))
    Hpl = np.zeros((n_obs, 6, 3))
    r, Jx, Jp = np.empty((3, 1)), np.empty((3, 6)), np.empty((3, 3))
    for o in range(n_obs):
        d = _observation(R, t, X, p, o, r, Jx, Jp, True)
        if d == 0:
            continue
        e2 = r[0, 0] ** 2 + r[1, 0] ** 2 + (r[2, 0] ** 2 if d == 3 else 0.0)
        w = _huber(e2, p[8][1] if d == 3 else p[8][0])[1]
        k, j = free[p[0][o]], p[1][o]
        for a in range(3):
            for c in range(d):
                gl[j, a] += w * Jp[c, a] * r[c, 0]
                for b in range(3):
                    Hll[j, a, b] += w * Jp[c, a] * Jp[c, b]
        if k < 0:
            continue
        for a in range(6):
            for c in range(d):
                gp[k, a] += w * Jx[c, a] * r[c, 0]
                for b in range(6):
                    Hpp[k, a, b] += w * Jx[c, a] * Jx[c, b]
                for b in range(3):
                    Hpl[o, a, b] += w * Jx[c, a] * Jp[c, b]
    # Priors: the residual's Jacobian on xi is -P (P: (rho, phi) -> (phi, rho)) to first order.
    for i in range(pri[0].shape[0]):
        k = free[pri[0][i]]
        if k < 0:
            continue
        res, _ = _prior_residual(R, t, pri[1], pri[2], i, pri[0][i])
        info = pri[2][i]
        for a in range(6):
            pa = (a + 3) % 6
            for b in range(6):
                Hpp[k, a, b] += info[pa, (b + 3) % 6]
            s = 0.0
            for b in range(6):
                s += info[pa, b] * res[b]
            gp[k, a] -= s
    if pri[3][0] >= 0 and free[int(pri[3][1])] >= 0:
        k = free[int(pri[3][1])]
        res, n = _anchor_residual(R, t, pri[3])
        # d centre / d rho = -R^T (the centre does not move with phi to first order)
        J = -(R[int(pri[3][1])] @ n) / pri[3][3]
        for a in range(3):
            gp[k, a] += J[a] * res
            for b in range(3):
                Hpp[k, a, b] += J[a] * J[b]
    return Hpp, gp, Hll, gl, Hpl


@njit(cache=True, nogil=True)
def _inverse_damped3(H, lam, out) -> bool:
    """out <- (H + lam diag(H) + floor I)^-1 of a symmetric 3x3 H; False if singular."""
    a = H[0, 0] * (1.0 + lam) + DAMPING_FLOOR
    e = H[1, 1] * (1.0 + lam) + DAMPING_FLOOR
    i = H[2, 2] * (1.0 + lam) + DAMPING_FLOOR
    b, c, f = H[0, 1], H[0, 2], H[1, 2]
    A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * A + b * B + c * C
    if not abs(det) > 0.0 or not math.isfinite(det):
        return False
    out[0, 0], out[0, 1], out[0, 2] = A / det, B / det, C / det
    out[1, 0], out[1, 1], out[1, 2] = B / det, (a * i - c * c) / det, (b * c - a * f) / det
    out[2, 0], out[2, 1], out[2, 2] = C / det, (b * c - a * f) / det, (a * e - b * b) / det
    return True


@njit(cache=True, nogil=True)
def _solve(Hpp, gp, Hll, gl, Hpl, p, free, lam):
    """(step of the free poses (F, 6), of the points (P, 3), solvable) of the system damped by
    lam: the points eliminated, the reduced system by Cholesky."""
    n_free, n_pts = gp.shape[0], gl.shape[0]
    S = np.zeros((6 * n_free, 6 * n_free))
    rhs = np.empty(6 * n_free)
    for k in range(n_free):
        for a in range(6):
            rhs[6 * k + a] = -gp[k, a]
            for b in range(6):
                S[6 * k + a, 6 * k + b] = Hpp[k, a, b]
    for q in range(6 * n_free):
        S[q, q] += DAMPING_FLOOR + lam * S[q, q]
    Hll_inv = np.empty((n_pts, 3, 3))
    Y = np.empty((64, 6, 3))  # Hpl Hll^-1 of a point's observations by free keyframes
    ks = np.empty(64, np.int64)
    for j in range(n_pts):
        if not _inverse_damped3(Hll[j], lam, Hll_inv[j]):
            return np.zeros((n_free, 6)), np.zeros((n_pts, 3)), False
        m = 0
        for a_i in range(p[9][j], p[9][j + 1]):
            a = p[10][a_i]
            ka = free[p[0][a]]
            if ka < 0:
                continue
            if m == Y.shape[0]:
                Y2 = np.empty((2 * m, 6, 3))
                Y2[:m] = Y
                Y = Y2
                k2 = np.empty(2 * m, np.int64)
                k2[:m] = ks
                ks = k2
            Hj, Ha, Ya = Hll_inv[j], Hpl[a], Y[m]
            for r in range(6):
                for c in range(3):
                    Ya[r, c] = Ha[r, 0] * Hj[0, c] + Ha[r, 1] * Hj[1, c] + Ha[r, 2] * Hj[2, c]
                rhs[6 * ka + r] += Ya[r, 0] * gl[j, 0] + Ya[r, 1] * gl[j, 1] + Ya[r, 2] * gl[j, 2]
            ks[m] = a
            m += 1
        for u in range(m):
            ku = free[p[0][ks[u]]]
            Yu = Y[u]
            for v in range(m):
                kv = free[p[0][ks[v]]]
                Hv = Hpl[ks[v]]
                for r in range(6):
                    for c in range(6):
                        S[6 * ku + r, 6 * kv + c] -= (
                            Yu[r, 0] * Hv[c, 0] + Yu[r, 1] * Hv[c, 1] + Yu[r, 2] * Hv[c, 2]
                        )
    dp = np.zeros((n_free, 6))
    if n_free:
        try:
            L = np.linalg.cholesky(S)
        except Exception:  # noqa: BLE001  (not positive definite)
            return dp, np.zeros((n_pts, 3)), False
        y = np.linalg.solve(L, rhs)
        dp = np.linalg.solve(L.T, y).reshape(n_free, 6)
    dl = np.empty((n_pts, 3))
    b = np.empty(3)
    for j in range(n_pts):
        b[:] = -gl[j]
        for a_i in range(p[9][j], p[9][j + 1]):
            a = p[10][a_i]
            ka = free[p[0][a]]
            if ka >= 0:
                for c in range(3):
                    for r in range(6):
                        b[c] -= Hpl[a, r, c] * dp[ka, r]
        for c in range(3):
            dl[j, c] = Hll_inv[j, c, 0] * b[0] + Hll_inv[j, c, 1] * b[1] + Hll_inv[j, c, 2] * b[2]
    return dp, dl, True


@njit(cache=True, nogil=True)
def _model_decrease(Hpp, gp, Hll, gl, Hpl, p, free, dp, dl):
    """-(g . step + step^T H step / 2) of the undamped system."""
    q = 0.0
    lin = 0.0
    n_free = gp.shape[0]
    for k in range(n_free):
        for a in range(6):
            lin += gp[k, a] * dp[k, a]
            for b in range(6):
                q += dp[k, a] * Hpp[k, a, b] * dp[k, b]
    for j in range(gl.shape[0]):
        for a in range(3):
            lin += gl[j, a] * dl[j, a]
            for b in range(3):
                q += dl[j, a] * Hll[j, a, b] * dl[j, b]
    for o in range(p[0].shape[0]):
        k = free[p[0][o]]
        if k < 0:
            continue
        j = p[1][o]
        for a in range(6):
            for b in range(3):
                q += 2.0 * dp[k, a] * Hpl[o, a, b] * dl[j, b]
    return -(lin + 0.5 * q)


@njit(cache=True, nogil=True)
def _retract(R, t, X, free, dp, dl):
    R2, t2, X2 = R.copy(), t.copy(), X + dl
    for k in range(R.shape[0]):
        m = free[k]
        if m < 0:
            continue
        E = exp_so3(dp[m, 3:])
        R2[k] = E @ R[k]
        t2[k] = E @ t[k] + dp[m, :3]
    return R2, t2, X2


class _LocalBa:
    """:class:`SchurProblem` for :func:`least_squares`; state = (R, t, points)."""

    def __init__(self, problem: SchurProblem):
        q = problem
        self.free = q.free
        self.n_free = int((q.free >= 0).sum())
        # numba takes tuples of arrays: observations (with the per-point index), priors.
        self.p = (
            q.obs_kf, q.obs_pt, q.obs_uv, q.obs_u_right, q.obs_level,
            (q.whiten_mono, q.whiten_stereo), q.K, float(q.bf), q.huber, q.pt_start, q.by_pt,
        )  # fmt: skip
        self.pri = (q.prior_kf, q.prior_T_map_cam, q.prior_info, q.anchor)

    def cost(self, state) -> float:
        return _cost(*state, self.p, self.pri)

    def linearize(self, state):
        return _linearize(*state, self.p, self.pri, self.free, self.n_free)

    def solve(self, lin, lam: float) -> np.ndarray:
        dp, dl, ok = _solve(*lin, self.p, self.free, lam)
        if not ok:
            raise np.linalg.LinAlgError("reduced camera system not positive definite")
        return np.concatenate([dp.ravel(), dl.ravel()])

    def _split(self, step: np.ndarray):
        n = 6 * self.n_free
        return step[:n].reshape(-1, 6), step[n:].reshape(-1, 3)

    def predicted_decrease(self, lin, step: np.ndarray) -> float:
        return _model_decrease(*lin, self.p, self.free, *self._split(step))

    def retract(self, state, step: np.ndarray):
        return _retract(*state, self.free, *self._split(step))


def solve(problem: SchurProblem, T_map_cam: np.ndarray, points_map: np.ndarray, rules: LmRules):
    """Optimized (T_map_cam (K, 4, 4), points (P, 3), LM iterations) from the given ones."""
    T_cam_map = np.linalg.inv(T_map_cam)
    state = (
        np.ascontiguousarray(T_cam_map[:, :3, :3]),
        np.ascontiguousarray(T_cam_map[:, :3, 3]),
        np.array(points_map, dtype=float),
    )
    outcome = least_squares(_LocalBa(problem), state, rules)
    R, t, X = outcome.state
    T_new = np.array(T_map_cam, dtype=float, copy=True)
    moved = problem.free >= 0  # the fixed keyframes come back exactly as given
    T_new[moved, :3, :3] = R[moved].transpose(0, 2, 1)
    T_new[moved, :3, 3] = -np.einsum("kji,kj->ki", R[moved], t[moved])
    return T_new, X, outcome.iterations


def warm_up() -> None:
    """Compile the kernels (or load them from numba's cache) on a tiny problem: two keyframes,
    one fixed, four points seen by both, one mono and one stereo observation kind, a prior."""
    T_map_cam = np.stack([np.eye(4), np.eye(4)])
    T_map_cam[1, 0, 3] = 0.1
    points = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0], [0.0, 0.5, 2.5], [0.5, 0.5, 3.0]])
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    obs_kf = np.repeat(np.arange(2), 4).astype(np.int64)
    obs_pt = np.tile(np.arange(4), 2).astype(np.int64)
    pc = points[obs_pt] - T_map_cam[obs_kf, :3, 3]
    uv = pc[:, :2] / pc[:, 2:] * 500.0 + [320.0, 240.0]
    by_pt = np.argsort(obs_pt, kind="stable").astype(np.int64)
    problem = SchurProblem(
        obs_kf=obs_kf, obs_pt=obs_pt, obs_uv=uv,
        obs_u_right=np.where(np.arange(8) % 2 == 0, uv[:, 0] - 20.0 / pc[:, 2], np.nan),
        obs_level=np.zeros(8, np.int64), whiten_mono=np.ones(8),
        whiten_stereo=np.repeat(np.eye(3)[None], 8, axis=0), huber=np.array([2.447, 2.796]),
        K=K, bf=20.0, free=np.array([-1, 0], np.int64),
        pt_start=np.searchsorted(obs_pt[by_pt], np.arange(5)).astype(np.int64), by_pt=by_pt,
        prior_kf=np.array([1], np.int64), prior_T_map_cam=T_map_cam[1:].copy(),
        prior_info=np.eye(6)[None] * 1e-3, anchor=np.array([0.0, 1.0, 0.1, 1e-5]),
    )  # fmt: skip
    solve(problem, T_map_cam, points + 0.01, LmRules(max_iterations=2))
