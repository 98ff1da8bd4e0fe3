"""Hierarchical bag-of-binary-words vocabulary for ORB descriptors, as in DBoW2.

The vocabulary is a k-ary tree of depth L trained by k-means++ seeding and k-majority clustering
per level (:mod:`.clustering`); its leaves are the *words*, weighted by inverse document frequency
(TF-IDF). A set of descriptors becomes an L1-normalised BoW vector (for place recognition) and a
*feature vector* (direct index: node ``levels_up`` above the leaves -> feature indices, for
BoW-guided matching). Two vectors are compared with DBoW2's L1 score ``s = 1 - 0.5 * |v1 - v2|_1``.

The tree is stored as flat arrays (parent, children table, node descriptors, node weights) so that
``transform`` descends all descriptors at once, one numpy step per level. Files: an own versioned
``.npz`` format and the DBoW2 text format of ORB-SLAM's ``ORBvoc.txt``.
"""

from __future__ import annotations

import functools
import os
import re
import time
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

import numpy as np
from numba import njit

from ..config import require
from ..descriptors import DESCRIPTOR_BYTES, as_descriptors, hamming
from ..errors import CoopSlamError
from .clustering import k_majority

FORMAT_NAME = "coop_slam.bow.vocabulary"
FORMAT_VERSION = 1
SCORING_L1_NORM = 0  # DBoW2 ScoringType L1_NORM
WEIGHTING_TF_IDF = 0  # DBoW2 WeightingType TF_IDF
DEFAULT_K = 10
DEFAULT_LEVELS = 5
DEFAULT_LEVELS_UP = 4  # ORB-SLAM's direct-index level (levels above the leaves)
_TEXT_FIELDS = 2 + DESCRIPTOR_BYTES + 1  # parent is_leaf d0..d31 weight

ProgressCallback = Callable[[str, int, int], None]  # (stage, done, total)


class VocabularyError(CoopSlamError):
    """A vocabulary file is malformed or a vocabulary cannot be trained/used as asked."""


@dataclass
class VocabularyConfig:
    """Training parameters: branching factor k, depth L, k-majority iteration cap, RNG seed."""

    k: int = DEFAULT_K
    levels: int = DEFAULT_LEVELS
    max_iterations: int = 10
    seed: int = 0

    def validate(self) -> None:
        require(2 <= self.k <= 20, f"vocabulary k must be in 2..20 (DBoW2 limit), got {self.k}")
        require(1 <= self.levels <= 10, f"vocabulary levels must be in 1..10, got {self.levels}")
        require(self.max_iterations >= 1, "vocabulary max_iterations must be >= 1")


@dataclass(frozen=True)
class BowVector:
    """Sparse L1-normalised BoW vector: sorted unique word ids and their weights."""

    words: np.ndarray  # (W,) int32, strictly increasing
    weights: np.ndarray  # (W,) float64, > 0, sum 1 (or empty)

    def __len__(self) -> int:
        return len(self.words)

    def to_dict(self) -> dict[int, float]:
        return dict(zip(self.words.tolist(), self.weights.tolist()))

    @classmethod
    def from_dict(cls, values: dict[int, float]) -> "BowVector":
        """Vector from ``{word: weight}`` (weights are L1-normalised here)."""
        words = np.array(sorted(values), dtype=np.int32)
        weights = np.array([values[w] for w in words.tolist()], dtype=np.float64)
        total = weights.sum()
        return cls(words, weights / total if total > 0 else weights)


@dataclass(frozen=True)
class FeatureVector:
    """Direct index in CSR form: feature indices ``indices[offsets[i]:offsets[i+1]]`` fell under
    tree node ``nodes[i]`` (``nodes`` sorted, so two frames' shared nodes are one intersect1d)."""

    nodes: np.ndarray  # (G,) int32, strictly increasing
    offsets: np.ndarray  # (G + 1,) int64
    indices: np.ndarray  # (F,) int32, increasing within each node

    def __len__(self) -> int:
        return len(self.nodes)

    def __getitem__(self, node: int) -> np.ndarray:
        i = int(np.searchsorted(self.nodes, node))
        if i == len(self.nodes) or self.nodes[i] != node:
            raise KeyError(node)
        return self.indices[self.offsets[i] : self.offsets[i + 1]]

    def items(self) -> Iterator[tuple[int, np.ndarray]]:
        for i, node in enumerate(self.nodes.tolist()):
            yield node, self.indices[self.offsets[i] : self.offsets[i + 1]]

    def to_dict(self) -> dict[int, np.ndarray]:
        return dict(self.items())


def l1_score(a: BowVector, b: BowVector) -> float:
    """DBoW2 L1 score ``1 - 0.5 * |a - b|_1`` of two L1-normalised vectors, in [0, 1].

    For non-negative unit-L1 vectors this equals the sum over shared words of ``min(a_w, b_w)``,
    which only needs the (small) intersection of the word lists.
    """
    if len(a) == 0 or len(b) == 0:
        return 0.0
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum())


class Vocabulary:
    """Vocabulary tree as flat arrays. Node 0 is the root; words are the leaves in node order."""

    def __init__(
        self,
        k: int,
        levels: int,
        parent: np.ndarray,
        descriptors: np.ndarray,
        weights: np.ndarray,
        is_leaf: np.ndarray | None = None,
        source: str = "<memory>",
        line_offset: int | None = None,
    ):
        """Build from node arrays (index = node id, node 0 = root with parent -1).

        ``is_leaf`` (as stored in DBoW2 text files) is checked against the tree; ``source`` and
        ``line_offset`` (text line of node 0) only make error messages point into the file.
        """

        def where(node: int) -> str:
            if line_offset is None:
                return f"{source}: node {node}"
            return f"{source}:{node + line_offset}"

        self.k = int(k)
        self.levels = int(levels)
        parent = np.asarray(parent, dtype=np.int64)
        descriptors = np.asarray(descriptors)
        n = len(parent)
        if n < 2 or parent[0] != -1:
            raise VocabularyError(f"{source}: a vocabulary needs a root and at least one word")
        if (
            descriptors.shape != (n, DESCRIPTOR_BYTES)
            or descriptors.dtype != np.uint8
            or np.shape(weights) != (n,)
        ):
            raise VocabularyError(f"{source}: node arrays have inconsistent shapes")
        ids = np.arange(n)
        bad = np.flatnonzero((parent[1:] < 0) | (parent[1:] >= ids[1:])) + 1
        if bad.size:  # parents precede children in DBoW2 files, which also rules out cycles
            raise VocabularyError(
                f"{where(int(bad[0]))}: unknown parent {parent[bad[0]]} (must be an earlier node)"
            )
        n_children = np.bincount(parent[1:], minlength=n)
        leaf = n_children == 0
        if is_leaf is not None:
            mismatch = np.flatnonzero(np.asarray(is_leaf, dtype=bool) != leaf)
            if mismatch.size:
                node = int(mismatch[0])
                if leaf[node]:
                    msg = f"node {node} is flagged as inner node (is_leaf 0) but has no children"
                else:
                    msg = f"node {node} is flagged as leaf (is_leaf 1) but has children"
                raise VocabularyError(f"{where(node)}: {msg}")
        crowded = np.flatnonzero(n_children > self.k)
        if crowded.size:
            node = int(crowded[0])
            raise VocabularyError(
                f"{where(node)}: node {node} has {n_children[node]} children, more than k={self.k}"
            )
        # Depth by pointer jumping (vectorised): levels+1 rounds reach the root from any valid node.
        depth = np.zeros(n, dtype=np.int64)
        anc = parent.copy()
        for _ in range(self.levels + 1):
            active = anc > 0
            depth += active
            anc[active] = parent[anc[active]]
        depth[1:] += 1
        deep = np.flatnonzero((anc > 0) | (depth > self.levels))
        if deep.size:
            raise VocabularyError(
                f"{where(int(deep[0]))}: node {deep[0]} is deeper than L={self.levels} levels"
            )
        weights = np.asarray(weights, dtype=np.float64)
        if not np.all(np.isfinite(weights)) or np.any(weights < 0):
            node = int(np.flatnonzero(~np.isfinite(weights) | (weights < 0))[0])
            raise VocabularyError(f"{where(node)}: weight {weights[node]} must be finite and >= 0")

        self.parent = parent.astype(np.int32)
        self.descriptors = np.ascontiguousarray(descriptors)
        self.weights = weights
        self.is_leaf = leaf
        self.depth = depth.astype(np.int32)
        # Children table (n, k): missing children repeat the first child and leaves point to
        # themselves, so every descent step is the same gather + argmin for all descriptors
        # (argmin returns the first of equal distances, i.e. the real child).
        order = np.argsort(parent[1:], kind="stable") + 1
        par_sorted = parent[order]
        first = np.searchsorted(par_sorted, par_sorted, side="left")
        slot = np.arange(len(order)) - first
        children = np.repeat(ids[:, None], self.k, axis=1).astype(np.int32)
        children[par_sorted, slot] = order
        has = ~leaf
        fill = np.arange(self.k)[None, :] >= n_children[:, None]
        children[has] = np.where(fill[has], children[has, :1], children[has])
        self.children = children
        self._desc64 = self.descriptors.view(np.uint64)
        self.word_node = np.flatnonzero(leaf).astype(np.int32)
        self.node_word = np.full(n, -1, dtype=np.int32)
        self.node_word[self.word_node] = np.arange(len(self.word_node), dtype=np.int32)

    # --- properties ---------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return len(self.parent)

    @property
    def n_words(self) -> int:
        return len(self.word_node)

    @functools.cached_property
    def word_weights(self) -> np.ndarray:
        """IDF weight of every word (0 = stop word, ignored by transform); gathered once (every
        place signature's counts are weighed with it), after training has set the weights."""
        out = self.weights[self.word_node]
        out.setflags(write=False)
        return out

    def __repr__(self) -> str:
        return (
            f"Vocabulary(k={self.k}, L={self.levels}, nodes={self.n_nodes}, words={self.n_words})"
        )

    # --- transform ----------------------------------------------------------------------------
    def _descend(self, q: np.ndarray, record_depth: int) -> tuple[np.ndarray, np.ndarray]:
        """Leaf node of each descriptor and its node at ``record_depth`` (0 when that is 0)."""
        return _descend(q.view(np.uint64), self.children, self._desc64, self.levels, record_depth)

    def words_of(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id of every descriptor (no weighting, no stop-word removal)."""
        leaf, _ = self._descend(as_descriptors(descriptors), 0)
        return self.node_word[leaf]

    def transform(
        self, descriptors: np.ndarray, levels_up: int = DEFAULT_LEVELS_UP
    ) -> tuple[BowVector, FeatureVector]:
        """BoW vector and feature vector (node ``levels_up`` above the leaves -> feature indices).

        As DBoW2, features falling on zero-weight words (stop words) are left out of both.
        """
        q = as_descriptors(descriptors)
        record_depth = max(self.levels - int(levels_up), 0)
        leaf, rec = self._descend(q, record_depth)
        w = self.weights[leaf]
        keep = np.flatnonzero(w > 0)
        words = self.node_word[leaf[keep]]
        uw, inv = np.unique(words, return_inverse=True)
        vals = np.bincount(inv, weights=w[keep], minlength=len(uw))
        total = vals.sum()
        bow = BowVector(uw.astype(np.int32), vals / total if total > 0 else vals)
        if record_depth == 0:
            rec_kept = np.zeros(len(keep), dtype=np.int32)
        else:
            rec_kept = rec[keep]
        order = np.argsort(rec_kept, kind="stable")
        sorted_nodes = rec_kept[order]
        un, starts = np.unique(sorted_nodes, return_index=True)
        offsets = np.append(starts, len(order)).astype(np.int64)
        fv = FeatureVector(un.astype(np.int32), offsets, keep[order].astype(np.int32))
        return bow, fv

    def score(self, a: BowVector, b: BowVector) -> float:
        """L1 score (see :func:`l1_score`)."""
        return l1_score(a, b)

    # --- own format ---------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Save as DBoW2 text if ``path`` ends with ``.txt``, else in the own ``.npz`` format."""
        if os.fspath(path).endswith(".txt"):
            self.save_text(path)
        else:
            self.save_npz(path)

    def save_npz(self, path: str | os.PathLike) -> None:
        _ensure_dir(path)
        with open(path, "wb") as fh:  # a file object keeps numpy from appending ".npz"
            np.savez_compressed(
                fh,
                format=np.array(FORMAT_NAME),
                version=np.array(FORMAT_VERSION),
                k=np.array(self.k),
                levels=np.array(self.levels),
                scoring=np.array(SCORING_L1_NORM),
                weighting=np.array(WEIGHTING_TF_IDF),
                parent=self.parent,
                descriptors=self.descriptors,
                weights=self.weights,
            )

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Vocabulary":
        """Load either format (told apart by content: ``.npz`` files are zip archives)."""
        try:
            with open(path, "rb") as fh:
                magic = fh.read(2)
        except OSError as exc:
            raise VocabularyError(f"cannot read vocabulary file {path}: {exc.strerror}") from None
        return cls.load_npz(path) if magic == b"PK" else cls.load_text(path)

    @classmethod
    def load_npz(cls, path: str | os.PathLike) -> "Vocabulary":
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
        except (OSError, ValueError) as exc:
            raise VocabularyError(f"{path}: not a readable .npz vocabulary ({exc})") from None
        needed = ("format", "version", "k", "levels", "parent", "descriptors", "weights")
        missing = [key for key in needed if key not in arrays]
        if missing:
            raise VocabularyError(
                f"{path}: not a coop_slam vocabulary (lacks {', '.join(missing)})"
            )
        if str(arrays["format"]) != FORMAT_NAME:
            raise VocabularyError(f"{path}: format '{arrays['format']}' is not {FORMAT_NAME}")
        if int(arrays["version"]) != FORMAT_VERSION:
            raise VocabularyError(
                f"{path}: vocabulary format version {int(arrays['version'])} is not supported "
                f"(this code reads version {FORMAT_VERSION}); retrain or convert it"
            )
        for key in ("scoring", "weighting"):
            if key in arrays and int(arrays[key]) != 0:
                raise VocabularyError(
                    f"{path}: only L1-norm scoring and TF-IDF weighting are supported"
                )
        desc = arrays["descriptors"]
        if desc.dtype != np.uint8:
            raise VocabularyError(f"{path}: node descriptors must be uint8, got {desc.dtype}")
        return cls(
            int(arrays["k"]),
            int(arrays["levels"]),
            arrays["parent"],
            desc,
            arrays["weights"],
            source=os.fspath(path),
        )

    # --- DBoW2 text format --------------------------------------------------------------------
    def save_text(self, path: str | os.PathLike) -> None:
        """DBoW2/ORB-SLAM text: ``k L scoring weighting``, then ``parent is_leaf d0..d31 weight``
        for every node but the root, in node order."""
        _ensure_dir(path)
        rows = np.column_stack(
            [self.parent[1:], self.is_leaf[1:].astype(np.int32), self.descriptors[1:]]
        ).astype(np.int64)
        with open(path, "w", encoding="ascii") as fh:
            fh.write(f"{self.k} {self.levels} {SCORING_L1_NORM} {WEIGHTING_TF_IDF}\n")
            ints = [" ".join(map(str, r)) for r in rows.tolist()]
            fh.writelines(f"{i} {w!r}\n" for i, w in zip(ints, self.weights[1:].tolist()))

    @classmethod
    def load_text(cls, path: str | os.PathLike) -> "Vocabulary":
        """Load a DBoW2 text vocabulary (e.g. ORB-SLAM's ORBvoc.txt) with full validation."""
        source = os.fspath(path)
        try:
            with open(path, "rb") as fh:
                raw = fh.read()
        except OSError as exc:
            raise VocabularyError(f"cannot read vocabulary file {source}: {exc.strerror}") from None
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError as exc:
            line = raw[: exc.start].count(b"\n") + 1
            raise VocabularyError(f"{source}:{line}: non-ASCII byte in a text vocabulary") from None
        header, _, body = text.partition("\n")
        k, levels = _parse_header(header, source)
        body = body.rstrip()
        blank = re.search(r"(^|\n)[ \t\r]*(\n|$)", body)
        if not body:
            raise VocabularyError(f"{source}: no nodes after the header line")
        if blank:
            line = body[: blank.start()].count("\n") + 2 + (1 if blank.group(1) else 0)
            raise VocabularyError(f"{source}:{line}: empty line inside the node list")
        data = _parse_rows(body, source)
        n = len(data) + 1  # row r of data is node r + 1, on line r + 2 (header is line 1)
        cols = data[:, :-1]
        if not np.all(cols == np.floor(cols)):
            bad = int(np.flatnonzero(np.any(cols != np.floor(cols), axis=1))[0])
            raise VocabularyError(f"{source}:{bad + 2}: non-integer parent, flag or byte")
        flags = data[:, 1]
        if np.any((flags != 0) & (flags != 1)):
            bad = int(np.flatnonzero((flags != 0) & (flags != 1))[0])
            raise VocabularyError(f"{source}:{bad + 2}: is_leaf must be 0 or 1")
        dbytes = data[:, 2:-1]
        out = (dbytes < 0) | (dbytes > 255)
        if np.any(out):
            bad = int(np.flatnonzero(np.any(out, axis=1))[0])
            raise VocabularyError(f"{source}:{bad + 2}: descriptor byte out of range 0..255")
        parent = np.concatenate([[-1], data[:, 0].astype(np.int64)])
        desc = np.zeros((n, DESCRIPTOR_BYTES), dtype=np.uint8)
        desc[1:] = dbytes.astype(np.uint8)
        weights = np.concatenate([[0.0], data[:, -1]])
        is_leaf = np.concatenate([[False], flags == 1])
        return cls(k, levels, parent, desc, weights, is_leaf, source=source, line_offset=1)

    # --- training -----------------------------------------------------------------------------
    @classmethod
    def train(
        cls,
        descriptor_sets: Sequence[np.ndarray],
        k: int = DEFAULT_K,
        levels: int = DEFAULT_LEVELS,
        seed: int = 0,
        progress: ProgressCallback | None = None,
        max_iterations: int = 10,
    ) -> "Vocabulary":
        """See :func:`train`."""
        return train(descriptor_sets, k, levels, seed, progress, max_iterations)


def _ensure_dir(path: str | os.PathLike) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)


def _parse_header(header: str, source: str) -> tuple[int, int]:
    parts = header.split()
    if len(parts) != 4:
        raise VocabularyError(
            f"{source}:1: header must be 'k L scoring weighting' (4 integers), got {header!r}"
        )
    try:
        k, levels, scoring, weighting = (int(p) for p in parts)
    except ValueError:
        raise VocabularyError(f"{source}:1: non-integer value in header {header!r}") from None
    if not (2 <= k <= 20 and 1 <= levels <= 10 and 0 <= scoring <= 5 and 0 <= weighting <= 3):
        raise VocabularyError(
            f"{source}:1: header values out of range (k 2..20, L 1..10, scoring 0..5, "
            f"weighting 0..3): {header!r}"
        )
    if scoring != SCORING_L1_NORM or weighting != WEIGHTING_TF_IDF:
        raise VocabularyError(
            f"{source}:1: scoring {scoring} / weighting {weighting} not supported "
            "(only 0 0 = L1-norm scoring with TF-IDF weights, as ORB-SLAM's ORBvoc.txt)"
        )
    return k, levels


def _parse_rows(body: str, source: str) -> np.ndarray:
    """(n, 35) float64 node rows. Fast C parse; on any failure a line-by-line pass finds the
    offending line so the message can name it."""
    lines = body.split("\n")
    try:
        data = np.loadtxt(lines, dtype=np.float64, comments=None, ndmin=2)
    except ValueError:
        data = None
    if data is not None and data.shape == (len(lines), _TEXT_FIELDS) and np.all(np.isfinite(data)):
        return data
    for lineno, line in enumerate(lines, start=2):
        parts = line.split()
        if len(parts) != _TEXT_FIELDS:
            raise VocabularyError(
                f"{source}:{lineno}: expected {_TEXT_FIELDS} fields "
                f"'parent is_leaf d0..d{DESCRIPTOR_BYTES - 1} weight', got {len(parts)}"
            )
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise VocabularyError(
                f"{source}:{lineno}: non-numeric field in {line[:60]!r}"
            ) from None
        if not all(np.isfinite(vals)):
            raise VocabularyError(f"{source}:{lineno}: non-finite value")
    raise VocabularyError(f"{source}: cannot parse the node list")  # pragma: no cover


# --- training ------------------------------------------------------------------------------------
def train(
    descriptor_sets: Sequence[np.ndarray],
    k: int = DEFAULT_K,
    levels: int = DEFAULT_LEVELS,
    seed: int = 0,
    progress: ProgressCallback | None = None,
    max_iterations: int = 10,
) -> Vocabulary:
    """Train a vocabulary from one descriptor array per training image (DBoW2's HKmeans).

    All nodes of a level are clustered together (batched numpy, no per-node Python recursion).
    As DBoW2: a node with at most k descriptors gets one child per descriptor, nodes holding one
    descriptor are leaves, and word weights are ``idf = log(N_images / N_images_with_word)``
    (0 for words no training image reaches).
    """
    cfg = VocabularyConfig(k=k, levels=levels, max_iterations=max_iterations, seed=seed)
    try:
        cfg.validate()
    except CoopSlamError as exc:
        raise VocabularyError(str(exc)) from None
    sets = [as_descriptors(d, f"descriptor set {i}") for i, d in enumerate(descriptor_sets)]
    if not sets:
        raise VocabularyError("cannot train a vocabulary without training images")
    data = np.concatenate(sets)
    if len(data) < 2:
        raise VocabularyError(f"cannot train a vocabulary from {len(data)} descriptor(s)")
    rng = np.random.default_rng(seed)
    report = progress or (lambda stage, done, total: None)

    parents = [np.array([-1], dtype=np.int64)]
    descs = [np.zeros((1, DESCRIPTOR_BYTES), dtype=np.uint8)]
    n_nodes = 1
    act = np.arange(len(data))  # descriptors still to be split
    node = np.zeros(len(data), dtype=np.int64)  # their current node
    for level in range(1, levels + 1):
        report("cluster level", level - 1, levels)
        if act.size == 0:
            break
        order = np.argsort(node, kind="stable")
        act, node = act[order], node[order]
        uniq, starts, sizes = np.unique(node, return_index=True, return_counts=True)
        per_row_size = np.repeat(sizes, sizes)
        local = np.arange(len(act)) - np.repeat(starts, sizes)  # trivial case: own child each
        big = sizes > k
        if np.any(big):
            rows_big = np.flatnonzero(per_row_size > k)
            g_sizes = sizes[big]
            g_starts = np.concatenate([[0], np.cumsum(g_sizes)[:-1]])
            g_of_row = np.repeat(np.arange(len(g_sizes)), g_sizes)
            lab, centres = k_majority(
                data[act[rows_big]], g_of_row, g_starts, g_sizes, k, rng, max_iterations
            )
            local[rows_big] = lab
            big_index = np.full(n_nodes, -1, dtype=np.int64)
            big_index[uniq[big]] = np.arange(len(g_sizes))
        key = node * k + local  # children numbered by (parent, cluster): contiguous per parent
        ukey, first, inv = np.unique(key, return_index=True, return_inverse=True)
        child_parent = ukey // k
        child_desc = data[act[first]].copy()
        if np.any(big):
            from_big = big_index[child_parent] >= 0
            child_desc[from_big] = centres[big_index[child_parent[from_big]], ukey[from_big] % k]
        parents.append(child_parent)
        descs.append(child_desc)
        node = n_nodes + inv
        n_nodes += len(ukey)
        keep = np.bincount(inv, minlength=len(ukey))[inv] > 1
        act, node = act[keep], node[keep]
    report("cluster level", levels, levels)

    parent = np.concatenate(parents)
    vocab = Vocabulary(
        k, levels, parent, np.concatenate(descs), np.zeros(n_nodes), source="training"
    )
    report("word weights", 0, 1)
    image_of = np.repeat(np.arange(len(sets)), [len(s) for s in sets])
    words = vocab.words_of(data)
    pairs = np.unique(image_of.astype(np.int64) * vocab.n_words + words)
    n_i = np.bincount(pairs % vocab.n_words, minlength=vocab.n_words)
    idf = np.zeros(vocab.n_words)
    seen = n_i > 0
    idf[seen] = np.log(len(sets) / n_i[seen])
    vocab.weights[vocab.word_node] = idf
    report("word weights", 1, 1)
    return vocab


def bench_transform(
    vocabulary: Vocabulary | None = None,
    n_descriptors: int = 1000,
    repeats: int = 50,
    seed: int = 0,
) -> float:
    """Median milliseconds per ``transform`` of ``n_descriptors`` random descriptors.

    Without a vocabulary a full random k=10, L=5 tree is built (no training), which costs the same
    per descent as a trained one.
    """
    rng = np.random.default_rng(seed)
    if vocabulary is None:
        vocabulary = _random_vocabulary(DEFAULT_K, DEFAULT_LEVELS, rng)
    q = rng.integers(0, 256, (n_descriptors, DESCRIPTOR_BYTES), dtype=np.uint8)
    vocabulary.transform(q)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        vocabulary.transform(q)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def _random_vocabulary(k: int, levels: int, rng: np.random.Generator) -> Vocabulary:
    """Complete k-ary tree with random node descriptors and random positive word weights."""
    counts = k ** np.arange(levels + 1)
    n = int(counts.sum())
    parent = np.full(n, -1, dtype=np.int64)
    parent[1:] = (np.arange(1, n) - 1) // k  # BFS numbering of a complete tree
    desc = rng.integers(0, 256, (n, DESCRIPTOR_BYTES), dtype=np.uint8)
    weights = np.zeros(n)
    weights[n - counts[-1] :] = rng.uniform(0.1, 5.0, counts[-1])
    return Vocabulary(k, levels, parent, desc, weights, source="random")


__all__ = [
    "BowVector",
    "FeatureVector",
    "Vocabulary",
    "VocabularyConfig",
    "VocabularyError",
    "bench_transform",
    "l1_score",
    "train",
]


@njit(cache=True, nogil=True)
def _descend(q64, children, desc64, levels, record_depth):
    """Per descriptor (four uint64 words): down the tree to the nearest child at each level (ties:
    the first child) -> (leaf nodes, nodes at ``record_depth``; 0 when that is 0). Compiled: one
    loop where numpy built a (descriptors, k, 4) array per level."""
    m, k = q64.shape[0], children.shape[1]
    leaf = np.empty(m, np.int32)
    recorded = np.zeros(m, np.int32)
    for i in range(m):
        node = 0
        for depth in range(1, levels + 1):
            best, best_d = children[node, 0], 1 << 30
            for c in range(k):
                d = hamming(q64[i], desc64[children[node, c]])
                if d < best_d:
                    best, best_d = children[node, c], d
            node = best
            if depth == record_depth:
                recorded[i] = node
        leaf[i] = node
    return leaf, recorded


def warm_up() -> None:
    """Compile (or load from numba's cache) the descent on a one-node tree."""
    _descend(
        np.zeros((1, 4), np.uint64), np.zeros((1, 1), np.int32), np.zeros((1, 4), np.uint64), 1, 0
    )
