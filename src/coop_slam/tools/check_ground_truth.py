"""``scripts/check_ground_truth``: how precise is a sequence's ground truth, next to the odometry?

Runs the client's odometry and a depth-only ICP odometry (OpenCV's ``rgbd.ICPOdometry``, an
estimator that shares nothing with ours but the depth images) over a sequence, and splits the
three pairwise disagreements of their relative motions into each one's own error (three-cornered
hat, :func:`coop_slam.evaluation.noise_split`). Where the ground truth's own error is as large as
the odometry's, an ATE against it measures the reference as much as the odometry. Also prints
each estimator's rotation gain per camera axis (:func:`coop_slam.evaluation.rotation_gain`):
x / y gains away from 1 with z at 1 are the mark of a focal length that does not fit the images;
the same gains in both estimators point at a reference that turns more or less than the images
show.
"""

from __future__ import annotations

import argparse
import sys
import time

import cv2
import numpy as np

from ..errors import CoopSlamError
from ..evaluation import EvaluationError, noise_split, rotation_gain
from ..evaluation.vo_run import ate_rmse, run_sequence
from ..vo.config import VoConfig
from .progress import throttled
from .sequence_args import add_sequence_arguments, load_sequence


def depth_icp_odometry(seq, progress=None) -> np.ndarray:
    """Frame-to-frame point-to-plane ICP on the depth images: ``T_first_cam`` (F, 4, 4) in the
    first frame's ground-truth pose (identity without one), NaN after a failed frame."""
    if not hasattr(cv2, "rgbd"):
        raise EvaluationError("this OpenCV has no rgbd module (opencv-contrib): no ICP odometry")
    cam = seq.camera
    odo = cv2.rgbd.ICPOdometry_create(cam.K.astype(np.float32))
    odo.setMinDepth(0.3)
    odo.setMaxDepth(4.0)
    odo.setMaxDepthDiff(0.07)
    n = len(seq)
    poses = np.full((n, 4, 4), np.nan)
    first = seq.frame_poses()[0]
    poses[0] = first if np.isfinite(first).all() else np.eye(4)
    gray = np.zeros((cam.height, cam.width), np.uint8)  # ICPOdometry reads depth only
    prev = seq.load_depth_m(seq.frames[0]).astype(np.float32)
    for i in range(1, n):
        depth = seq.load_depth_m(seq.frames[i]).astype(np.float32)
        ok, T_cur_prev = odo.compute(gray, prev, None, gray, depth, None)
        if ok and np.isfinite(poses[i - 1]).all():
            poses[i] = poses[i - 1] @ np.linalg.inv(T_cur_prev)
        prev = depth
        if progress is not None:
            progress(i + 1, n)
    return poses


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="scripts/check_ground_truth", description=__doc__.split("\n\n")[0]
    )
    add_sequence_arguments(p, "TUM RGB-D folder with ground truth")
    p.add_argument(
        "--steps", default="1,5,15,30", help="frame gaps of the relative motions compared"
    )
    args = p.parse_args(argv)
    t0 = time.monotonic()
    try:
        steps = [int(s) for s in args.steps.split(",")]
    except ValueError:
        print(
            f"[check_ground_truth] ERROR: --steps must be integers, got {args.steps}",
            file=sys.stderr,
        )
        return 2
    try:
        seq = load_sequence(args)
        if seq.camera.sensor != "rgbd":
            raise EvaluationError(f"{seq.name} is {seq.camera.sensor}: the ICP needs depth images")
        gt = seq.frame_poses()
        if not np.isfinite(gt).all(axis=(1, 2)).any():
            raise EvaluationError(f"{seq.name} has no ground truth")
        say = lambda what: throttled(  # noqa: E731
            lambda done, total, *_: print(
                f"[check_ground_truth] {what} {done}/{total} frames", flush=True
            )
        )
        vo_report = say("odometry")
        run = run_sequence(seq, VoConfig(threaded=False), lambda i, n, _r: vo_report(i + 1, n))
        icp = depth_icp_odometry(seq, say("depth ICP"))
        trajectories = {"odometry": run.poses_se3, "depth ICP": icp, "ground truth": gt}
        splits = [noise_split(trajectories, s) for s in steps]
        gains = {
            n: [rotation_gain(trajectories[n], gt, s) for s in steps]
            for n in ("odometry", "depth ICP")
        }
    except CoopSlamError as exc:
        print(f"[check_ground_truth] ERROR: {exc}", file=sys.stderr)
        return 2
    print(f"[check_ground_truth] {seq.name}: {len(seq)} frames, {time.monotonic() - t0:.0f} s")
    for name in ("odometry", "depth ICP"):
        print(
            f"  ATE of {name} against ground truth: "
            f"{100 * ate_rmse(seq.stamps_s, trajectories[name], gt):.2f} cm"
        )
    print("  own RMS error of the relative motion over N frames (three-cornered hat):")
    print(f"  {'N':>4} {'pairs':>6} " + " ".join(f"{n:>22}" for n in trajectories))
    for sp in splits:
        cells = [f"{sp.rot_deg[n]:8.3f} deg {100 * sp.trans_m[n]:6.2f} cm" for n in trajectories]
        print(f"  {sp.step:>4} {sp.pairs:>6} " + " ".join(f"{c:>22}" for c in cells))
    print(
        "  rotation gain against ground truth per camera axis, x / y / z (1 = right; a wrong focal"
        " length scales x and y only):"
    )
    print(f"  {'N':>4} " + " ".join(f"{n:>20}" for n in gains))
    for k, step in enumerate(steps):
        cells = [" / ".join(f"{g:.2f}" for g in gains[n][k]) for n in gains]
        print(f"  {step:>4} " + " ".join(f"{c:>20}" for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
