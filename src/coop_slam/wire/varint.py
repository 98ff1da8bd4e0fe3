"""Little-endian base-128 varints (LEB128): small non-negative integers in one byte each, what
the compact keyframe messages carry their ids in (place signatures' word ids, map point ids)."""

from __future__ import annotations

import numpy as np

from ..errors import CoopSlamError


class VarintError(CoopSlamError):
    """Bytes that are no sequence of varints (or one longer than allowed)."""


def encode_varints(values: np.ndarray) -> bytes:
    """Non-negative integers (below 2^63) as concatenated varints."""
    out = bytearray()
    for v in np.asarray(values, np.int64).tolist():
        if v < 0:
            raise VarintError(f"a varint holds a non-negative integer, got {v}")
        while v >= 0x80:
            out.append((v & 0x7F) | 0x80)
            v >>= 7
        out.append(v)
    return bytes(out)


def decode_varints(raw: bytes, max_bytes: int) -> np.ndarray:
    """The int64 values of concatenated varints, each at most ``max_bytes`` long; VarintError if
    the bytes end inside one or one is longer."""
    raw = np.frombuffer(bytes(raw), np.uint8)
    if len(raw) == 0:
        return np.zeros(0, np.int64)
    if raw[-1] & 0x80:
        raise VarintError("the bytes end inside a varint")
    # Each varint ends at a byte below 0x80: split there and add up the 7-bit groups.
    ends = np.flatnonzero(raw < 0x80)
    starts = np.concatenate([[0], ends[:-1] + 1]).astype(np.int64)
    if (ends - starts).max() >= max_bytes:
        raise VarintError(f"a varint is longer than {max_bytes} bytes")
    value = (raw & 0x7F).astype(np.int64)
    shift = 7 * (np.arange(len(raw)) - np.repeat(starts, ends - starts + 1))
    return np.add.reduceat(value << shift, starts)
