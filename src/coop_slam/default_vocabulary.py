"""The default vocabulary: trained by the project itself on its own synthetic world (never
downloaded), cached per user; and the training images a synthetic world gives."""

from __future__ import annotations

import os

from .bow.training import ExtractionConfig, train_from_sequences
from .bow.vocabulary import DEFAULT_K, DEFAULT_LEVELS, ProgressCallback, VocabularyError
from .datasets import Sequence

# Built by the project itself from its own synthetic world (never downloaded). The training world
# uses a seed no test or demo scenario uses, so the vocabulary has not seen the places it must
# recognise.
DEFAULT_VOCABULARY_VERSION = 1
DEFAULT_TRAINING_WORLD = {"scenario": "team", "seed": 1000, "robots": 4}
DEFAULT_TRAINING_EVERY = 6  # every 6th frame at 15 Hz: ~2.5 training images per second of travel


def default_vocabulary_path() -> str:
    """Where the default vocabulary is cached (``$COOP_SLAM_CACHE`` or ``~/.cache/coop_slam``)."""
    root = os.environ.get("COOP_SLAM_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "coop_slam"
    )
    return os.path.join(
        root,
        "vocabulary",
        f"default-v{DEFAULT_VOCABULARY_VERSION}-k{DEFAULT_K}-L{DEFAULT_LEVELS}.npz",
    )


def ensure_default_vocabulary(progress: ProgressCallback | None = None, world_progress=None) -> str:
    """Return the default vocabulary's path, training it first (world + ORB + k-majority tree) if
    it is not cached yet. Written atomically, so an interrupted run leaves no half file."""
    path = default_vocabulary_path()
    if os.path.isfile(path):
        return path
    from .datasets.synthetic import read_synthetic
    from .synthetic.generate import generate

    folder = generate(**DEFAULT_TRAINING_WORLD, progress=world_progress, workers=2)
    world = read_synthetic(folder)
    sequences = [world.sequences[k] for k in sorted(world.sequences)]
    tmp = f"{path}.{os.getpid()}.tmp.npz"
    train_from_sequences(
        sequences,
        extraction=ExtractionConfig(every=DEFAULT_TRAINING_EVERY),
        out=tmp,
        progress=progress,
    )
    os.replace(tmp, path)
    return path


def synthetic_sequences(folder: str) -> list[Sequence]:
    """Every robot's sequence in a synthetic world folder (via datasets.read_synthetic).

    Raises VocabularyError if this checkout has no synthetic reader.
    """
    from . import datasets

    reader = getattr(datasets, "read_synthetic", None)
    if reader is None:
        raise VocabularyError(
            "reading synthetic worlds needs coop_slam.datasets.read_synthetic, which this version "
            "does not provide; use --images on the world's image folders instead"
        )
    result = reader(folder)
    result = getattr(result, "sequences", result)  # a SyntheticWorld holds {robot_id: Sequence}
    if isinstance(result, Sequence):
        result = [result]
    elif isinstance(result, dict):
        result = [result[key] for key in sorted(result)]
    seqs = [s for s in result if isinstance(s, Sequence)]
    if not seqs:
        raise VocabularyError(f"synthetic world {folder} has no robot sequences")
    return seqs
