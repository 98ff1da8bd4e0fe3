"""Turn one sequence into K robot segments (frame ranges, or equal parts with an overlap)."""

from __future__ import annotations

from .base import DatasetError, Sequence


def parse_ranges(text: str) -> list[tuple[int, int]]:
    """Parse ``"0-299,300-599"`` into inclusive (first, last) frame ranges."""
    ranges = []
    for part in text.split(","):
        part = part.strip()
        try:
            first_s, last_s = part.split("-") if "-" in part else (part, part)
            first, last = int(first_s), int(last_s)
        except ValueError:
            raise DatasetError(
                f"bad frame range '{part}' in '{text}': "
                "use FIRST-LAST (inclusive), e.g. 0-299,300-599"
            ) from None
        if first < 0 or last < first:
            raise DatasetError(f"bad frame range '{part}': need 0 <= FIRST <= LAST")
        ranges.append((first, last))
    if not ranges:
        raise DatasetError("no frame range given")
    return ranges


def split_ranges(seq: Sequence, ranges: list[tuple[int, int]] | str) -> list[Sequence]:
    """One sequence per inclusive frame range (positions in ``seq``), named
    ``<name>_<first>-<last>``."""
    if isinstance(ranges, str):
        ranges = parse_ranges(ranges)
    out = []
    for first, last in ranges:
        if last >= len(seq):
            raise DatasetError(
                f"frame range {first}-{last} exceeds {seq.name}, which has frames 0-{len(seq) - 1}"
            )
        out.append(seq.slice(first, last + 1, name=f"{seq.name}_{first}-{last}"))
    return out


def split_equal(seq: Sequence, parts: int, overlap_frames: int = 0) -> list[Sequence]:
    """``parts`` consecutive segments of about equal length; each shares ``overlap_frames`` frames
    with the next one."""
    if parts < 1:
        raise DatasetError(f"number of parts must be >= 1, got {parts}")
    if overlap_frames < 0:
        raise DatasetError(f"overlap must be >= 0 frames, got {overlap_frames}")
    n = len(seq)
    step = (n + overlap_frames * (parts - 1)) / parts
    if step - overlap_frames < 1:
        raise DatasetError(
            f"{seq.name}: {n} frames cannot make {parts} parts overlapping by " f"{overlap_frames}"
        )
    ranges = []
    for k in range(parts):
        first = int(round(k * (step - overlap_frames)))
        last = n - 1 if k == parts - 1 else min(n - 1, int(round(first + step)) - 1)
        ranges.append((first, last))
    return split_ranges(seq, ranges)
