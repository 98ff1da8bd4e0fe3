"""Low-bandwidth mode: place signatures, the pull planner, the durable server taking signatures
and pulled keyframes, and the client's uplink in pull mode (no ROS master needed)."""

import dataclasses

import numpy as np
import pytest

from coop_slam.bow.vocabulary import BowVector, l1_score
from coop_slam.team.durable import DurableServer
from coop_slam.team.map_store import MapStoreError
from coop_slam.team.pull import PullConfig, PullPlanner
from coop_slam.team.server import TeamServer
from coop_slam.uplink.config import UplinkConfig
from coop_slam.uplink.planner import Planner
from coop_slam.uplink.records import signature_of
from coop_slam.wire.bow_signature import SignatureError, decode_signature, encode_signature
from coop_slam.wire.record import (
    ACTION_NEW,
    ACTION_REMOVE,
    ACTION_UPDATE,
    KeyframeError,
    KeyframeRecord,
    PlaceSignature,
)
from helpers import make_keyframe, team_keyframes, team_server_config, team_world


def test_a_signature_travels_in_about_two_bytes_a_word_and_scores_the_same():
    rng = np.random.default_rng(0)
    for vocabulary_words in (100_000, 2**31 - 1):  # gaps of one byte, and of five
        words = np.unique(rng.integers(0, vocabulary_words, 900))
        weights = rng.uniform(0.1, 1.0, len(words))
        bow = BowVector(words.astype(np.int32), weights / weights.sum())
        gaps, q, scale = encode_signature(bow)
        back = decode_signature(gaps, q, scale)
        np.testing.assert_array_equal(back.words, bow.words)
        assert l1_score(back, bow) > 0.995
    assert len(encode_signature(bow)[0]) <= 5 * len(words)
    words = np.unique(rng.integers(0, 100_000, 900))
    gaps, q, _ = encode_signature(BowVector(words.astype(np.int32), np.full(len(words), 1.0)))
    assert len(gaps) + len(q) < 2.5 * len(words)
    empty = decode_signature(*encode_signature(BowVector(np.zeros(0, np.int32), np.zeros(0))))
    assert len(empty) == 0
    gaps, q, scale = encode_signature(bow)
    with pytest.raises(SignatureError, match="words but"):
        decode_signature(gaps, q[:-1], scale)
    with pytest.raises(SignatureError, match="inside a varint"):
        decode_signature(gaps + b"\x80", q, scale)
    with pytest.raises(SignatureError, match="scale"):
        decode_signature(gaps, q, float("nan"))


def _sig(robot, kf, words, covisible=(), seed=0):
    rec = dataclasses.replace(
        make_keyframe(n=0, robot_id=robot, keyframe_id=kf, seed=seed),
        covisible_ids=np.array(covisible, np.uint32),
        covisible_weights=np.full(len(covisible), 50, np.uint16),
    )
    words = np.array(sorted(set(words)), np.int32)
    return PlaceSignature(rec, BowVector(words, np.full(len(words), 1.0 / len(words))))


def _views(rng, place, n=8, keep=150):
    """Signatures of n views of one place: each 150 of its 200 words plus 50 words of its own."""
    out = []
    for _ in range(n):
        own = rng.choice(place, keep, replace=False)
        noise = rng.integers(10**6, 2 * 10**6, 50)
        out.append(np.concatenate([own, noise]))
    return out


def test_the_planner_asks_for_both_keyframes_of_a_consistent_match_within_budget():
    rng = np.random.default_rng(1)
    place_a, place_b = rng.choice(10**5, 200, replace=False), rng.choice(10**5, 200) + 10**5
    planner = PullPlanner(PullConfig(keyframes_per_min=1.0, burst=1, timeout_s=5.0))
    # Robot 1 maps place A (keyframes 1-8), robot 2 place B (1-4), then A (5-8).
    for k, words in enumerate(_views(rng, place_a), start=1):
        assert planner.add(_sig(1, k, words, covisible=[k - 1] if k > 1 else []), k) == []
    views_b, views_a = _views(rng, place_b, 4), _views(rng, place_a, 4)
    asked = []
    for k, words in enumerate(views_b + views_a, start=1):
        asked.append(planner.add(_sig(2, k, words, covisible=[k - 1] if k > 1 else []), 10 + k))
    # Robot 2's first view of A is a candidate; its second makes it consistent: both asked for.
    assert asked[:5] == [[]] * 5
    assert len(asked[5]) == 2 and asked[5][0] == (2, 6) and asked[5][1][0] == 1
    assert planner.take_requests() == {2: [6], 1: [asked[5][1][1]]}
    assert planner.take_requests() == {}  # each once
    # The budget (1 a minute, 1 at once) is spent: the next consistent matches wait.
    assert asked[6:] == [[], []] and planner.over_budget >= 2
    # Robot 1 never answers: given up after 5 s; robot 2's keyframe arrived whole.
    planner.hold(2, 6)
    assert planner.expire(16.0 + 4.0) == []
    assert planner.expire(16.0 + 5.5) == [asked[5][1]] and planner.timeouts == 1
    assert planner.stats()["held"] == {"2": 1} and planner.requested == 2
    # A minute later the budget allows another pair (robot 2's 6 is held: only robot 1's).
    later = planner.add(_sig(2, 20, _views(rng, place_a, 1)[0], covisible=[8]), 90.0)
    assert later and later[0] == (2, 20) and all(k[0] == 1 for k in later[1:])
    planner.remove(2, 20)
    assert (2, 20) not in planner.pending and (2, 20) not in planner.db


def test_unlike_places_are_never_asked_for():
    rng = np.random.default_rng(2)
    planner = PullPlanner(PullConfig())
    for robot in (1, 2):
        place = rng.choice(10**5, 200, replace=False) + robot * 10**5
        for k, words in enumerate(_views(rng, place), start=1):
            planner.add(_sig(robot, k, words, covisible=[k - 1] if k > 1 else []), k)
    assert planner.requested == 0 and planner.take_requests() == {}


def _pull_server(world, tmp_path=None):
    cfg = team_server_config()
    cfg.pull.enabled = True
    clock = [0.0]
    path = str(tmp_path / "team.db") if tmp_path is not None else None
    durable = DurableServer(cfg, lambda c: TeamServer(c, world[3]), path, clock=lambda: clock[0])
    return durable, clock


def test_a_pulled_pair_merges_two_robots_that_sent_only_signatures(world, tmp_path):
    """Robot 1's 36 keyframes and robot 2's 8 go as signatures; the server asks for the pair it
    needs, a client answers from its own keyframes, and the robots merge with only those whole."""
    points, desc, kfs_a, vocab = world
    kfs_b = team_keyframes(
        2, np.linspace(2.0, 3.0, 8), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
    )
    own = {1: {k.keyframe_id: k for k in kfs_a}, 2: {k.keyframe_id: k for k in kfs_b}}
    durable, clock = _pull_server(world, tmp_path)
    seq = {1: 0, 2: 0}

    def send(item):
        seq[item.robot_id] += 1
        return durable.add_keyframe(item, 7, seq[item.robot_id])

    merges = []
    for kf in kfs_a + kfs_b:
        clock[0] = kf.stamp_s
        taken = send(signature_of(kf, vocab))
        assert taken.taken == 1 and not taken.rejected
        for robot, ids in durable.pull.take_requests().items():
            for kid in ids:
                merges += send(own[robot][kid]).merges
    assert merges and durable.server.robot_groups() == [(1, 2)]
    held = durable.pull.stats()["held"]
    assert sum(held.values()) <= 4 and durable.pull.requested == sum(held.values())
    assert sorted(durable.server.store.keys()) == sorted(durable.pull.held)
    # Signatures are not in the map file; the acknowledgement covers them.
    assert durable.acknowledged(1) == (7, seq[1]) and seq[1] > len(kfs_a)
    assert durable.store.count_inputs() == sum(held.values())
    # A removal of a keyframe the server never held touches only the planner.
    gone = next(k for k in own[1] if (1, k) not in durable.pull.held)
    send(KeyframeRecord(1, gone, 0.0, kfs_a[0].camera, np.eye(4), action=ACTION_REMOVE))
    assert durable.store.count_inputs() == sum(held.values()) and (1, gone) not in durable.pull.db


def test_a_server_not_in_low_bandwidth_mode_takes_signatures_and_refuses_unknown_robots(world):
    """A robot's radio budget sends signatures of the keyframes it holds back: a server in the
    default mode then asks for whole keyframes as in low-bandwidth mode, counting on those it
    holds already."""
    sig = signature_of(world[2][0], world[3])
    plain = DurableServer(team_server_config(), lambda c: TeamServer(c, world[3]), None)
    whole = dataclasses.replace(world[2][1], keyframe_id=77)
    assert plain.add_keyframe(whole).taken == 1 and plain.pull is None
    taken = plain.add_keyframe(sig)
    assert taken.taken == 1 and not taken.rejected and plain.pull is not None
    assert plain.pull.holds(whole.robot_id, 77)
    # Stored: the whole keyframe, not the one heard of as a signature only (not in the map file)
    assert plain.keyframes_stored()[whole.robot_id] == 1
    assert plain.last_ids()[whole.robot_id][0] == max(77, sig.keyframe_id)
    # A whole keyframe is cheap against a robot's budget: a lower floor, more of them a minute
    pull = team_server_config().pull
    assert plain.pull.config.min_score_ratio == pull.budget_min_score_ratio < pull.min_score_ratio
    assert plain.pull.config.keyframes_per_min == pull.budget_keyframes_per_min
    durable, _ = _pull_server(world)
    assert durable.pull.config.min_score_ratio == pull.min_score_ratio
    stranger = dataclasses.replace(sig, record=dataclasses.replace(sig.record, robot_id=9))
    with pytest.raises((KeyframeError, MapStoreError), match="unknown"):
        durable.add_keyframe(stranger)
    with pytest.raises(KeyframeError, match="without keypoints"):
        PlaceSignature(world[2][0], sig.bow).validate()


def test_the_client_uplink_in_pull_mode():
    up = Planner(UplinkConfig(mode="pull"))
    kf = make_keyframe(n=40, robot_id=1, keyframe_id=3)
    assert up.prepare(kf).signature
    moved = dataclasses.replace(kf, action=ACTION_UPDATE)
    assert up.prepare(moved).skip  # the server does not hold it: nothing to move
    assert not up.answer(kf).delta  # asked for: goes whole
    out = up.prepare(moved)
    assert out.delta and len(out.patched) == 0  # then its pose only
    assert not up.prepare(dataclasses.replace(kf, action=ACTION_REMOVE)).skip
    with pytest.raises(Exception, match="uplink.mode"):
        Planner(UplinkConfig(mode="push"))
    assert UplinkConfig().mode == "full" and not Planner().prepare(kf).signature
    assert kf.action == ACTION_NEW


@pytest.fixture(scope="module")
def world():
    return team_world()


def test_robots_seen_together_match_at_once():
    """A marker sighting: the two robots' alike views are asked for at the first query, without
    waiting for consistency over consecutive keyframes; after the window, as before."""
    rng = np.random.default_rng(4)
    place = rng.choice(10**5, 200, replace=False)
    for together, expect_first in ((True, True), (False, False)):
        planner = PullPlanner(PullConfig(rendezvous_window_s=10.0))
        views = _views(rng, place, 4)
        planner.add(_sig(1, 1, views[0]), 0.0)
        planner.add(_sig(1, 2, views[1], covisible=[1]), 0.5)
        if together:
            planner.seen_together(2, 1, 0.6)
        asked = planner.add(_sig(2, 1, views[2]), 1.0)
        assert bool(asked) == expect_first


def test_a_lost_robots_view_has_the_matching_keyframe_asked_for():
    """Assisted relocalization in low-bandwidth mode: the place a lost robot sees is a signature
    of its teammate's; the planner asks for that keyframe (once), and when the server holds it
    leaves the answer to the server's own keyframes."""
    rng = np.random.default_rng(5)
    place_a, place_b = rng.choice(10**5, 200, replace=False), rng.choice(10**5, 200) + 10**5
    planner = PullPlanner(PullConfig(burst=1), same_group=lambda a, b: True)
    for k, words in enumerate(_views(rng, place_a, 3), start=1):
        planner.add(_sig(1, k, words, covisible=[k - 1] if k > 1 else []), k)
    planner.add(_sig(2, 1, _views(rng, place_b, 1)[0]), 4.0)
    planner._spend([(1, 0)], 4.0)  # robot 1's budget is spent: a lost robot goes first anyway
    planner.take_requests()
    view = _sig(2, 99, _views(rng, place_a, 1)[0]).bow
    key = planner.ask_for_view(2, view, 5.0)
    assert key is not None and key[0] == 1
    assert planner.take_requests() == {1: [key[1]]}
    assert planner.ask_for_view(2, view, 5.5) == key and planner.take_requests() == {}
    planner.hold(*key)
    assert planner.ask_for_view(2, view, 6.0) is None  # the server holds it: its map answers
    alone = PullPlanner(PullConfig(), same_group=lambda a, b: a == b)
    for k, words in enumerate(_views(rng, place_a, 3), start=1):
        alone.add(_sig(1, k, words), k)
    assert alone.ask_for_view(2, view, 5.0) is None  # robot 1 is not in robot 2's group
