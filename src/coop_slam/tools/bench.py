"""Benchmarks behind ``scripts/bench``: each prints ``name value unit`` lines; all go to bench.json.

Speed lives here, not in tests (tests must not depend on machine speed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Callable, Iterator

Figure = tuple[str, float, str]
REDKITCHEN = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "..", "..", "..",
                                           "shared", "data", "redkitchen_0000_0599"))


def bench_render() -> Iterator[Figure]:
    import cv2

    from ..synthetic.render import bench_render as run

    cv2.setNumThreads(1)
    yield ("render_fps_640x480_one_core", run(), "frames/s")


REGISTRY: dict[str, Callable[[], Iterator[Figure]]] = {
    "render": bench_render,
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--only", choices=sorted(REGISTRY), help="run one benchmark")
    p.add_argument("--out", default="bench.json", help="where to write the figures (JSON)")
    args = p.parse_args(argv)
    names = [args.only] if args.only else list(REGISTRY)
    figures = {}
    for name in names:
        t0 = time.monotonic()
        try:
            for fig, value, unit in REGISTRY[name]():
                figures[fig] = {"value": value, "unit": unit}
                print(f"{fig} {value:.4g} {unit}", flush=True)
        except ImportError as exc:
            print(f"# {name}: skipped ({exc})", flush=True)
        print(f"# {name}: {time.monotonic() - t0:.1f} s", file=sys.stderr, flush=True)
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump(figures, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
