"""``scripts/check_intrinsics``: which colour focal length fits a sequence's ground-truth motion.

Prints the truncated Sampson error of ORB matches under the true motion for a range of focal
lengths around the camera model's, the best one, and which client settings apply when it
differs (see :mod:`coop_slam.vo.intrinsics_check`).
"""

from __future__ import annotations

import argparse
import sys
import time

import cv2
import numpy as np

from ..errors import CoopSlamError
from ..vo.intrinsics_check import check_focal, match_pairs
from .progress import throttled
from .sequence_args import add_sequence_arguments, load_sequence

# A focal length this far off the model's is worth acting on (the check itself is ~1 % precise).
_ACT_RATIO = 0.03


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="scripts/check_intrinsics", description=__doc__.split("\n\n")[0]
    )
    add_sequence_arguments(p, "TUM RGB-D or KITTI odometry folder with ground truth")
    p.add_argument("--gap", type=int, default=8, help="frames between the two frames of a pair")
    p.add_argument("--pairs", type=int, default=60, help="frame pairs used")
    p.add_argument(
        "--min-rotation-deg", type=float, default=2.0, help="least true rotation within a pair"
    )
    args = p.parse_args(argv)
    t0 = time.monotonic()
    progress = throttled(
        lambda done, total: print(
            f"[check_intrinsics] matching {done}/{total} frame pairs", flush=True
        )
    )

    try:
        seq = load_sequence(args)

        def load_gray(i: int) -> np.ndarray:
            img = seq.load_color(seq.frames[i])
            return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)

        pairs = match_pairs(
            load_gray,
            seq.frame_poses(),
            args.gap,
            args.min_rotation_deg,
            args.pairs,
            progress=progress,
        )
        cam = seq.camera
        res = check_focal(pairs, cam.fx, cam.fy, cam.cx, cam.cy)
    except CoopSlamError as exc:
        print(f"[check_intrinsics] ERROR: {exc}", file=sys.stderr)
        return 2
    print(f"{'fx [px]':>8} {'Sampson [px]':>13}")
    for f, e in zip(res.focal_px[::4], res.error_px[::4]):
        print(f"{f:8.1f} {e:13.3f}")
    print(
        f"[check_intrinsics] {seq.name}: {res.pairs} pairs, {res.matches} matches, "
        f"{time.monotonic() - t0:.0f} s"
    )
    print(
        f"[check_intrinsics] camera model fx {res.model_focal_px:.1f} px: "
        f"{res.model_error_px:.3f} px; best fx {res.best_focal_px:.1f} px: "
        f"{res.best_error_px:.3f} px (x{res.ratio:.3f})"
    )
    if abs(res.ratio - 1.0) > _ACT_RATIO:
        print(
            "[check_intrinsics] the colour images do not fit the model's focal length: the "
            "odometry's rotations will be off by about that ratio. A model that is the depth "
            "camera's (depth not registered to colour) can be given to the client as both cameras "
            "(vo.color_fx/fy/cx/cy and vo.depth_fx/fy/cx/cy in config/client.yaml); that needs the "
            "depth-to-colour offset too (vo.depth_in_color_m): compare ATE with and without"
        )
    else:
        print("[check_intrinsics] the model's focal length fits the colour images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
