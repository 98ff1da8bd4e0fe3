"""Accuracy metrics against ground truth, computed with evo (ATE/RPE) — never re-implemented here.

Trajectories are (stamps_s (N,), poses_se3 (N, 4, 4)) pairs. Estimated and ground-truth poses are
associated by timestamp; the alignment is SE(3) (no scale) unless asked otherwise (Sim(3), for a
monocular map without metric scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import CoopSlamError
from ..geometry import invert, rotation_angle_deg, transform_error
from ..timestamps import associate


class EvaluationError(CoopSlamError):
    """Trajectories that cannot be evaluated (too few associated poses, NaN, ...)."""


@dataclass
class AteResult:
    rmse_m: float
    mean_m: float
    max_m: float
    count: int  # associated poses
    # alignment applied to the estimate: p_gt = scale * R p_est + t, with (R, t) = T_gt_est
    T_gt_est: np.ndarray
    scale: float = 1.0  # ground truth's lengths per estimated length (1 unless correct_scale)
    # the associated estimated poses' stamps and their position errors after the alignment [m]
    stamps_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    errors_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # team_ate: the robot of each error, and its keyframes' stamps on its own timeline
    robot_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    robot_stamps_s: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def robot_rmse(self) -> dict[int, float]:
        """team_ate: each robot's keyframes' RMSE under the team's one alignment."""
        return {
            int(r): float(np.sqrt(np.mean(self.errors_m[self.robot_ids == r] ** 2)))
            for r in np.unique(self.robot_ids)
        }


def _traj(poses, stamps):
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(
        poses_se3=[np.asarray(p, float) for p in poses], timestamps=np.asarray(stamps, float)
    )


def ate(
    stamps_est,
    poses_est,
    stamps_gt,
    poses_gt,
    max_dt_s: float = 0.02,
    align: bool = True,
    correct_scale: bool = False,
) -> AteResult:
    """Absolute trajectory error (translation RMSE) after SE(3) alignment, with evo; Sim(3) with
    ``correct_scale`` (the error then in ground truth's metres, ``scale`` the estimate's metric
    scale)."""
    from evo.core import metrics

    poses_est = np.asarray(poses_est, float).reshape(-1, 4, 4)  # (an empty list: no poses)
    poses_gt = np.asarray(poses_gt, float).reshape(-1, 4, 4)
    i_est, i_gt = associate(stamps_est, stamps_gt, max_dt_s)
    keep = np.all(np.isfinite(poses_est[i_est]), axis=(1, 2)) & np.all(
        np.isfinite(poses_gt[i_gt]), axis=(1, 2)
    )
    i_est, i_gt = i_est[keep], i_gt[keep]
    if len(i_est) < 3:
        raise EvaluationError(
            f"only {len(i_est)} estimated poses match ground truth in time; "
            "need at least 3 for ATE"
        )
    stamps = np.asarray(stamps_est, float)[i_est]
    ref = _traj(poses_gt[i_gt], stamps)
    est = _traj(poses_est[i_est], stamps)
    T = np.eye(4)
    scale = 1.0
    if align:
        from evo.core.geometry import GeometryException

        try:
            r, t, scale = est.align(ref, correct_scale=correct_scale)
            T[:3, :3], T[:3, 3] = r, t
        except GeometryException:
            if correct_scale:
                # Positions on a line (a robot driving straight): the rotation about the line is
                # undetermined, but any one of them fits the positions alike, and the scale and
                # error are the line's.
                T, scale = _sim3_on_a_line(est.positions_xyz, ref.positions_xyz)
                est.scale(scale)
                est.transform(T)
            else:
                # Positions on a line (or a point) leave Umeyama's rotation undetermined: align
                # the first poses instead, which uses their orientations too.
                T = est.align_origin(ref)
            if T is None or not np.all(np.isfinite(T)):
                raise EvaluationError("cannot align the trajectories") from None
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    st = ape.get_all_statistics()
    return AteResult(
        rmse_m=float(st["rmse"]),
        mean_m=float(st["mean"]),
        max_m=float(st["max"]),
        count=len(i_est),
        T_gt_est=T,
        scale=float(scale),
        stamps_s=stamps,
        errors_m=np.asarray(ape.error, float),
    )


def _sim3_on_a_line(points_est: np.ndarray, points_gt: np.ndarray) -> tuple[np.ndarray, float]:
    """(T_gt_est, scale) of the least-squares similarity of positions on a line; raises
    EvaluationError when the estimate does not move (no scale to take)."""
    from ..registration.umeyama import umeyama_batch

    if min(np.ptp(points_est, axis=0).max(), np.ptp(points_gt, axis=0).max()) <= 1e-9:
        raise EvaluationError("cannot align the trajectories with scale: a camera stands still")
    T, scale = umeyama_batch(points_est[None], points_gt[None], with_scale=True)
    return T[0], float(scale[0])


def team_ate(
    est: dict[int, tuple], gt: dict[int, tuple], max_dt_s: float = 0.02, correct_scale=False
) -> AteResult:
    """ATE over all robots' poses together (all in one estimated frame, e.g. ``world``) with a
    single SE(3) alignment for the whole team (Sim(3) with ``correct_scale``); each error's robot
    in ``robot_ids``."""
    stamps, poses_e, poses_g, spans = [], [], [], []
    offset = 0.0
    for rid in sorted(est):
        if rid not in gt:
            continue
        se, pe = est[rid]
        sg, pg = gt[rid]
        i_est, i_gt = associate(se, sg, max_dt_s)
        # Robots may share stamps: shift each robot onto its own stretch of a synthetic timeline.
        stamps.append(np.asarray(se, float)[i_est] - float(np.min(se)) + offset)
        spans.append((rid, offset - 1.0, float(np.min(se)) - offset))
        offset = float(stamps[-1].max()) + 1000.0 if len(stamps[-1]) else offset
        poses_e.append(np.asarray(pe, float)[i_est])
        poses_g.append(np.asarray(pg, float)[i_gt])
    if not stamps:
        raise EvaluationError("no robot has both an estimate and ground truth")
    s = np.concatenate(stamps)
    res = ate(
        s,
        np.concatenate(poses_e),
        s,
        np.concatenate(poses_g),
        max_dt_s=1e-6,
        correct_scale=correct_scale,
    )
    # Each robot's stretch of the synthetic timeline starts after the one before it.
    starts = np.array([start for _, start, _ in spans])
    which = np.searchsorted(starts, res.stamps_s, side="right") - 1
    res.robot_ids = np.array([spans[k][0] for k in which], int)
    res.robot_stamps_s = res.stamps_s + np.array([spans[k][2] for k in which])
    return res


def rpe_rmse(
    stamps_est, poses_est, stamps_gt, poses_gt, delta: int = 1, max_dt_s: float = 0.02
) -> float:
    """Relative pose error (translation RMSE over ``delta`` consecutive poses), with evo."""
    from evo.core import metrics

    i_est, i_gt = associate(stamps_est, stamps_gt, max_dt_s)
    if len(i_est) <= delta:
        raise EvaluationError(f"need more than {delta} associated poses for RPE")
    stamps = np.asarray(stamps_est, float)[i_est]
    ref = _traj(np.asarray(poses_gt)[i_gt], stamps)
    est = _traj(np.asarray(poses_est)[i_est], stamps)
    rpe = metrics.RPE(
        metrics.PoseRelation.translation_part,
        delta=delta,
        delta_unit=metrics.Unit.frames,
        all_pairs=False,
    )
    rpe.process_data((ref, est))
    return float(rpe.get_statistic(metrics.StatisticsType.rmse))


def merge_error(
    T_mapA_mapB_est: np.ndarray, T_world_mapA_gt: np.ndarray, T_world_mapB_gt: np.ndarray
) -> tuple[float, float]:
    """(translation [m], rotation [deg]) error of an estimated map-to-map transform."""
    return transform_error(T_mapA_mapB_est, invert(T_world_mapA_gt) @ T_world_mapB_gt)


def pose_at(stamps_gt, poses_gt, stamp_s: float, max_dt_s: float = 0.02) -> np.ndarray | None:
    """The ground-truth pose nearest in time to ``stamp_s``; None when none is within
    ``max_dt_s`` (or there is no ground truth)."""
    if len(stamps_gt) == 0:
        return None
    i = int(np.argmin(np.abs(np.asarray(stamps_gt) - stamp_s)))
    if abs(stamps_gt[i] - stamp_s) > max_dt_s:
        return None
    return np.asarray(poses_gt[i], float)


def relative_pose_error(
    T_camA_camB_est: np.ndarray, stamp_a: float, stamp_b: float, gt_a: tuple, gt_b: tuple
) -> tuple[float, float] | None:
    """(translation [m], rotation [deg]) error of an estimated relative pose of two cameras
    (e.g. a merge's or link's registration of two keyframes) against their true relative pose at
    their stamps; ``gt_a`` / ``gt_b`` are (stamps, T_world_cam). None without ground truth there.
    Odometry drift does not enter."""
    T_world_camA, T_world_camB = pose_at(*gt_a, stamp_a), pose_at(*gt_b, stamp_b)
    if T_world_camA is None or T_world_camB is None:
        return None
    return transform_error(T_camA_camB_est, invert(T_world_camA) @ T_world_camB)


@dataclass
class NoiseSplit:
    """Each trajectory's own RMS error of the relative motion over ``step`` frames."""

    step: int
    pairs: int  # frame pairs (i, i + step) where all trajectories have a pose
    rot_deg: dict[str, float]
    trans_m: dict[str, float]


def noise_split(trajectories: dict[str, np.ndarray], step: int) -> NoiseSplit:
    """Three-cornered hat over relative motions: three trajectories (F, 4, 4) of the same frames
    (NaN where one has no pose), with independent errors, give each one's own error from their three
    pairwise disagreements: own_a^2 = (d_ab^2 + d_ac^2 - d_bc^2) / 2. Ground truth is no exception,
    which is the point: it tells how much of an ATE is the reference's. Errors shared by two
    trajectories are credited to the third (a negative own variance is reported as 0)."""
    if len(trajectories) != 3:
        raise EvaluationError(f"noise_split needs exactly 3 trajectories, got {len(trajectories)}")
    names = list(trajectories)
    i, rel = _relative_motions(trajectories, step)
    rot2, trans2 = {}, {}
    for a, b in ((0, 1), (0, 2), (1, 2)):
        err = np.linalg.inv(rel[a]) @ rel[b]
        angles = [rotation_angle_deg(R) for R in err[:, :3, :3]]
        rot2[a, b] = float(np.mean(np.square(angles)))
        trans2[a, b] = float(np.mean(np.sum(err[:, :3, 3] ** 2, axis=1)))

    def own(var: dict, k: int) -> float:
        others = [x for x in range(3) if x != k]
        d = lambda x, y: var[min(x, y), max(x, y)]  # noqa: E731
        v = (d(k, others[0]) + d(k, others[1]) - d(*others)) / 2
        return float(np.sqrt(max(v, 0.0)))

    return NoiseSplit(
        step=step,
        pairs=len(i),
        rot_deg={n: own(rot2, k) for k, n in enumerate(names)},
        trans_m={n: own(trans2, k) for k, n in enumerate(names)},
    )


def _relative_motions(trajectories: dict[str, np.ndarray], step: int, min_pairs: int = 10):
    """Frames i where every trajectory (name -> (F, 4, 4) poses of the same frames) has a pose at
    i and i + step, and each trajectory's motion ``T_i^-1 T_(i+step)`` there."""
    poses = [np.asarray(p, float).reshape(-1, 4, 4) for p in trajectories.values()]
    if len({len(p) for p in poses}) != 1:
        raise EvaluationError(
            "needs trajectories of the same frames, got lengths "
            + ", ".join(f"{n} {len(p)}" for n, p in zip(trajectories, poses))
        )
    if step < 1:
        raise EvaluationError(f"step must be at least 1 frame, got {step}")
    finite = np.all([np.isfinite(p).all(axis=(1, 2)) for p in poses], axis=0)
    i = np.flatnonzero(finite[:-step] & finite[step:]) if len(finite) > step else np.zeros(0, int)
    if len(i) < min_pairs:
        raise EvaluationError(
            f"only {len(i)} frame pairs {step} frames apart have every pose (need {min_pairs})"
        )
    return i, [np.linalg.inv(p[i]) @ p[i + step] for p in poses]


def rotation_gain(poses_est, poses_gt, step: int, min_rms_deg: float = 0.1) -> np.ndarray:
    """Per camera axis (x, y, z), the least-squares gain g of an estimate's rotations over
    ``step`` frames against ground truth's: rotation vectors in the earlier frame's camera axes,
    est_k = g_k gt_k. 1 is right. A wrong focal length scales x and y, not z (a rotation about
    the optical axis moves pixels independently of it). NaN for an axis about which ground truth
    turns less than ``min_rms_deg`` (RMS over the pairs)."""
    _, (rel_est, rel_gt) = _relative_motions(
        {"estimate": poses_est, "ground truth": poses_gt}, step
    )
    rotvec_est_rad = Rotation.from_matrix(rel_est[:, :3, :3]).as_rotvec()
    rotvec_gt_rad = Rotation.from_matrix(rel_gt[:, :3, :3]).as_rotvec()
    power = np.sum(rotvec_gt_rad**2, axis=0)
    enough = np.degrees(np.sqrt(power / len(rotvec_gt_rad))) >= min_rms_deg
    gain = np.sum(rotvec_est_rad * rotvec_gt_rad, axis=0) / np.where(enough, power, 1.0)
    return np.where(enough, gain, np.nan)
