"""Local bundle adjustment, as a pure function of arrays: compiled (:mod:`.schur_ba`), or with
GTSAM when the problem holds keyframes to relative-pose priors (the server's global BA).

The problem is plain numpy data (picklable) so it can run in a worker process (:class:`BaWorker`):
GTSAM's Python bindings hold the GIL while optimizing (measured: a 370 ms optimize() stalled
another Python thread for 330 ms), so a background *thread* would stall tracking for the whole
optimization.
The worker is a plain ``python -m coop_slam.optim.bundle`` child fed pickles over a pipe rather than
a multiprocessing pool: "spawn" re-imports the caller's ``__main__`` (breaks scripts and ROS nodes
without a main guard) and "fork" of a multi-threaded process can deadlock.

Factors, as ORB-SLAM2's RGB-D local BA (named as GTSAM's; the compiled solver has the same
residuals): keypoints with a usable depth get a ``GenericStereoFactor3D`` on (u, v, u_right) of a
virtual stereo pair (u_right = u - fx * baseline / depth), the others a
``GenericProjectionFactorCal3_S2``; both with a Huber kernel and sigma = scale**octave px.
Keyframes outside the window that see window points are held fixed (stiff ``PriorFactorPose3``;
the compiled solver does not move them). A monocular camera has projection factors only; its
map's scale is held by the fixed keyframes, or (fewer than two of them) by a range factor between
a fixed and a free keyframe (``scale_anchor``).
"""

from __future__ import annotations

import atexit
import logging
import os
import pickle
import select
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..geometry import invert, se3

log = logging.getLogger(__name__)


@dataclass
class BaProblem:
    segment: int
    kf_ids: np.ndarray  # (K,)
    T_map_cam: np.ndarray  # (K, 4, 4)
    fixed: np.ndarray  # (K,) bool
    point_ids: np.ndarray  # (P,)
    points_map: np.ndarray  # (P, 3)
    obs_kf: np.ndarray  # (O,) index into kf_ids
    obs_pt: np.ndarray  # (O,) index into point_ids
    obs_kp: np.ndarray  # (O,) keypoint index in its keyframe
    obs_uv: np.ndarray  # (O, 2)
    obs_u_right: np.ndarray  # (O,) NaN = no usable depth (projection factor)
    obs_octave: np.ndarray  # (O,)
    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    scale_factor: float
    n_levels: int
    iterations: int = 5
    huber_mono: float = 2.447
    huber_stereo: float = 2.796
    chi2_mono: float = 5.991
    chi2_stereo: float = 7.815
    # Standard deviation of the measured disparity (fx * baseline / depth) [px]. None: the
    # ORB-SLAM model (u_right as noisy as u). With a depth sensor's noise sigma_z = c * z^2 it is
    # fx * baseline * c at every range, much smaller than a pixel for a Kinect, so depth then
    # constrains the points (correlated (u, u_right) noise: u_right = u - disparity).
    disparity_sigma_px: float | None = None
    # Ground robot (see VoConfig.planar): the floor normal in the camera frame ((3,), or
    # (K, 3) one per keyframe), and the (tilt [rad], height [m]) std of the soft prior holding each
    # keyframe at its start height and tilt. None: no prior. planar_T_map_plane (K, 4, 4): each
    # keyframe's plane (see planar_prior); None: the level frame at the map origin.
    planar_up_cam: np.ndarray | None = None
    planar_sigmas: tuple[float, float] = (0.0, 0.0)
    planar_T_map_plane: np.ndarray | None = None
    # Monocular map (no metric scale): (index of a fixed keyframe, index of a free one) whose
    # distance is held at its current value. With fewer than two fixed keyframes the problem's
    # scale is a gauge freedom, and LM's small damping lets it wander (docs/tuning.md). None: no
    # such factor.
    scale_anchor: tuple[int, int] | None = None
    # Relative-pose priors between keyframes (a robot's own odometry, which the server's global
    # BA keeps a thinned map's shape by): index pairs (B, 2), measured T_i_j (B, 4, 4) and their
    # (rotation [rad], translation [m]) sigmas (B, 2). None: none.
    between_pairs: np.ndarray | None = None
    between_T: np.ndarray | None = None
    between_sigmas: np.ndarray | None = None


def _level_frame(up_cam: np.ndarray) -> np.ndarray:
    """T_cam_level: a frame at the camera centre whose z axis is the floor normal ``up_cam``."""
    z = np.asarray(up_cam, float) / np.linalg.norm(up_cam)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return se3(np.column_stack([x, np.cross(z, x), z]))


def planar_prior(
    T_map_cam: np.ndarray,
    up_cam: np.ndarray,
    sigma_tilt_rad: float,
    sigma_height_m: float,
    T_map_plane: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Prior of a ground robot's camera: (mean T_map_cam, 6x6 information in GTSAM's Pose3
    tangent order (rotation, translation) at the camera). ``T_map_plane`` is the plane the camera
    centre moves in (its z axis the floor normal); default: the client's map frame is the
    segment's first camera pose, so that plane is the level frame at the map origin. The mean
    keeps the pose's position along the floor and its heading and puts it back on that plane,
    level. Only height and tilt are informed."""
    T_cam_level = _level_frame(up_cam)
    T_level_cam = invert(T_cam_level)
    if T_map_plane is None:
        T_map_plane = T_cam_level
    # The keyframe's level frame, seen from the plane frame.
    T = invert(T_map_plane) @ T_map_cam @ T_cam_level
    yaw = np.arctan2(T[1, 0], T[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    level = se3(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [T[0, 3], T[1, 3], 0.0])
    T_prior = T_map_plane @ level @ T_level_cam
    free = 1e-6  # heading and position along the floor: (almost) no information
    info_level = np.diag(
        [sigma_tilt_rad**-2, sigma_tilt_rad**-2, free, free, free, sigma_height_m**-2]
    )
    # A tangent step at the camera, xi_cam, is Ad(T_level_cam) xi_cam at the level frame; with a
    # pure rotation between them the adjoint is block-diagonal.
    R = T_level_cam[:3, :3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    return T_prior, A.T @ info_level @ A


@dataclass
class BaResult:
    segment: int
    ok: bool
    kf_ids: np.ndarray
    T_map_cam: np.ndarray
    point_ids: np.ndarray
    points_map: np.ndarray
    outlier_obs: np.ndarray  # (O,) bool, observations to erase from the map
    obs_kf_ids: np.ndarray  # (O,) keyframe id of each observation
    obs_point_ids: np.ndarray  # (O,) point id of each observation
    error_before: float = 0.0
    error_after: float = 0.0
    time_ms: float = 0.0
    message: str = ""


def reprojection_chi2(
    problem: BaProblem, T_map_cam: np.ndarray, points_map: np.ndarray
) -> np.ndarray:
    """Whitened squared error of every observation (stereo or mono) for given poses and points."""
    p = problem
    T_cam_map = np.linalg.inv(T_map_cam)
    R = T_cam_map[p.obs_kf, :3, :3]
    t = T_cam_map[p.obs_kf, :3, 3]
    pc = np.einsum("nij,nj->ni", R, points_map[p.obs_pt]) + t
    z = np.maximum(pc[:, 2], 1e-6)
    u = p.fx * pc[:, 0] / z + p.cx
    v = p.fy * pc[:, 1] / z + p.cy
    ur = u - p.fx * p.baseline_m / z
    stereo = np.isfinite(p.obs_u_right)
    e2 = (u - p.obs_uv[:, 0]) ** 2 + (v - p.obs_uv[:, 1]) ** 2
    e2 = e2 + np.where(stereo, (ur - np.nan_to_num(p.obs_u_right)) ** 2, 0.0)
    inv_s2 = p.scale_factor ** (-2.0 * p.obs_octave)
    e2 = e2 * inv_s2
    return np.where(pc[:, 2] > 1e-6, e2, np.inf)


def run_local_ba(problem: BaProblem) -> BaResult:
    """Optimize the non-fixed poses and all points of ``problem``; never raises."""
    t0 = time.perf_counter()
    p = problem
    fail = BaResult(
        segment=p.segment,
        ok=False,
        kf_ids=p.kf_ids,
        T_map_cam=p.T_map_cam,
        point_ids=p.point_ids,
        points_map=p.points_map,
        outlier_obs=np.zeros(len(p.obs_kf), bool),
        obs_kf_ids=p.kf_ids[p.obs_kf],
        obs_point_ids=p.point_ids[p.obs_pt],
    )
    try:
        chi2_before = reprojection_chi2(p, p.T_map_cam, p.points_map)
        # Observations in front of their camera only: GTSAM's stereo camera throws on cheirality.
        usable = np.isfinite(chi2_before)
        # Compiled (schur_ba), but for relative-pose priors (the server's global BA): GTSAM.
        if p.between_pairs is None:
            T_new, pts_new = _optimize_compiled(p, usable)
        else:
            T_new, pts_new = _optimize_gtsam(p, usable)
        chi2_after = reprojection_chi2(p, T_new, pts_new)
        stereo = np.isfinite(p.obs_u_right)
        gate = np.where(stereo, p.chi2_stereo, p.chi2_mono)
        outlier = ~(chi2_after <= gate)
        return BaResult(
            segment=p.segment,
            ok=True,
            kf_ids=p.kf_ids,
            T_map_cam=T_new,
            point_ids=p.point_ids,
            points_map=pts_new,
            outlier_obs=outlier,
            obs_kf_ids=fail.obs_kf_ids,
            obs_point_ids=fail.obs_point_ids,
            error_before=float(np.sqrt(np.mean(np.minimum(chi2_before[usable], 100.0)))),
            error_after=float(np.sqrt(np.mean(np.minimum(chi2_after[usable], 100.0)))),
            time_ms=(time.perf_counter() - t0) * 1e3,
        )
    except (RuntimeError, ValueError, IndexError) as exc:  # GTSAM errors arrive as RuntimeError
        fail.message = f"local BA failed: {type(exc).__name__}: {exc}"
        fail.time_ms = (time.perf_counter() - t0) * 1e3
        return fail


def _optimize_compiled(p: BaProblem, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The problem's usable observations, priors and anchor solved by :mod:`.schur_ba`."""
    from . import schur_ba

    idx = np.flatnonzero(usable)
    obs_pt = p.obs_pt[idx].astype(np.int64)
    by_pt = np.argsort(obs_pt, kind="stable")
    pt_start = np.searchsorted(obs_pt[by_pt], np.arange(len(p.point_ids) + 1))
    fixed = np.asarray(p.fixed, bool)
    free = np.full(len(p.kf_ids), -1, np.int64)
    free[~fixed] = np.arange(int((~fixed).sum()))
    priors = list(_planar_priors(p))
    anchor = _scale_anchor(p)
    sigmas = p.scale_factor ** np.arange(p.n_levels)
    problem = schur_ba.SchurProblem(
        obs_kf=p.obs_kf[idx].astype(np.int64),
        obs_pt=obs_pt,
        obs_uv=np.ascontiguousarray(p.obs_uv[idx], dtype=float),
        obs_u_right=np.ascontiguousarray(p.obs_u_right[idx], dtype=float),
        obs_level=np.clip(p.obs_octave[idx].astype(np.int64), 0, p.n_levels - 1),
        whiten_mono=1.0 / sigmas,
        whiten_stereo=np.array([_stereo_whitening(p, s) for s in sigmas]),
        huber=np.array([p.huber_mono, p.huber_stereo], float),
        K=np.array([[p.fx, 0.0, p.cx], [0.0, p.fy, p.cy], [0.0, 0.0, 1.0]]),
        bf=p.fx * p.baseline_m,
        free=free,
        pt_start=pt_start,
        by_pt=by_pt,
        prior_kf=np.array([k for k, _, _ in priors], np.int64),
        prior_T_map_cam=np.array([T for _, T, _ in priors], float).reshape(-1, 4, 4),
        prior_info=np.array([info for _, _, info in priors], float).reshape(-1, 6, 6),
        anchor=np.array(anchor if anchor is not None else (-1, -1, 0.0, 1.0), float),
    )
    rules = schur_ba.LmRules(max_iterations=p.iterations, relative_tol=1e-5, absolute_tol=1e-5)
    T_new, pts_new, _ = schur_ba.solve(problem, p.T_map_cam, p.points_map, rules)
    return T_new, pts_new


def _stereo_whitening(p: BaProblem, sigma_px: float) -> np.ndarray:
    """W (3x3, upper triangular) with W^T W = the information of a (u, v, u_right) residual
    at a level of ``sigma_px``: isotropic, or with the disparity's own sigma (_noise_models)."""
    if p.disparity_sigma_px is None:
        return np.eye(3) / sigma_px
    cov = sigma_px**2 * np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 1.0]])
    cov[2, 2] += p.disparity_sigma_px**2
    return np.linalg.cholesky(np.linalg.inv(cov)).T


def _optimize_gtsam(p: BaProblem, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    _add_keyframes(graph, values, p)
    _add_points(graph, values, p, usable)
    return _optimize(graph, values, p)


def _planar_priors(p: BaProblem):
    """(keyframe index, prior T_map_cam, 6x6 information) of each free keyframe of a ground
    robot (:func:`planar_prior`); none without ``planar_up_cam``."""
    if p.planar_up_cam is None:
        return
    up_cam = np.broadcast_to(np.asarray(p.planar_up_cam, float), (len(p.kf_ids), 3))
    for k in np.flatnonzero(~np.asarray(p.fixed, bool)):
        plane = None if p.planar_T_map_plane is None else p.planar_T_map_plane[k]
        T_prior, info = planar_prior(p.T_map_cam[k], up_cam[k], *p.planar_sigmas, plane)
        yield int(k), T_prior, info


def _scale_anchor(p: BaProblem) -> tuple[int, int, float, float] | None:
    """(fixed keyframe, free keyframe, their distance, its sigma) of a monocular map's scale
    anchor (the distance held at its current value), or None."""
    if p.scale_anchor is None:
        return None
    f, k = (int(i) for i in p.scale_anchor)
    dist = float(np.linalg.norm(p.T_map_cam[k][:3, 3] - p.T_map_cam[f][:3, 3]))
    return f, k, dist, 1e-4 * dist


def _add_keyframes(graph, values, p: BaProblem) -> None:
    """Keyframe poses X(k) and their priors: stiff ones on the fixed keyframes, a ground robot's
    planar priors on the others, a monocular map's scale anchor, relative-pose priors."""
    import gtsam
    from gtsam.symbol_shorthand import X

    # Fixed keyframes: a very stiff prior. A NonlinearEquality linearizes to a constrained noise
    # model that Cholesky reports as indeterminant; LM then recovers only by raising lambda
    # again and again, several times slower (docs/tuning.md).
    fixed_noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for k, T in enumerate(p.T_map_cam):
        pose = gtsam.Pose3(T)
        values.insert(X(k), pose)
        if p.fixed[k]:
            graph.add(gtsam.PriorFactorPose3(X(k), pose, fixed_noise))
    for k, T_prior, info in _planar_priors(p):
        model = gtsam.noiseModel.Gaussian.Information(info)
        graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T_prior), model))
    anchor = _scale_anchor(p)
    if anchor is not None:
        f, k, dist, sigma = anchor
        noise = gtsam.noiseModel.Isotropic.Sigma(1, sigma)
        graph.add(gtsam.RangeFactorPose3(X(f), X(k), dist, noise))
    if p.between_pairs is not None:
        for (i, j), T_i_j, (rot, trans) in zip(p.between_pairs, p.between_T, p.between_sigmas):
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([rot] * 3 + [trans] * 3, float))
            graph.add(gtsam.BetweenFactorPose3(X(int(i)), X(int(j)), gtsam.Pose3(T_i_j), noise))


def _noise_models(p: BaProblem) -> tuple[list, list]:
    """Huber-robust noise of a (mono, stereo) observation at each pyramid level."""
    import gtsam

    sigmas = p.scale_factor ** np.arange(p.n_levels)
    huber_m = gtsam.noiseModel.mEstimator.Huber.Create(p.huber_mono)
    huber_s = gtsam.noiseModel.mEstimator.Huber.Create(p.huber_stereo)
    noise_mono = [
        gtsam.noiseModel.Robust.Create(huber_m, gtsam.noiseModel.Isotropic.Sigma(2, s))
        for s in sigmas
    ]
    if p.disparity_sigma_px is None:
        stereo_models = [gtsam.noiseModel.Isotropic.Sigma(3, s) for s in sigmas]
    else:
        corr = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # (u, u_right, v)
        d2 = np.diag([0.0, p.disparity_sigma_px**2, 0.0])
        stereo_models = [gtsam.noiseModel.Gaussian.Covariance(s**2 * corr + d2) for s in sigmas]
    noise_stereo = [gtsam.noiseModel.Robust.Create(huber_s, m) for m in stereo_models]
    return noise_mono, noise_stereo


def _add_points(graph, values, p: BaProblem, usable: np.ndarray) -> None:
    """Points L(j) and a stereo or projection factor for each ``usable`` observation."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    K_mono = gtsam.Cal3_S2(p.fx, p.fy, 0.0, p.cx, p.cy)
    K_stereo = gtsam.Cal3_S2Stereo(p.fx, p.fy, 0.0, p.cx, p.cy, p.baseline_m)
    noise_mono, noise_stereo = _noise_models(p)
    for j, xyz in enumerate(p.points_map):
        values.insert(L(j), np.asarray(xyz, dtype=float))
    stereo = np.isfinite(p.obs_u_right)
    octave = np.clip(p.obs_octave.astype(int), 0, p.n_levels - 1)
    for o in np.flatnonzero(usable):
        k, j = int(p.obs_kf[o]), int(p.obs_pt[o])
        u, v = float(p.obs_uv[o, 0]), float(p.obs_uv[o, 1])
        if stereo[o]:
            meas = gtsam.StereoPoint2(u, float(p.obs_u_right[o]), v)
            graph.add(
                gtsam.GenericStereoFactor3D(meas, noise_stereo[octave[o]], X(k), L(j), K_stereo)
            )
        else:
            graph.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    np.array([u, v]), noise_mono[octave[o]], X(k), L(j), K_mono
                )
            )


def _optimize(graph, values, p: BaProblem) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the graph: (optimized poses (K, 4, 4), points (P, 3))."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(p.iterations)
    # Points first: eliminating them leaves the small reduced camera system (Schur complement).
    ordering = gtsam.Ordering()
    for j in range(len(p.point_ids)):
        ordering.push_back(L(j))
    for k in range(len(p.kf_ids)):
        ordering.push_back(X(k))
    params.setOrdering(ordering)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    T_new = np.array([result.atPose3(X(k)).matrix() for k in range(len(p.kf_ids))])
    pts_new = np.array([result.atPoint3(L(j)) for j in range(len(p.point_ids))]).reshape(-1, 3)
    return T_new, pts_new


class BaWorker:
    """A child process running :func:`run_local_ba` on problems sent over its stdin."""

    def __init__(self):
        env = dict(os.environ)
        # The child must import this package the way the parent did (catkin devel space,
        # PYTHONPATH=src).
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        self._proc = subprocess.Popen(
            [sys.executable, "-c", "from coop_slam.optim.bundle import serve; serve()"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self._ready = False  # the child said it has its kernels loaded (serve's first message)
        self._pipe = threading.Lock()  # one reader of the child's stdout at a time

    def lower_priority(self, niceness: int) -> None:
        """Run the child ``niceness`` steps nicer than this process (Linux nice, capped at 19):
        where both want a core, the scheduler then gives it to tracking, and the BA takes the
        time tracking leaves (issue #50). Linux keeps a nice value per thread: every thread the
        child has (a prestarted one has its libraries' already) is set; later ones inherit it."""
        if niceness <= 0:
            return
        try:
            target = min(os.getpriority(os.PRIO_PROCESS, 0) + int(niceness), 19)
            pid = self._proc.pid
            tasks = os.listdir(f"/proc/{pid}/task") if os.path.isdir("/proc") else [pid]
            for tid in tasks:
                os.setpriority(os.PRIO_PROCESS, int(tid), target)
        except (AttributeError, OSError) as exc:  # not Linux, no permission, or the child gone
            log.warning("local BA process kept its priority (vo.ba.worker_nice): %s", exc)

    def wait_ready(self, timeout_s: float | None = None) -> bool:
        """Wait until the child has its compiled kernels loaded (its start-up takes most of a
        core for a second or two); False if that did not happen within ``timeout_s``. Raises
        OSError / EOFError if the child died."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        if not self._pipe.acquire(timeout=-1 if timeout_s is None else max(timeout_s, 0.0)):
            return False
        try:
            if not self._ready:
                if deadline is not None:
                    left = max(deadline - time.monotonic(), 0.0)
                    readable, _, _ = select.select([self._proc.stdout], [], [], left)
                    if not readable:
                        return False
                greeting = pickle.load(self._proc.stdout)
                if greeting != _READY:
                    raise OSError(f"local BA process: unexpected first message {greeting!r}")
                self._ready = True
            return True
        finally:
            self._pipe.release()

    def run(self, problem: BaProblem) -> BaResult:
        """Solve one problem in the child; raises OSError / EOFError if the child died."""
        self.wait_ready()
        with self._pipe:
            pickle.dump(problem, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
            return pickle.load(self._proc.stdout)

    def close(self) -> None:
        try:
            self._proc.stdin.close()
            self._proc.wait(timeout=10.0)
        except (OSError, subprocess.TimeoutExpired):
            self._proc.kill()
            self._proc.wait()


_READY = "ready"  # the worker's first message: its kernels are loaded

# A worker started ahead of the odometry that will use it (:func:`prestart_worker`).
_PRESTARTED: list = []
_PRESTARTED_LOCK = threading.Lock()


def prestart_worker(wait_s: float = 30.0) -> None:
    """Start the BA worker process now (a node before its camera's first frame) and wait up to
    ``wait_s`` for it to be ready: the child's imports and kernels take most of a core for a
    second or two, which would otherwise fall on the first frames tracked."""
    with _PRESTARTED_LOCK:
        if not _PRESTARTED:
            _PRESTARTED.append(BaWorker())
        worker = _PRESTARTED[0]
    try:
        if not worker.wait_ready(wait_s):
            log.warning("local BA process not ready after %.0f s: frames may wait for it", wait_s)
    except (OSError, EOFError, pickle.UnpicklingError) as exc:
        log.warning("local BA process failed to start (%s): local mapping starts another", exc)
        with _PRESTARTED_LOCK:
            if worker in _PRESTARTED:
                _PRESTARTED.remove(worker)
        worker.close()


@atexit.register
def _close_prestarted() -> None:
    """A prestarted worker no odometry took (no frame came) ends with its node."""
    with _PRESTARTED_LOCK:
        while _PRESTARTED:
            _PRESTARTED.pop().close()


def take_worker() -> BaWorker:
    """The prestarted worker if there is one, else a new one; raises OSError if none starts."""
    with _PRESTARTED_LOCK:
        if _PRESTARTED:
            return _PRESTARTED.pop()
    return BaWorker()


def serve() -> None:
    """Worker main loop: unpickle BaProblem from stdin, pickle BaResult to stdout, until EOF."""
    # Results go to a private copy of stdout; anything a library prints goes to stderr instead.
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    inp = sys.stdin.buffer
    from . import schur_ba

    schur_ba.warm_up()  # the compiled kernels, before the first problem arrives
    pickle.dump(_READY, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.flush()

    while True:
        try:
            problem = pickle.load(inp)
        except EOFError:
            return
        pickle.dump(run_local_ba(problem), out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()
