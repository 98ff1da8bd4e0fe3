"""A keyframe's place signature as it travels in low-bandwidth mode (``uplink.mode: pull``): its
BoW vector in about two bytes a word instead of the keyframe's 50-60 kB.

Word ids go as increasing gaps, each a little-endian base-128 varint (LEB128: one byte for gaps
below 128, which most are); weights as uint8 fractions of the largest weight. The server scores
signatures with the L1 score of :mod:`.vocabulary`; quantising the weights moves a score by well
under 1 %.
"""

from __future__ import annotations

import numpy as np

from ..errors import CoopSlamError
from ..varint import VarintError, decode_varints, encode_varints
from .vocabulary import BowVector

_MAX_VARINT_BYTES = 5  # word ids are int32


class SignatureError(CoopSlamError):
    """A place signature is malformed (gaps, weights or scale do not fit together)."""


def encode_signature(bow: BowVector) -> tuple[bytes, bytes, float]:
    """(word-id gaps as varints, uint8 weights, the largest weight) of an L1-normalised BoW
    vector."""
    words = np.asarray(bow.words, np.int64)
    weights = np.asarray(bow.weights, float)
    if len(words) == 0:
        return b"", b"", 0.0
    gaps = np.diff(np.concatenate([[-1], words]))
    scale = float(weights.max())
    q = np.clip(np.rint(weights / scale * 255.0), 1, 255).astype(np.uint8)
    return encode_varints(gaps), q.tobytes(), scale


def decode_signature(gaps: bytes, weights: bytes, scale: float) -> BowVector:
    """The BoW vector (L1-normalised again) of an encoded signature; SignatureError if the parts
    do not fit."""
    q = np.frombuffer(bytes(weights), np.uint8)
    if not np.isfinite(scale) or scale < 0 or (len(q) and scale == 0):
        raise SignatureError(f"signature weight scale {scale!r} must be finite and > 0")
    try:
        gap = decode_varints(gaps, _MAX_VARINT_BYTES)
    except VarintError as exc:
        raise SignatureError(f"signature word ids: {exc}") from None
    if len(gap) == 0:
        if len(q):
            raise SignatureError(f"signature lists 0 words but {len(q)} weights")
        return BowVector(np.zeros(0, np.int32), np.zeros(0))
    if len(gap) != len(q):
        raise SignatureError(f"signature lists {len(gap)} words but {len(q)} weights")
    words = np.cumsum(gap) - 1
    if (gap <= 0).any():
        raise SignatureError("signature word ids must increase")
    if words[-1] > np.iinfo(np.int32).max:
        raise SignatureError("signature word id beyond int32")
    w = q.astype(float) / 255.0 * scale
    total = w.sum()
    return BowVector(words.astype(np.int32), w / total if total > 0 else w)
