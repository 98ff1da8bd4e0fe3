"""Vocabulary training from image data: ORB extraction over sequences/folders, then :func:`train`.
A sequence is anything with ``frames`` and ``load_color(frame)`` (a datasets ``Sequence``).

This is the glue behind ``scripts/train_vocabulary`` and what setup code calls
(:func:`train_from_sequences`); one descriptor set per used frame is one training "image" for IDF.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from typing import Iterable, TextIO

import cv2
import numpy as np

from ..config import require
from ..descriptors import DESCRIPTOR_BYTES
from ..errors import CoopSlamError
from .vocabulary import (
    DEFAULT_K,
    DEFAULT_LEVELS,
    ProgressCallback,
    Vocabulary,
    VocabularyConfig,
    VocabularyError,
    train,
)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")


@dataclass
class ExtractionConfig:
    """ORB extraction for training (ORB-SLAM's pyramid: scale 1.2, 8 levels)."""

    features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    every: int = 5  # use every N-th frame: consecutive frames add little but time

    def validate(self) -> None:
        require(self.features >= 1, f"features must be >= 1, got {self.features}")
        require(self.scale_factor > 1.0, f"scale_factor must be > 1, got {self.scale_factor}")
        require(self.n_levels >= 1, f"n_levels must be >= 1, got {self.n_levels}")
        require(self.every >= 1, f"every must be >= 1, got {self.every}")


def make_orb(cfg: ExtractionConfig) -> cv2.ORB:
    return cv2.ORB_create(cfg.features, scaleFactor=cfg.scale_factor, nlevels=cfg.n_levels)


def orb_descriptors(image: np.ndarray, orb: cv2.ORB) -> np.ndarray:
    """(N, 32) uint8 ORB descriptors of a BGR, BGRA or grey image (any bit depth)."""
    img = np.asarray(image)
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code) if img.shape[2] in (3, 4) else img[..., 0]
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    _, desc = orb.detectAndCompute(img, None)
    if desc is None:
        return np.zeros((0, DESCRIPTOR_BYTES), dtype=np.uint8)
    return desc


def image_files(folder: str) -> list[str]:
    """Image files under ``folder`` (recursive), sorted by path."""
    if not os.path.isdir(folder):
        raise VocabularyError(f"image folder not found: {folder}")
    out = [
        os.path.join(root, name)
        for root, _, names in os.walk(folder)
        for name in names
        if name.lower().endswith(IMAGE_EXTENSIONS)
    ]
    if not out:
        raise VocabularyError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) under {folder}")
    return sorted(out)


def collect_descriptors(
    sequences: Iterable = (),
    image_paths: Iterable[str] = (),
    extraction: ExtractionConfig | None = None,
    progress: ProgressCallback | None = None,
) -> list[np.ndarray]:
    """ORB descriptors of every ``every``-th frame of each sequence and of each image list."""
    cfg = extraction or ExtractionConfig()
    cfg.validate()
    orb = make_orb(cfg)
    # Frames to read: (sequence, frame) for datasets, a path for loose images.
    jobs: list = [(seq, frame) for seq in sequences for frame in seq.frames[:: cfg.every]]
    jobs.extend(list(image_paths)[:: cfg.every])
    if not jobs:
        raise VocabularyError("no training frames: give at least one sequence or image")
    report = progress or (lambda stage, done, total: None)
    sets = []
    for i, job in enumerate(jobs):
        if isinstance(job, str):
            image = cv2.imread(job, cv2.IMREAD_UNCHANGED)
            if image is None:
                raise VocabularyError(f"cannot decode image {job}")
        else:
            image = job[0].load_color(job[1])
        sets.append(orb_descriptors(image, orb))
        report("extract ORB", i + 1, len(jobs))
    return sets


def train_from_sequences(
    sequences: Iterable = (),
    image_paths: Iterable[str] = (),
    *,
    extraction: ExtractionConfig | None = None,
    vocabulary: VocabularyConfig | None = None,
    out: str | None = None,
    progress: ProgressCallback | None = None,
) -> Vocabulary:
    """Extract ORB from the sequences/images, train a vocabulary, optionally save it to ``out``."""
    vcfg = vocabulary or VocabularyConfig()
    try:
        vcfg.validate()
    except CoopSlamError as exc:
        raise VocabularyError(str(exc)) from None
    sets = collect_descriptors(sequences, image_paths, extraction, progress)
    vocab = train(sets, vcfg.k, vcfg.levels, vcfg.seed, progress, vcfg.max_iterations)
    if out:
        vocab.save(out)
    return vocab


class ConsoleProgress:
    """Progress callback for terminals: one updating line per stage, with elapsed time.

    On a non-terminal (log file) only every 10 % step is printed, one line each.
    """

    def __init__(self, stream: TextIO | None = None):
        self.stream = stream or sys.stdout
        self.start = time.perf_counter()
        self.tty = self.stream.isatty()
        self._last: tuple[str, int] = ("", -1)

    def __call__(self, stage: str, done: int, total: int) -> None:
        text = f"{stage}: {done}/{total}  ({time.perf_counter() - self.start:.1f} s)"
        if self.tty:
            print("\r" + text, end="\n" if done >= total else "", file=self.stream, flush=True)
            return
        decile = 10 * done // max(total, 1)
        if (stage, decile) != self._last:
            self._last = (stage, decile)
            print(text, file=self.stream, flush=True)


__all__ = [
    "ConsoleProgress",
    "DEFAULT_K",
    "DEFAULT_LEVELS",
    "ExtractionConfig",
    "collect_descriptors",
    "image_files",
    "make_orb",
    "orb_descriptors",
    "train_from_sequences",
]
