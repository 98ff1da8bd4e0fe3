"""Bag of binary words: the shared ORB vocabulary and the team keyframe database."""

from .database import (
    ConsistencyChecker,
    ConsistencyConfig,
    DatabaseConfig,
    DatabaseError,
    KeyframeDatabase,
    LoopCandidate,
)
from .vocabulary import (
    BowVector,
    FeatureVector,
    Vocabulary,
    VocabularyConfig,
    VocabularyError,
    bench_transform,
    l1_score,
    train,
)

__all__ = [
    "BowVector",
    "ConsistencyChecker",
    "ConsistencyConfig",
    "DatabaseConfig",
    "DatabaseError",
    "FeatureVector",
    "KeyframeDatabase",
    "LoopCandidate",
    "Vocabulary",
    "VocabularyConfig",
    "VocabularyError",
    "bench_transform",
    "l1_score",
    "train",
]
