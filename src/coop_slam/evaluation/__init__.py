"""Judging a run against ground truth: trajectory metrics (:mod:`.metrics`, with evo), the report
of a run (:mod:`.run_report` over :mod:`.run_data`, with :mod:`.bandwidth`; :mod:`.report`) and its
pictures (:mod:`.plots`)."""

from .metrics import (
    AteResult,
    EvaluationError,
    NoiseSplit,
    ate,
    merge_error,
    noise_split,
    rotation_gain,
    rpe_rmse,
    team_ate,
)

__all__ = [
    "AteResult",
    "EvaluationError",
    "NoiseSplit",
    "ate",
    "merge_error",
    "noise_split",
    "rotation_gain",
    "rpe_rmse",
    "team_ate",
]
