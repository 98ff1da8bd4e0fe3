"""Command-line source of one ground-truth sequence for the check tools (scenario or dataset)."""

from __future__ import annotations

import argparse

from ..datasets.base import Sequence
from ..playback import load_run_source


def add_sequence_arguments(parser: argparse.ArgumentParser, dataset_help: str) -> None:
    """``--scenario`` (robot 1 of a synthetic world) or ``--dataset DIR``, and ``--camera``."""
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", help="synthetic scenario (robot 1)")
    src.add_argument("--dataset", help=dataset_help)
    parser.add_argument("--camera", help="camera.yaml for a dataset folder without one")


def load_sequence(args: argparse.Namespace) -> Sequence:
    """The sequence the arguments name (raises the loaders' CoopSlamError when it cannot)."""
    return load_run_source(vars(args)).streams[0].sequence
