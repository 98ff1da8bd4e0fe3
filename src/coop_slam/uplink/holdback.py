"""When a client's keyframe records go: new keyframes wait a while and go as local BA left them,
culled ones never; updates of sent keyframes go coalesced."""

from __future__ import annotations

import dataclasses

from ..wire.record import ACTION_NEW, ACTION_UPDATE, KeyframeRecord


class Holdback:
    """When each keyframe record goes: a new keyframe after ``hold_new_s`` (its record then the
    latest snapshot, still as new; nothing at all when it was removed meanwhile), the updates of a
    keyframe already sent at most once per ``coalesce_s`` (the latest, ``coalesce_s`` after the
    first of them was held), removals of sent keyframes at once. Times are data time (frame
    stamps), so a lock-step run sends the same messages however fast the machine is. Records of
    one keyframe go in the order they were made; the server handles keyframes in any order."""

    def __init__(self, hold_new_s: float = 0.0, coalesce_s: float = 0.0):
        self.hold_new_s, self.coalesce_s = float(hold_new_s), float(coalesce_s)
        # keyframe id -> (data time held since, latest record); insertion order = creation order
        self._new: dict[int, tuple[float, KeyframeRecord]] = {}
        self._updates: dict[int, tuple[float, KeyframeRecord]] = {}

    def __len__(self) -> int:
        return len(self._new) + len(self._updates)

    def offer(self, rec: KeyframeRecord, now_s: float) -> list[KeyframeRecord]:
        """Hold ``rec`` (made at data time ``now_s``); returns what goes at once."""
        k = rec.keyframe_id
        if rec.action == ACTION_NEW:
            if self.hold_new_s <= 0:
                return [rec]
            self._new[k] = (now_s, rec)
        elif rec.action == ACTION_UPDATE:
            if k in self._new:  # not sent yet: it goes as new, as it is now
                self._new[k] = (self._new[k][0], dataclasses.replace(rec, action=ACTION_NEW))
            elif self.coalesce_s <= 0:
                return [rec]
            else:
                self._updates[k] = (self._updates.get(k, (now_s,))[0], rec)
        else:
            self._updates.pop(k, None)
            if self._new.pop(k, None) is None:  # the server has it
                return [rec]
        return []

    def due(self, now_s: float) -> list[KeyframeRecord]:
        """What has waited long enough at data time ``now_s``: new keyframes first, oldest
        first. Held later than ``now_s`` (data time went back: a looped bag, a reset clock) is
        due too, or it would wait until data time caught up."""
        out = []
        for held, wait in ((self._new, self.hold_new_s), (self._updates, self.coalesce_s)):
            for k in [k for k, (t, _) in held.items() if now_s - t >= wait or now_s < t]:
                out.append(held.pop(k)[1])
        return out

    def flush(self) -> list[KeyframeRecord]:
        """Everything held, new keyframes first."""
        return self.due(float("inf"))
