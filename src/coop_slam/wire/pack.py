"""Lossless packing of a keyframe message's integer arrays into one deflate stream (the
``packed`` field of each message kind): keypoint steps, octaves, depth halves, ids and references
repeat and follow each other, so deflate shrinks them where each array on its own is already as
small as its type allows. Descriptors and float positions are left out: they look random to
deflate. Each kind packs its own arrays (a :class:`Schema`); its first byte names the schema."""

from __future__ import annotations

import zlib
from typing import Mapping, NamedTuple

import numpy as np

from ..errors import CoopSlamError
from .varint import VarintError, decode_varints, encode_varints


class Schema(NamedTuple):
    """The arrays one kind of message packs, in stream order, with their little-endian element
    types; ``format`` is the stream's first byte (a change to the fields is a new format)."""

    format: int
    name: str
    fields: tuple[tuple[str, str], ...]


_LEVEL = 6
# A keyframe of 10000 keypoints holds ~100 kB of these arrays; more is a broken or hostile stream.
MAX_UNPACKED_BYTES = 8 << 20


class PackError(CoopSlamError):
    """A ``packed`` stream that does not decode to the arrays it names."""


def pack_fields(arrays: Mapping[str, np.ndarray], schema: Schema) -> bytes:
    """The deflate stream of ``arrays`` (names of the ``schema``'s fields; a name left out is an
    empty array): the schema's format byte, each array's length as a varint, then their bytes."""
    unknown = set(arrays) - {name for name, _ in schema.fields}
    if unknown:
        raise PackError(f"cannot pack {sorted(unknown)} in a {schema.name}: not among its fields")
    parts = [field_array(arrays.get(name, ()), dtype) for name, dtype in schema.fields]
    head = bytes([schema.format]) + encode_varints([len(p) for p in parts])
    return zlib.compress(head + b"".join(p.tobytes() for p in parts), _LEVEL)


def field_array(values, dtype: str = "u1") -> np.ndarray:
    """A message field's values as an array of ``dtype``: a uint8[] field is bytes on the wire, a
    list when a message is built in-process."""
    if isinstance(values, (bytes, bytearray)):
        return np.frombuffer(values, np.uint8)
    return np.asarray(values, dtype)


def unpack_fields(blob: bytes, schema: Schema) -> dict[str, np.ndarray]:
    """The arrays of :func:`pack_fields`' stream of this ``schema``, by name (every field, empty
    ones too); PackError if it is not one."""
    inflate = zlib.decompressobj()
    try:
        raw = inflate.decompress(bytes(blob), MAX_UNPACKED_BYTES)
    except zlib.error as exc:
        raise PackError(f"packed is no deflate stream ({exc})") from None
    if inflate.unconsumed_tail:
        raise PackError(f"packed unpacks to more than {MAX_UNPACKED_BYTES} bytes")
    if not inflate.eof:
        raise PackError("packed ends inside its deflate stream")
    if inflate.unused_data:
        raise PackError(f"packed holds {len(inflate.unused_data)} bytes after its deflate stream")
    if not raw or raw[0] != schema.format:
        raise PackError(
            f"packed is of format {raw[0] if raw else 'none'}, a {schema.name} is format "
            f"{schema.format}: client and server must run the same coop_slam"
        )
    fields = schema.fields
    # The lengths are the first varints: each ends at a byte below 0x80.
    ends = np.flatnonzero(np.frombuffer(raw[1:], np.uint8) < 0x80)
    if len(ends) < len(fields):
        raise PackError("packed ends inside its array lengths")
    body = 1 + int(ends[len(fields) - 1]) + 1
    try:
        lengths = decode_varints(raw[1:body], 5).tolist()
    except VarintError as exc:
        raise PackError(f"packed array lengths: {exc}") from None
    sizes = [n * np.dtype(dtype).itemsize for n, (_, dtype) in zip(lengths, fields)]
    if body + sum(sizes) != len(raw):
        raise PackError(
            f"packed holds {len(raw) - body} bytes of arrays, its lengths say {sum(sizes)}"
        )
    out, at = {}, body
    for (name, dtype), size in zip(fields, sizes):
        out[name] = np.frombuffer(raw, dtype, size // np.dtype(dtype).itemsize, at)
        at += size
    return out
