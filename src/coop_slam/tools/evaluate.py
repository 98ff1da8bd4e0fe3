"""``scripts/evaluate RESULTS``: re-derive a demo run's report, trajectories, plots and team map
from what it recorded (``run.json`` and ``run.bag`` in the results folder)."""

from __future__ import annotations

import os


def main(argv=None) -> int:
    """``scripts/evaluate RESULTS``: re-evaluate a demo run from its recorded bag."""
    import argparse
    import json
    import sys

    from ..errors import CoopSlamError
    from ..evaluation import EvaluationError
    from ..evaluation.run_report import evaluate_results, run_input_of
    from ..geometry import T_base_cam_of
    from ..playback import load_run_source
    from ..ros.run_recorder import read_bag_input, run_bags, run_data_from_bag
    from .framing import dense_truth_of

    p = argparse.ArgumentParser(prog="scripts/evaluate", description=main.__doc__.split(":")[1])
    p.add_argument("results", help="results folder of a demo run (holds run.json and run.bag)")
    p.add_argument(
        "--bag", help="bag to evaluate (default: RESULTS/run.bag and each host's run_robot_<k>.bag)"
    )
    args = p.parse_args(argv)
    try:
        info_path = os.path.join(args.results, "run.json")
        if not os.path.isfile(info_path):
            raise EvaluationError(
                f"{info_path} not found: is {args.results} a demo results folder?"
            )
        with open(info_path, encoding="utf-8") as fh:
            info = json.load(fh)
        bags = [args.bag] if args.bag else run_bags(args.results)
        what = info.get("bag") or info.get("scenario") or info.get("dataset")
        print(f"[evaluate] loading the ground truth ({what})", flush=True)
        if info.get("bag"):  # the run played a sensor bag: ground truth (if any) is in it
            inputs = read_bag_input(info["bag"])
        else:
            # A later session (load_map) is judged with the loaded robots too.
            options = dict(info, only_robots=None) if info.get("load_map") else info
            inputs = run_input_of(load_run_source(options), bool(info.get("keep_timing")))
        print(f"[evaluate] reading {', '.join(bags)}", flush=True)
        run = run_data_from_bag(bags, inputs.robot_ids, info.get("clock_offsets"))
        run.duration_s = inputs.end_s - inputs.start_s
        run.radio_bytes = {int(r): tuple(b) for r, b in (info.get("radio_bytes") or {}).items()}
        faults = {"faults": {"spec": info["faults"]}} if info.get("faults") else None
        _, json_path, md_path, ply = evaluate_results(
            args.results,
            run,
            inputs.gts,
            inputs.overlap,
            extra=faults,
            T_base_cam=T_base_cam_of(info.get("T_base_cam") or []),
            dense_truth=dense_truth_of(inputs, T_base_cam_of(info.get("T_base_cam") or [])),
        )
    except (CoopSlamError, OSError, ValueError) as exc:
        print(f"[evaluate] ERROR: {exc}", file=sys.stderr)
        return 2
    print(f"[evaluate] report: {json_path}\n[evaluate]         {md_path}", flush=True)
    if ply:
        print(f"[evaluate] team map: {ply}", flush=True)
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
