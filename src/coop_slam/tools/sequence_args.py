"""Command-line source of one ground-truth sequence for the check tools (scenario or dataset),
and the ``--duration`` of a synthetic scenario that ``scripts/demo`` and ``export_bag`` take."""

from __future__ import annotations

import argparse
import math

from ..datasets.base import Sequence
from ..playback import load_run_source


def add_sequence_arguments(parser: argparse.ArgumentParser, dataset_help: str) -> None:
    """``--scenario`` (robot 1 of a synthetic world) or ``--dataset DIR``, and ``--camera``."""
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", help="synthetic scenario (robot 1)")
    src.add_argument("--dataset", help=dataset_help)
    parser.add_argument("--camera", help="camera.yaml for a dataset folder without one")


def add_duration_argument(parser: argparse.ArgumentParser) -> None:
    """``--duration S``: a synthetic scenario's first S seconds (see :func:`check_duration`)."""
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        help="synthetic world length [s] (default: the scenario's own); a shorter one is the "
        "scenario's beginning",
    )


def check_duration(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse a ``--duration`` that is not a positive length, or not for a ``--scenario``."""
    if args.duration is not None and (not args.scenario or not 0 < args.duration < math.inf):
        parser.error("--duration: a positive length in seconds, for a synthetic --scenario")


def load_sequence(args: argparse.Namespace) -> Sequence:
    """The sequence the arguments name (raises the loaders' CoopSlamError when it cannot)."""
    return load_run_source(vars(args)).streams[0].sequence
