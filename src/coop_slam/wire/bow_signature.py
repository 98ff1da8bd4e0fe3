"""A keyframe's place signature as it travels in low-bandwidth mode (``uplink.mode: pull``): its
BoW vector in about two bytes a word or less instead of the keyframe's 35-40 kB.

Word ids go as increasing gaps, each a little-endian base-128 varint (LEB128: one byte for gaps
below 128, which most are); with them either the number of the keyframe's features on each word,
which the server weighs with its vocabulary's IDF as the client did (exact; mostly ones, which the
message's packing all but removes), or weights as uint8 fractions of the largest weight (a
client's relocalization request, a vector counts do not give, signatures recorded before counts).
The server scores signatures with the L1 score of :mod:`.vocabulary`; quantising the weights
moves a score by well under 1 %.
"""

from __future__ import annotations

import numpy as np

from ..bow.vocabulary import BowVector
from ..errors import CoopSlamError
from .varint import VarintError, decode_varints, encode_varints

_MAX_VARINT_BYTES = 5  # word ids are int32


class SignatureError(CoopSlamError):
    """A place signature is malformed (gaps, weights or scale do not fit together)."""


def encode_word_ids(bow: BowVector) -> bytes:
    """A BoW vector's (increasing) word ids as varint gaps from -1."""
    words = np.asarray(bow.words, np.int64)
    return encode_varints(np.diff(np.concatenate([[-1], words]))) if len(words) else b""


def encode_signature(bow: BowVector) -> tuple[bytes, bytes, float]:
    """(word-id gaps as varints, uint8 weights, the largest weight) of an L1-normalised BoW
    vector."""
    weights = np.asarray(bow.weights, float)
    if len(weights) == 0:
        return b"", b"", 0.0
    scale = float(weights.max())
    q = np.clip(np.rint(weights / scale * 255.0), 1, 255).astype(np.uint8)
    return encode_word_ids(bow), q.tobytes(), scale


def word_counts(bow: BowVector, word_idf: np.ndarray) -> np.ndarray | None:
    """The number of features on each word of ``bow`` (L1-normalised TF-IDF, as
    :meth:`Vocabulary.transform` makes it; ``word_idf`` the vocabulary's ``word_weights``), or
    None when ``bow`` is not such a vector (or a word holds more than 255 features): then its
    weights travel."""
    words = np.asarray(bow.words, np.int64)
    if len(words) == 0 or words.max() >= len(word_idf) or np.any(word_idf[words] <= 0):
        return None
    ratio = np.asarray(bow.weights, float) / word_idf[words]
    ratio /= ratio.min()
    # The least-seen word holds n features: one in a keyframe's hundreds of words, almost always.
    for n in range(1, 256):
        counts = np.rint(ratio * n)
        if counts.max() > 255:
            return None
        if np.allclose(counts_to_weights(words, counts, word_idf), bow.weights, rtol=1e-9, atol=0):
            return counts.astype(np.uint8)
    return None


def counts_to_weights(words: np.ndarray, counts: np.ndarray, word_idf: np.ndarray) -> np.ndarray:
    """The L1-normalised TF-IDF weights of ``counts`` features on ``words``."""
    w = np.asarray(counts, float) * word_idf[np.asarray(words, np.int64)]
    total = w.sum()
    return w / total if total > 0 else w


def decode_counted_signature(gaps: bytes, counts: bytes, word_idf: np.ndarray) -> BowVector:
    """The BoW vector of word-id gaps and per-word feature counts (see :func:`word_counts`);
    SignatureError if they do not fit this vocabulary."""
    n = np.frombuffer(bytes(counts), np.uint8)
    words = _words(gaps, len(n), "counts")
    if len(words) and words[-1] >= len(word_idf):
        raise SignatureError(
            f"signature word id {int(words[-1])} beyond the vocabulary's {len(word_idf)} words: "
            "client and server must share one vocabulary"
        )
    if np.any(n == 0) or np.any(word_idf[words] <= 0):
        raise SignatureError("signature counts no feature on a word, or one on a stop word")
    return BowVector(words.astype(np.int32), counts_to_weights(words, n, word_idf))


def _words(gaps: bytes, n: int, values: str = "weights") -> np.ndarray:
    """The word ids of varint gaps, ``n`` of them (as many as the signature's ``values``; int64);
    SignatureError if they are not."""
    try:
        gap = decode_varints(gaps, _MAX_VARINT_BYTES)
    except VarintError as exc:
        raise SignatureError(f"signature word ids: {exc}") from None
    if len(gap) != n:
        raise SignatureError(f"signature lists {len(gap)} words but {n} {values}")
    if (gap <= 0).any():
        raise SignatureError("signature word ids must increase")
    words = np.cumsum(gap) - 1
    if len(words) and words[-1] > np.iinfo(np.int32).max:
        raise SignatureError("signature word id beyond int32")
    return words


def decode_signature(gaps: bytes, weights: bytes, scale: float) -> BowVector:
    """The BoW vector (L1-normalised again) of an encoded signature; SignatureError if the parts
    do not fit."""
    q = np.frombuffer(bytes(weights), np.uint8)
    if not np.isfinite(scale) or scale < 0 or (len(q) and scale == 0):
        raise SignatureError(f"signature weight scale {scale!r} must be finite and > 0")
    words = _words(gaps, len(q))
    w = q.astype(float) / 255.0 * scale
    total = w.sum()
    return BowVector(words.astype(np.int32), w / total if total > 0 else w)
