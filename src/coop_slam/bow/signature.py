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
    out = bytearray()
    for g in gaps.tolist():
        while g >= 0x80:
            out.append((g & 0x7F) | 0x80)
            g >>= 7
        out.append(g)
    scale = float(weights.max())
    q = np.clip(np.rint(weights / scale * 255.0), 1, 255).astype(np.uint8)
    return bytes(out), q.tobytes(), scale


def decode_signature(gaps: bytes, weights: bytes, scale: float) -> BowVector:
    """The BoW vector (L1-normalised again) of an encoded signature; SignatureError if the parts
    do not fit."""
    raw = np.frombuffer(bytes(gaps), np.uint8)
    q = np.frombuffer(bytes(weights), np.uint8)
    if not np.isfinite(scale) or scale < 0 or (len(q) and scale == 0):
        raise SignatureError(f"signature weight scale {scale!r} must be finite and > 0")
    if len(raw) == 0:
        if len(q):
            raise SignatureError(f"signature lists 0 words but {len(q)} weights")
        return BowVector(np.zeros(0, np.int32), np.zeros(0))
    if raw[-1] & 0x80:
        raise SignatureError("signature word ids end inside a varint")
    # Each varint ends at a byte below 0x80: split there and add up the 7-bit groups.
    ends = np.flatnonzero(raw < 0x80)
    starts = np.concatenate([[0], ends[:-1] + 1]).astype(np.int64)
    if len(ends) and (ends - starts).max() >= _MAX_VARINT_BYTES:
        raise SignatureError("signature word id gap longer than an int32")
    if len(ends) != len(q):
        raise SignatureError(f"signature lists {len(ends)} words but {len(q)} weights")
    value = (raw & 0x7F).astype(np.int64)
    shift = 7 * (np.arange(len(raw)) - np.repeat(starts, ends - starts + 1))
    gap = np.add.reduceat(value << shift, starts)
    words = np.cumsum(gap) - 1
    if (gap <= 0).any():
        raise SignatureError("signature word ids must increase")
    if words[-1] > np.iinfo(np.int32).max:
        raise SignatureError("signature word id beyond int32")
    w = q.astype(float) / 255.0 * scale
    total = w.sum()
    return BowVector(words.astype(np.int32), w / total if total > 0 else w)
