"""Tests of the bag-of-words vocabulary, the team keyframe database and vocabulary training."""

from __future__ import annotations

import json
import os
import subprocess

import cv2
import numpy as np
import pytest

from coop_slam.bow import BowVector, Vocabulary, VocabularyError, l1_score, train
from coop_slam.bow.database import (
    ConsistencyChecker,
    ConsistencyConfig,
    DatabaseConfig,
    DatabaseError,
    KeyframeDatabase,
)
from coop_slam.bow.training import ExtractionConfig, image_files, train_from_sequences
from coop_slam.config import load_config
from coop_slam.descriptors import DescriptorError, hamming_matrix, hamming_rows, most_distinctive
from coop_slam.errors import ConfigError

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REDKITCHEN = os.path.join(REPO, "..", "shared", "data", "redkitchen_0000_0599")

N_CLUSTERS = 100
PLACE_SIZE = 8
N_IMAGES = 100
PER_IMAGE = 200
FLIP_BITS = 3


def _noisy(
    centres: np.ndarray, labels: np.ndarray, rng: np.random.Generator, flips: int = FLIP_BITS
) -> np.ndarray:
    """Descriptors of the given clusters with up to ``flips`` random bits flipped each."""
    bits = np.unpackbits(centres[labels], axis=1)
    n = len(labels)
    for _ in range(flips):
        bits[np.arange(n), rng.integers(0, 256, n)] ^= 1
    return np.packbits(bits, axis=1)


@pytest.fixture(scope="module")
def world():
    """Clustered descriptors; each training image sees a few clusters ("a place").

    100 clusters in 10 families of 10 (~40 bits apart inside a family, ~128 between families), so
    a k=10, L=2 tree has one leaf per cluster. Cluster 0 is in every image (a stop word), cluster 1
    in exactly one.
    """
    rng = np.random.default_rng(42)
    families = rng.integers(0, 256, (10, 32), dtype=np.uint8)
    centres = _noisy(families, np.repeat(np.arange(10), N_CLUSTERS // 10), rng, flips=24)
    sets, labels = [], []
    for i in range(N_IMAGES):
        lab = rng.choice(rng.choice(np.arange(2, N_CLUSTERS), PLACE_SIZE, replace=False), PER_IMAGE)
        lab[0] = 0
        if i == 7:
            lab[1] = 1
        sets.append(_noisy(centres, lab, rng))
        labels.append(lab)
    vocab = train(sets, k=10, levels=2, seed=1)
    return {"centres": centres, "sets": sets, "labels": labels, "vocab": vocab, "rng": rng}


# --- vocabulary -----------------------------------------------------------------------------------
def test_same_cluster_same_word(world):
    vocab, centres, rng = world["vocab"], world["centres"], world["rng"]
    labels = np.repeat(np.arange(N_CLUSTERS), 20)
    fresh = _noisy(centres, labels, rng)  # new noise, not seen in training
    words = vocab.words_of(fresh).reshape(N_CLUSTERS, 20)
    pure = np.all(words == words[:, :1], axis=1)
    assert pure.mean() >= 0.97, f"only {pure.mean():.1%} of clusters map to a single word"
    # ... and different clusters to different words.
    assert len(np.unique(words[pure, 0])) >= 0.8 * pure.sum()


def test_tree_structure(world):
    vocab = world["vocab"]
    assert vocab.k == 10 and vocab.levels == 2
    assert 90 <= vocab.n_words <= 110
    assert np.all(vocab.depth[vocab.word_node] <= 2)
    assert np.all(vocab.weights[~vocab.is_leaf] == 0)
    # Descent agrees with a brute-force per-level nearest child (Hamming from descriptors module).
    q = world["sets"][3][:50]
    node = np.zeros(len(q), dtype=int)
    for _ in range(vocab.levels):
        for i in range(len(q)):
            if vocab.is_leaf[node[i]]:
                continue
            ch = np.flatnonzero(vocab.parent == node[i])
            node[i] = ch[np.argmin(hamming_matrix(q[i : i + 1], vocab.descriptors[ch])[0])]
    assert np.array_equal(vocab.node_word[node], vocab.words_of(q))


def test_popcount_kernel_matches_descriptors_module():
    rng = np.random.default_rng(5)
    a = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    a[0], b[0] = 0, 255  # distance 256: overflows a naive byte-sum
    b[1] = a[1]
    # hamming_rows (SWAR popcount) against hamming_matrix (an independent BLAS bit product).
    assert np.array_equal(hamming_rows(a, b), np.diag(hamming_matrix(a, b)))
    assert hamming_rows(a[:1], b[:1])[0] == 256


def test_the_most_distinctive_descriptor_has_the_least_median_distance():
    """Against the definition written out with hamming_matrix, on rows of 0..8 descriptors (near
    copies of one another, so ties are common: the first wins); and a case worked by hand."""
    rng = np.random.default_rng(7)
    n, m = 300, 8
    base = rng.integers(0, 256, (n, 1, 32), dtype=np.uint8)
    noise = rng.integers(0, 256, (n, m, 32), dtype=np.uint8) * (rng.random((n, m, 32)) < 0.05)
    descs = np.ascontiguousarray(base ^ noise.astype(np.uint8))
    valid = np.arange(m)[None, :] < rng.integers(0, m + 1, n)[:, None]
    got = most_distinctive(descs.view(np.uint64), valid)
    for i in range(n):
        idx = np.flatnonzero(valid[i])
        if len(idx) == 0:
            assert got[i] == 0
            continue
        d = np.sort(hamming_matrix(descs[i, idx], descs[i, idx]), axis=1)
        assert got[i] == idx[np.argmin(d[:, (len(idx) - 1) // 2])]
    # a, a' (1 bit apart) and b (far): a and a' tie on the median (1 bit), a comes first.
    a = np.zeros(32, np.uint8)
    a2, b = a.copy(), np.full(32, 255, np.uint8)
    a2[0] = 1
    row = np.stack([b, a, a2, b])[None]
    valid = np.array([[True, True, True, False]])
    assert most_distinctive(row.view(np.uint64), valid)[0] == 1


def test_tf_idf_weights(world):
    vocab, sets = world["vocab"], world["sets"]
    idf = vocab.word_weights
    assert np.all(np.isfinite(idf)) and np.all(idf >= 0)
    per_image = [np.unique(vocab.words_of(s)) for s in sets]
    n_i = np.bincount(np.concatenate(per_image), minlength=vocab.n_words)
    seen = n_i > 0
    np.testing.assert_allclose(idf[seen], np.log(N_IMAGES / n_i[seen]))
    stop = vocab.words_of(world["centres"][:1])[0]
    assert idf[stop] == 0.0  # the word of cluster 0 is in every image: no information
    bow, fv = vocab.transform(sets[0])
    assert stop not in bow.words.tolist()
    assert abs(bow.weights.sum() - 1.0) < 1e-12 and np.all(bow.weights > 0)
    assert np.all(np.diff(bow.words) > 0)
    assert idf.max() <= np.log(N_IMAGES) + 1e-12


def test_a_signature_counts_the_features_on_its_words(world):
    """word_counts: the counts behind a transform's vector give it back exactly; a vector that is
    no such thing (weights not whole multiples of the IDF) has none, nor a word of 256 features."""
    from coop_slam.wire.bow_signature import counts_to_weights, word_counts

    vocab, sets = world["vocab"], world["sets"]
    idf = vocab.word_weights
    for image in sets[:5]:
        bow = vocab.transform(image)[0]
        counts = word_counts(bow, idf)
        words = vocab.words_of(image)
        truth = np.bincount(words, minlength=vocab.n_words)[bow.words]
        np.testing.assert_array_equal(counts, truth)  # (each image has a word seen once)
        np.testing.assert_allclose(counts_to_weights(bow.words, counts, idf), bow.weights)
    skewed = BowVector(bow.words, bow.weights * np.linspace(1.0, 1.3, len(bow)))
    assert word_counts(BowVector(skewed.words, skewed.weights / skewed.weights.sum()), idf) is None
    crowded = vocab.transform(np.concatenate([sets[0][1:2]] * 256 + [sets[0]]))[0]
    assert word_counts(crowded, idf) is None
    assert word_counts(bow, idf[: bow.words[-1]]) is None  # another vocabulary


def test_scores(world):
    vocab, sets = world["vocab"], world["sets"]
    a, _ = vocab.transform(sets[0])
    a2, _ = vocab.transform(sets[0][::-1].copy())
    assert vocab.score(a, a2) == pytest.approx(1.0)
    assert l1_score(a, a) == pytest.approx(1.0)
    # L1 score as DBoW2: 1 - 0.5 |a - b|_1 over the dense vectors.
    b, _ = vocab.transform(sets[1])
    dense = np.zeros((2, vocab.n_words))
    dense[0, a.words], dense[1, b.words] = a.weights, b.weights
    assert vocab.score(a, b) == pytest.approx(1 - 0.5 * np.abs(dense[0] - dense[1]).sum())
    # Images of disjoint cluster sets score low; a half-overlapping one in between.
    rng, centres = world["rng"], world["centres"]
    lab = world["labels"][0]
    same_place = vocab.transform(_noisy(centres, lab, rng))[0]
    others = np.setdiff1d(np.arange(2, N_CLUSTERS), lab)
    other = rng.choice(rng.choice(others, PLACE_SIZE, replace=False), PER_IMAGE)
    other[0] = 0  # the stop word, shared by everything, must not make images look alike
    unrelated = vocab.transform(_noisy(centres, other, rng))[0]
    half = vocab.transform(_noisy(centres, np.concatenate([lab[:100], other[100:]]), rng))[0]
    s_same, s_half, s_unrel = (vocab.score(a, v) for v in (same_place, half, unrelated))
    assert s_same > 0.85 and s_unrel < 0.05 and 0.3 < s_half < 0.7


def test_feature_vector(world):
    vocab, desc = world["vocab"], world["sets"][5]
    bow, fv = vocab.transform(desc, levels_up=1)
    idx = np.concatenate([ix for _, ix in fv.items()])
    words = vocab.words_of(desc)
    kept = np.flatnonzero(vocab.word_weights[words] > 0)
    assert np.array_equal(np.sort(idx), kept)  # each non-stop feature exactly once
    for node, ix in fv.items():
        assert vocab.depth[node] == 1
        leaves = vocab.word_node[words[ix]]
        assert np.all((vocab.parent[leaves] == node) | (leaves == node))
    assert np.array_equal(fv[int(fv.nodes[0])], fv.to_dict()[int(fv.nodes[0])])
    _, root_fv = vocab.transform(desc, levels_up=5)  # above the root: everything under node 0
    assert root_fv.nodes.tolist() == [0]


def test_transform_edge_cases(world):
    vocab = world["vocab"]
    bow, fv = vocab.transform(np.zeros((0, 32), np.uint8))
    assert len(bow) == 0 and len(fv) == 0
    assert l1_score(bow, bow) == 0.0
    with pytest.raises(DescriptorError, match="shape"):
        vocab.transform(np.zeros((3, 31), np.uint8))
    with pytest.raises(VocabularyError):
        train([], k=10, levels=2)
    with pytest.raises(VocabularyError, match="k must be"):
        train(world["sets"][:2], k=1, levels=2)
    assert BowVector.from_dict({5: 2.0, 1: 2.0}).to_dict() == {1: 0.5, 5: 0.5}


def test_bench_command_prints_and_writes_the_same_figures(tmp_path, capsys):
    """scripts/bench's contract: a ``name value unit`` line per figure, the same figures in the
    JSON file; the values themselves are never asserted (speed is the machine's)."""
    from coop_slam.tools.bench import main

    out = tmp_path / "bench.json"
    assert main(["--only", "bow", "--out", str(out)]) == 0
    lines = [ln.split() for ln in capsys.readouterr().out.splitlines() if not ln.startswith("#")]
    figures = json.loads(out.read_text())
    assert lines and len(lines) == len(figures)
    for name, value, unit in lines:
        assert figures[name]["unit"] == unit
        assert float(value) == pytest.approx(figures[name]["value"], rel=1e-3)


# --- files ----------------------------------------------------------------------------------------
def _same(a: Vocabulary, b: Vocabulary) -> None:
    assert (a.k, a.levels) == (b.k, b.levels)
    assert np.array_equal(a.parent, b.parent)
    assert np.array_equal(a.descriptors, b.descriptors)
    assert np.array_equal(a.weights, b.weights)


def test_round_trip_npz_and_text(world, tmp_path):
    vocab, desc = world["vocab"], world["sets"][9]
    for name in ("voc.npz", "voc.txt"):
        path = tmp_path / name
        vocab.save(path)
        loaded = Vocabulary.load(path)
        _same(vocab, loaded)
        assert loaded.transform(desc)[0].to_dict() == vocab.transform(desc)[0].to_dict()
    first = (tmp_path / "voc.txt").read_text().splitlines()
    assert first[0] == "10 2 0 0" and len(first) == vocab.n_nodes
    assert len(first[1].split()) == 35


def _dbow2_text() -> str:
    """Tiny DBoW2 file in HKmeansStep's depth-first order (not breadth-first), ORBvoc spacing."""

    def d(values: list[int]) -> str:
        return " ".join(map(str, values))

    return (
        "\n".join(
            [
                "3 2  0 0",
                f"0 0 {d([0] * 32)}  0",  # node 1 (line 2): inner
                f"0 1 {d([255] * 32)}  1.5",  # node 2 (line 3): leaf at level 1
                f"1 1 {d([1] + [0] * 31)}  0.7",  # node 3 (line 4)
                f"1 1 {d([0] * 31 + [7])}  0.2",  # node 4 (line 5)
                f"0 0 {d([15] * 32)}  0",  # node 5 (line 6): inner, after the children of node 1
                f"5 1 {d([15] * 31 + [31])}  0.9",  # node 6 (line 7)
            ]
        )
        + "\n"
    )


def test_load_dbow2_text(tmp_path):
    path = tmp_path / "ORBvoc.txt"
    path.write_text(_dbow2_text())
    vocab = Vocabulary.load(path)
    assert vocab.n_nodes == 7 and vocab.n_words == 4
    assert vocab.word_node.tolist() == [2, 3, 4, 6]
    assert vocab.children[0, :3].tolist() == [1, 2, 5] and vocab.children[5].tolist() == [6, 6, 6]
    assert vocab.words_of(vocab.descriptors[[3, 4, 6, 2]]).tolist() == [1, 2, 3, 0]
    assert vocab.word_weights.tolist() == [1.5, 0.7, 0.2, 0.9]
    vocab.save_text(tmp_path / "again.txt")
    _same(vocab, Vocabulary.load_text(tmp_path / "again.txt"))


def _edit(line: int, field: int, value: str):
    """Mutation: set whitespace-separated ``field`` of 1-based ``line`` (None = drop it)."""

    def mutate(lines: list[str]) -> list[str]:
        parts = lines[line - 1].split()
        if value is None:
            del parts[field]
        else:
            parts[field] = value
        return lines[: line - 1] + [" ".join(parts)] + lines[line:]

    return mutate


@pytest.mark.parametrize(
    "mutate, line, message",
    [
        (lambda ls: ["3 2 0"] + ls[1:], 1, "header"),
        (lambda ls: ["a 2 0 0"] + ls[1:], 1, "non-integer"),
        (lambda ls: ["3 2 1 0"] + ls[1:], 1, "not supported"),
        (lambda ls: ["3 2 0 0"] + ls[1:], None, None),  # control: valid
        (_edit(4, 34, None), 4, "expected 35 fields"),
        (lambda ls: ls[:4] + [ls[4] + " 1"] + ls[5:], 5, "expected 35 fields"),
        (_edit(3, 2, "256"), 3, "out of range"),
        (_edit(5, 33, "-1"), 5, "out of range"),
        (_edit(4, 5, "1.5"), 4, "non-integer"),
        (_edit(4, 0, "9"), 4, "unknown parent"),
        (_edit(3, 0, "2"), 3, "unknown parent"),
        (_edit(3, 0, "-1"), 3, "unknown parent"),
        (_edit(2, 1, "2"), 2, "is_leaf must be 0 or 1"),
        (_edit(3, 1, "0"), 3, "no children"),
        (_edit(2, 1, "1"), 2, "flagged as leaf"),
        (lambda ls: ls[:4] + [""] + ls[4:], 5, "empty line"),
        (_edit(7, 34, "x"), 7, "non-numeric"),
        (_edit(7, 34, "nan"), 7, "non-finite"),
        (_edit(7, 34, "-0.5"), 7, "weight"),
        (lambda ls: ls[:1], None, "no nodes"),
    ],
)
def test_malformed_text_rejected(tmp_path, mutate, line, message):
    path = tmp_path / "bad.txt"
    path.write_text("\n".join(mutate(_dbow2_text().splitlines())) + "\n")
    if message is None:
        Vocabulary.load(path)
        return
    with pytest.raises(VocabularyError, match=message) as err:
        Vocabulary.load(path)
    where = f"{path}:{line}:" if line is not None else str(path)
    assert where in str(err.value)


def test_malformed_structure_rejected(tmp_path):
    d = " ".join(["1"] * 32)
    too_many = ["2 2 0 0"] + [f"0 1 {d} 1"] * 3
    too_deep = ["2 1 0 0", f"0 0 {d} 0", f"1 1 {d} 1"]
    for lines, message in ((too_many, "more than k=2"), (too_deep, "deeper than L=1")):
        path = tmp_path / "bad.txt"
        path.write_text("\n".join(lines) + "\n")
        with pytest.raises(VocabularyError, match=message):
            Vocabulary.load(path)
    with pytest.raises(VocabularyError, match="cannot read"):
        Vocabulary.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    np.savez(junk, something=np.zeros(3))
    with pytest.raises(VocabularyError, match="not a coop_slam vocabulary"):
        Vocabulary.load(junk)


def test_npz_version_checked(world, tmp_path):
    path = tmp_path / "v.npz"
    world["vocab"].save_npz(path)
    with np.load(path) as data:
        arrays = dict(data)
    arrays["version"] = np.array(99)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    with pytest.raises(VocabularyError, match="version 99"):
        Vocabulary.load(path)


# --- database -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def places(world):
    """20 places of 8 clusters each; view(p) is a fresh noisy view of 7 of place p's clusters."""
    rng = np.random.default_rng(7)
    members = np.array(
        [rng.choice(np.arange(2, N_CLUSTERS), PLACE_SIZE, replace=False) for _ in range(20)]
    )
    vocab, centres = world["vocab"], world["centres"]

    def view(p: int) -> BowVector:
        lab = rng.choice(rng.choice(members[p], 7, replace=False), 200)
        return vocab.transform(_noisy(centres, lab, rng))[0]

    return view


def _team_db(view, config: DatabaseConfig | None = None) -> KeyframeDatabase:
    """Two covisible keyframes per place for robot 0 (kf 2p, 2p+1) and place 3 for robot 1."""
    db = KeyframeDatabase(config)
    for p in range(20):
        db.add(0, 2 * p, view(p), covisible=[(0, 2 * p + 1)])
        db.add(0, 2 * p + 1, view(p), covisible=[(0, 2 * p)])
    db.add(1, 100, view(3), covisible=[(1, 101)])
    db.add(1, 101, view(3), covisible=[(1, 100)])
    return db


def test_query_finds_other_robot_keyframe(places):
    db = _team_db(places)
    result = db.query(places(3), robot_id=1, keyframe_id=200)
    assert result, "no candidate found"
    assert result[0].key in {(0, 6), (0, 7)}
    assert all(c.key[0] == 0 for c in result)  # other_robots_only
    best = result[0]
    assert best.accumulated_score > best.score > 0.3  # group of two covisible keyframes
    assert {c.key for c in result} <= {(0, 6), (0, 7)}

    own_view = db.bow(1, 100)  # robot 1 back where it was: its own keyframe is the best match
    assert db.query(own_view, 1, 200, other_robots_only=False)[0].key == (1, 100)
    assert all(c.key[0] == 0 for c in db.query(own_view, 1, 200))

    excluded = db.query(places(3), 1, 200, exclude=[(0, 6), (0, 7)])
    assert not {c.key for c in excluded} & {(0, 6), (0, 7)}


def test_query_covisible_threshold_and_maintenance(places):
    db = _team_db(places)
    # Robot 1's keyframe 100 sees place 3; if its covisible keyframe were a copy of the query, the
    # ORB-SLAM threshold (worst covisible score) would be 1 and nothing else could pass.
    query = places(3)
    db.add(1, 102, query)
    assert db.query(query, 1, 200, covisible=[(1, 102)]) == []
    assert db.query(query, 1, 200, covisible=[(1, 102)], other_robots_only=False) == []
    relaxed = KeyframeDatabase(DatabaseConfig(use_covisible_min_score=False))
    for key in db.keys():
        relaxed.add(*key, db.bow(*key), db.covisible(key))
    assert relaxed.query(query, 1, 200, covisible=[(1, 102)])[0].key in {(0, 6), (0, 7)}
    # A query's own covisible keyframes are never candidates.
    own = db.query(query, 0, 6, covisible=[(0, 7)], other_robots_only=False)
    assert not {c.key for c in own} & {(0, 6), (0, 7)}

    db.remove(0, 6)
    db.remove(0, 7)
    assert (0, 6) not in db and len(db) == 41
    result = db.query(query, 1, 200)
    assert not result or result[0].key not in {(0, 6), (0, 7)}
    db.update(0, 10, bow=query, covisible=[])  # keyframe 10 now shows place 3
    assert db.query(query, 1, 200)[0].key == (0, 10)
    db.add(0, 6, query)  # reuses a freed slot
    assert {c.key for c in db.query(query, 1, 200)} == {(0, 6), (0, 10)}
    with pytest.raises(DatabaseError, match="already"):
        db.add(0, 6, query)
    with pytest.raises(DatabaseError, match="not in the database"):
        db.remove(5, 5)
    with pytest.raises(DatabaseError, match="must belong to robot 0"):
        db.add(0, 999, query, covisible=[(1, 100)])


def test_configs_validate():
    with pytest.raises(ConfigError):
        load_config(DatabaseConfig, {"min_common_words_ratio": 1.5})
    with pytest.raises(ConfigError):
        load_config(ConsistencyConfig, {"min_consecutive": 0})
    with pytest.raises(ConfigError, match="unknown"):
        load_config(DatabaseConfig, {"min_scor": 0.1})
    assert load_config(DatabaseConfig, {"covisible_neighbours": 5}).covisible_neighbours == 5


def test_consistency_checker():
    # Covisibility of robot 0's keyframes: a chain 1-2-3-4; 10 stands alone.
    groups = {
        (0, 1): [(0, 2)],
        (0, 2): [(0, 1), (0, 3)],
        (0, 3): [(0, 2), (0, 4)],
        (0, 4): [(0, 3)],
    }
    checker = ConsistencyChecker()
    assert checker.check(1, [(0, 1)], groups) == []
    assert checker.check(1, [(0, 2), (0, 10)], groups) == []
    assert checker.check(1, [(0, 3)], groups) == [(0, 3)]  # third consecutive consistent query
    assert checker.check(1, [(0, 4)], groups) == [(0, 4)]
    # An empty query breaks the chain; a jump to an unrelated group restarts it.
    assert checker.check(1, [], groups) == []
    assert checker.check(1, [(0, 1)], groups) == []
    assert checker.check(1, [(0, 10)], groups) == []
    assert checker.check(1, [(0, 1)], groups) == []
    assert checker.check(1, [(0, 2)], groups) == []
    # Another robot's queries do not touch robot 1's chain.
    assert checker.check(2, [(0, 10)], groups) == []
    assert checker.check(1, [(0, 3)], groups) == [(0, 3)]
    # Works from a database's covisibility too, and with ORB-SLAM's exact count (4).
    db = KeyframeDatabase()
    bow = BowVector.from_dict({1: 1.0})
    for key, cov in groups.items():
        db.add(*key, bow, cov)
    orb_slam = ConsistencyChecker(ConsistencyConfig(min_consecutive=4))
    results = [orb_slam.check(3, [(0, i)], db) for i in (1, 2, 3, 4)]
    assert results == [[], [], [], [(0, 4)]]


# --- training from images ----------------------------------------------------------------------
def _write_images(folder, n: int = 4) -> None:
    rng = np.random.default_rng(3)
    os.makedirs(folder / "sub", exist_ok=True)
    for i in range(n):
        img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (5, 5), 0)
        cv2.imwrite(str(folder / ("sub" if i % 2 else "") / f"img{i}.png"), img)


@pytest.mark.slow
def test_train_from_images_and_cli(tmp_path):
    _write_images(tmp_path / "imgs")
    paths = image_files(str(tmp_path / "imgs"))
    assert len(paths) == 4
    vocab = train_from_sequences(
        image_paths=paths,
        extraction=ExtractionConfig(features=300, every=1),
        out=str(tmp_path / "v.npz"),
    )
    _same(vocab, Vocabulary.load(tmp_path / "v.npz"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(VocabularyError, match="no images"):
        image_files(str(tmp_path / "empty"))
    env = dict(os.environ, PYTHONPATH=os.path.join(REPO, "src"))
    script = os.path.join(REPO, "scripts", "train_vocabulary")
    out = tmp_path / "cli.txt"
    args = ["--images", str(tmp_path / "imgs"), "--every", "2", "--features", "200"]
    args += ["-k", "5", "-L", "3", "--out", str(out)]
    done = subprocess.run([script, *args], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert Vocabulary.load(out).k == 5
    bad = subprocess.run(
        [script, "--images", str(tmp_path / "nowhere"), "--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert bad.returncode == 1 and "image folder not found" in bad.stderr


def test_synthetic_sequences(monkeypatch):
    import coop_slam.datasets as datasets
    from coop_slam.camera import CameraModel
    from coop_slam.datasets import Sequence
    from coop_slam.default_vocabulary import synthetic_sequences

    cam = CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0)
    seqs = {2: Sequence("b", cam, []), 1: Sequence("a", cam, [])}

    class World:  # stands in for datasets.SyntheticWorld
        sequences = seqs

    monkeypatch.setattr(datasets, "read_synthetic", lambda folder: World(), raising=False)
    assert [s.name for s in synthetic_sequences("world")] == ["a", "b"]
    monkeypatch.delattr(datasets, "read_synthetic", raising=False)
    with pytest.raises(VocabularyError, match="read_synthetic"):
        synthetic_sequences("world")


# --- real data ------------------------------------------------------------------------------------
def _near(t_a: np.ndarray, t_b: np.ndarray, max_m: float = 0.5, max_deg: float = 30.0) -> bool:
    rel = np.linalg.inv(t_a) @ t_b
    angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1)))
    return bool(np.linalg.norm(rel[:3, 3]) < max_m and angle < max_deg)


@pytest.mark.slow
def test_redkitchen_retrieval():
    """Frames 300-599 (robot 1) must find robot 0's keyframes (0-299) seen from a nearby pose."""
    if not os.path.isdir(REDKITCHEN):
        pytest.skip(f"RedKitchen test data not found at {os.path.normpath(REDKITCHEN)}")
    from coop_slam.bow.training import collect_descriptors
    from coop_slam.datasets import read_tum

    seq = read_tum(REDKITCHEN)
    poses = seq.frame_poses()
    cfg = ExtractionConfig(every=5)
    db_sets = collect_descriptors([seq.slice(0, 300)], extraction=cfg)
    q_sets = collect_descriptors([seq.slice(300, 600)], extraction=cfg)
    vocab = train(db_sets, k=10, levels=4, seed=0)
    db_frames, q_frames = list(range(0, 300, 5)), list(range(300, 600, 5))
    db = KeyframeDatabase()
    for i, (frame, desc) in enumerate(zip(db_frames, db_sets)):
        neighbours = [j for j in (i - 1, i + 1, i - 2, i + 2) if 0 <= j < len(db_frames)]
        db.add(0, frame, vocab.transform(desc)[0], [(0, db_frames[j]) for j in neighbours])
    answerable = found = 0
    for frame, desc in zip(q_frames, q_sets):
        if not any(_near(poses[frame], poses[g]) for g in db_frames):
            continue  # nothing of frames 0-299 was seen from near this pose
        answerable += 1
        result = db.query(vocab.transform(desc)[0], 1, frame)
        found += bool(result) and _near(poses[frame], poses[result[0].key[1]])
    assert answerable >= 20
    assert found / answerable >= 0.7, f"top candidate near in only {found}/{answerable} queries"
