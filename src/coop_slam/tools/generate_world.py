"""Generate (or fetch from the cache) a synthetic multi-robot RGB-D (and stereo) world and print
its folder."""

import argparse
import os
import sys
import time

from ..errors import CoopSlamError
from ..synthetic.generate import generate
from ..synthetic.scenarios import DEFAULT_SCENARIO, SCENARIOS
from .progress import throttled


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="scripts/generate_world", description=__doc__)
    parser.add_argument("--scenario", default=DEFAULT_SCENARIO, choices=sorted(SCENARIOS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--robots", type=int, default=None, help="robot count (scenario default)")
    parser.add_argument("--duration", type=float, default=None, help="seconds (scenario default)")
    parser.add_argument(
        "--rate",
        type=float,
        default=None,
        help="frame rate [Hz] (scenario default: 15, kitchen 30)",
    )
    parser.add_argument("--no-noise", action="store_true", help="ideal images and exact depth")
    parser.add_argument(
        "--stereo-baseline",
        type=float,
        default=0.0,
        help="also render each robot's right camera this far to the right [m] (0: none)",
    )
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument(
        "--out",
        "--cache",
        dest="out",
        default=None,
        help="output folder (default: ${COOP_SLAM_CACHE:-~/.cache/coop_slam}/worlds/...)",
    )
    args = parser.parse_args(argv)
    start = time.monotonic()
    progress = throttled(
        lambda done, total: print(
            f"rendered {done}/{total} frames ({time.monotonic() - start:.0f} s)",
            file=sys.stderr,
            flush=True,
        )
    )

    try:
        folder = generate(
            args.scenario,
            seed=args.seed,
            robots=args.robots,
            duration_s=args.duration,
            rate_hz=args.rate,
            noise=not args.no_noise,
            out_dir=args.out,
            progress=progress,
            workers=args.workers,
            stereo_baseline_m=args.stereo_baseline,
        )
    except CoopSlamError as exc:
        print(f"generate_world: error: {exc}", file=sys.stderr)
        return 1
    print(f"world ready in {time.monotonic() - start:.1f} s", file=sys.stderr)
    print(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
