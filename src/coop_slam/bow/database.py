"""Team keyframe database: inverted-file place recognition over the keyframes of all robots.

Keyframes are keyed by ``(robot_id, keyframe_id)`` and carry a BoW vector (from the shared
vocabulary) and optionally their covisible keyframes of the same robot, best first. ``query``
follows ORB-SLAM's ``KeyFrameDatabase::DetectLoopCandidates``; :class:`ConsistencyChecker` is the
covisibility-consistency test of ORB-SLAM's ``LoopClosing::DetectLoop``, kept per querying robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping, Union

import numpy as np

from ..config import require
from ..errors import CoopSlamError
from .vocabulary import BowVector, l1_score

Key = tuple[int, int]  # (robot_id, keyframe_id)
_NO_ROBOT = np.iinfo(np.int64).min  # robot id of a free database slot


class DatabaseError(CoopSlamError):
    """A keyframe database operation refers to a missing or duplicate keyframe."""


@dataclass
class DatabaseConfig:
    """Candidate selection of :meth:`KeyframeDatabase.query` (ORB-SLAM values as defaults)."""

    # Absolute floor on a candidate's BoW score; also the threshold when the query has no
    # covisible keyframe in the database.
    min_score: float = 0.0
    # ORB-SLAM: a candidate must score at least as well as the query's worst covisible keyframe.
    use_covisible_min_score: bool = True
    # Candidates must share more than this fraction of the best candidate's common-word count.
    min_common_words_ratio: float = 0.8
    # Covisible keyframes of a candidate whose scores are accumulated into its group score.
    covisible_neighbours: int = 10
    # Groups whose accumulated score reaches this fraction of the best group are returned.
    accumulated_score_ratio: float = 0.75

    def validate(self) -> None:
        require(0.0 <= self.min_score <= 1.0, f"min_score must be in [0, 1], got {self.min_score}")
        require(
            0.0 <= self.min_common_words_ratio <= 1.0,
            f"min_common_words_ratio must be in [0, 1], got {self.min_common_words_ratio}",
        )
        require(self.covisible_neighbours >= 0, "covisible_neighbours must be >= 0")
        require(
            0.0 <= self.accumulated_score_ratio <= 1.0,
            f"accumulated_score_ratio must be in [0, 1], got {self.accumulated_score_ratio}",
        )


@dataclass
class ConsistencyConfig:
    """Temporal consistency: a candidate group must be seen in this many consecutive queries.

    ORB-SLAM's threshold 3 counts *successors* of the first detection (4 keyframes in all); here the
    first detection counts, so ``min_consecutive=4`` reproduces ORB-SLAM exactly.
    """

    min_consecutive: int = 3

    def validate(self) -> None:
        require(
            self.min_consecutive >= 1, f"min_consecutive must be >= 1, got {self.min_consecutive}"
        )


@dataclass(frozen=True)
class LoopCandidate:
    """Best keyframe of a retained covisibility group."""

    key: Key
    score: float  # BoW score of this keyframe against the query
    accumulated_score: float  # score summed over the group it was chosen from


@dataclass
class _Entry:
    key: Key
    bow: BowVector
    covisible: tuple[Key, ...] = field(default_factory=tuple)


def _key(robot_id: int, keyframe_id: int) -> Key:
    return (int(robot_id), int(keyframe_id))


class KeyframeDatabase:
    """Inverted index (word -> keyframes) over the keyframes of every robot of the team."""

    def __init__(self, config: DatabaseConfig | None = None):
        self.config = config or DatabaseConfig()
        self.config.validate()
        self._slot: dict[Key, int] = {}  # slots are reused so per-query arrays stay dense
        self._entries: list[_Entry | None] = []
        self._free: list[int] = []
        self._index: dict[int, set[int]] = {}
        self._robot = np.full(64, _NO_ROBOT, dtype=np.int64)  # robot id per slot

    # --- maintenance --------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._slot)

    def __contains__(self, key: Key) -> bool:
        return tuple(key) in self._slot

    def keys(self) -> list[Key]:
        return list(self._slot)

    def bow(self, robot_id: int, keyframe_id: int) -> BowVector:
        return self._get(_key(robot_id, keyframe_id)).bow

    def covisible(self, key: Key) -> tuple[Key, ...]:
        """Stored covisible keyframes of ``key`` (empty if unknown)."""
        slot = self._slot.get(tuple(key))
        return self._entries[slot].covisible if slot is not None else ()

    def add(
        self, robot_id: int, keyframe_id: int, bow: BowVector, covisible: Iterable[Key] = ()
    ) -> None:
        """Insert a keyframe; ``covisible`` lists same-robot keyframes, most shared points first."""
        key = _key(robot_id, keyframe_id)
        if key in self._slot:
            raise DatabaseError(f"keyframe {key} is already in the database; use update()")
        slot = self._free.pop() if self._free else len(self._entries)
        if slot == len(self._entries):
            self._entries.append(None)
            if slot == len(self._robot):
                self._robot = np.concatenate([self._robot, np.full_like(self._robot, _NO_ROBOT)])
        self._robot[slot] = key[0]
        self._entries[slot] = _Entry(key, bow, self._covisible_of(key, covisible))
        self._slot[key] = slot
        for w in bow.words.tolist():
            self._index.setdefault(w, set()).add(slot)

    def update(
        self,
        robot_id: int,
        keyframe_id: int,
        bow: BowVector | None = None,
        covisible: Iterable[Key] | None = None,
    ) -> None:
        """Replace a keyframe's BoW vector and/or covisible keyframes."""
        key = _key(robot_id, keyframe_id)
        entry = self._get(key)
        if bow is not None:
            slot = self._slot[key]
            self._unindex(slot, entry.bow)
            entry.bow = bow
            for w in bow.words.tolist():
                self._index.setdefault(w, set()).add(slot)
        if covisible is not None:
            entry.covisible = self._covisible_of(key, covisible)

    def remove(self, robot_id: int, keyframe_id: int) -> None:
        key = _key(robot_id, keyframe_id)
        entry = self._get(key)
        slot = self._slot.pop(key)
        self._unindex(slot, entry.bow)
        self._entries[slot] = None
        self._robot[slot] = _NO_ROBOT
        self._free.append(slot)

    def _get(self, key: Key) -> _Entry:
        slot = self._slot.get(key)
        if slot is None:
            raise DatabaseError(f"keyframe {key} is not in the database")
        return self._entries[slot]

    def _unindex(self, slot: int, bow: BowVector) -> None:
        for w in bow.words.tolist():
            slots = self._index.get(w)
            if slots is not None:
                slots.discard(slot)
                if not slots:
                    del self._index[w]

    @staticmethod
    def _covisible_of(key: Key, covisible: Iterable[Key]) -> tuple[Key, ...]:
        out = tuple(_key(*c) for c in covisible)
        other = [c for c in out if c[0] != key[0]]
        if other:
            raise DatabaseError(
                f"covisible keyframes of {key} must belong to robot {key[0]}, got {other[:3]}"
            )
        return tuple(c for c in out if c != key)

    # --- query --------------------------------------------------------------------------------
    def query(
        self,
        bow: BowVector,
        robot_id: int,
        keyframe_id: int,
        covisible: Iterable[Key] | None = None,
        other_robots_only: bool = True,
        exclude: Iterable[Key] = (),
        min_score: float | None = None,
    ) -> list[LoopCandidate]:
        """Place-recognition candidates for keyframe ``(robot_id, keyframe_id)``, best first.

        ``covisible`` defaults to the stored covisible keyframes of the query keyframe. They, the
        query itself and ``exclude`` are never returned; neither are keyframes of ``robot_id`` when
        ``other_robots_only``. ``min_score`` overrides ``config.min_score`` for this query.
        """
        cfg = self.config
        key = _key(robot_id, keyframe_id)
        covis = set(self.covisible(key) if covisible is None else (_key(*c) for c in covisible))
        floor = cfg.min_score if min_score is None else float(min_score)
        threshold = floor
        if cfg.use_covisible_min_score:
            present = [self._slot[c] for c in covis if c in self._slot]
            covis_scores = [l1_score(bow, self._entries[s].bow) for s in present]
            if covis_scores:
                threshold = max(floor, min(covis_scores))

        hits = [self._index[w] for w in bow.words.tolist() if w in self._index]
        if not hits:
            return []
        flat = np.fromiter(
            (s for slots in hits for s in slots), dtype=np.int64, count=sum(map(len, hits))
        )
        common = np.bincount(flat, minlength=len(self._entries))
        banned_keys = covis | {key} | {_key(*e) for e in exclude}
        banned = [self._slot[c] for c in banned_keys if c in self._slot]
        allowed = common > 0
        allowed[banned] = False
        if other_robots_only:
            allowed &= self._robot[: len(allowed)] != key[0]
        candidates = np.flatnonzero(allowed)
        if candidates.size == 0:
            return []
        min_common = cfg.min_common_words_ratio * common[candidates].max()
        # Every keyframe sharing enough words is scored (also below threshold): its score still
        # counts towards the group of a covisible candidate, as in ORB-SLAM.
        scored = {
            int(s): l1_score(bow, self._entries[s].bow)
            for s in candidates[common[candidates] >= min_common].tolist()
        }
        groups: dict[int, float] = {}  # best keyframe slot of a group -> accumulated score
        for slot, score in scored.items():
            if score < threshold:
                continue
            acc, best_slot, best = score, slot, score
            neighbours = self._entries[slot].covisible[: cfg.covisible_neighbours]
            for nb in neighbours:
                nb_slot = self._slot.get(nb)
                nb_score = scored.get(nb_slot) if nb_slot is not None else None
                if nb_score is None:
                    continue
                acc += nb_score
                if nb_score > best:
                    best_slot, best = nb_slot, nb_score
            groups[best_slot] = max(acc, groups.get(best_slot, 0.0))
        if not groups:
            return []
        keep = cfg.accumulated_score_ratio * max(groups.values())
        out = [
            LoopCandidate(self._entries[s].key, scored[s], acc)
            for s, acc in groups.items()
            if acc >= keep
        ]
        out.sort(key=lambda c: (-c.accumulated_score, -c.score, c.key))
        return out


GroupSource = Union[KeyframeDatabase, Mapping[Key, Iterable[Key]], Callable[[Key], Iterable[Key]]]


class ConsistencyChecker:
    """Accepts a candidate once its covisibility group has been consistent over consecutive queries.

    Two groups (candidate + its covisible keyframes) are consistent when they share a keyframe.
    State is kept per querying robot, so interleaved queries of different robots do not interfere.
    """

    def __init__(self, config: ConsistencyConfig | None = None):
        self.config = config or ConsistencyConfig()
        self.config.validate()
        self._groups: dict[int, list[tuple[frozenset[Key], int]]] = {}

    def reset(self, robot_id: int | None = None) -> None:
        if robot_id is None:
            self._groups.clear()
        else:
            self._groups.pop(int(robot_id), None)

    def check(
        self,
        robot_id: int,
        candidates: Iterable[Key | LoopCandidate],
        groups: GroupSource,
    ) -> list[Key]:
        """Feed the candidates of one query of ``robot_id``; return those now consistent enough.

        ``groups`` gives each candidate's covisible keyframes: a database, a mapping or a callable.
        An empty candidate list breaks every chain of this robot (as ORB-SLAM).
        """
        group_of = _group_source(groups)
        previous = self._groups.get(int(robot_id), [])
        used = [False] * len(previous)
        current: list[tuple[frozenset[Key], int]] = []
        accepted: list[Key] = []
        for cand in candidates:
            ckey = _key(*(cand.key if isinstance(cand, LoopCandidate) else cand))
            group = frozenset({ckey, *(_key(*k) for k in group_of(ckey))})
            consistent_somewhere = False
            enough = False
            for i, (prev_group, count) in enumerate(previous):
                if group.isdisjoint(prev_group):
                    continue
                consistent_somewhere = True
                if not used[i]:  # each previous group continues at most once
                    current.append((group, count + 1))
                    used[i] = True
                if count + 1 >= self.config.min_consecutive and not enough:
                    accepted.append(ckey)
                    enough = True
            if not consistent_somewhere:
                current.append((group, 1))
                if self.config.min_consecutive <= 1:
                    accepted.append(ckey)
        self._groups[int(robot_id)] = current
        return accepted


def _group_source(groups: GroupSource) -> Callable[[Key], Iterable[Key]]:
    if isinstance(groups, KeyframeDatabase):
        return groups.covisible
    if isinstance(groups, Mapping):
        return lambda k: groups.get(k, ())
    if callable(groups):
        return groups
    raise DatabaseError(f"groups must be a KeyframeDatabase, mapping or callable, got {groups!r}")


__all__ = [
    "ConsistencyChecker",
    "ConsistencyConfig",
    "DatabaseConfig",
    "DatabaseError",
    "Key",
    "KeyframeDatabase",
    "LoopCandidate",
]
