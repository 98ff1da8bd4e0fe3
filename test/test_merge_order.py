"""Merge-order selection: greedy clustering of maps by shared matches."""

import pytest

from coop_slam.team.merge_order import MergeOrderError, plan_merge_steps, plan_merges

# Six robots in two clusters, {1, 2, 3} and {4, 5, 6}, linked only weakly (3-4).
TWO_CLUSTERS = {
    (1, 2): 50,
    (2, 3): 30,
    (1, 3): 10,
    (4, 5): 45,
    (5, 6): 35,
    (4, 6): 2,
    (3, 4): 2,
}
SINGLETONS = [[r] for r in range(1, 7)]


def test_two_clusters_grow_independently():
    steps = plan_merge_steps(TWO_CLUSTERS, SINGLETONS, min_matches=5)
    assert [(s.map_a, s.map_b) for s in steps] == [(1, 2), (4, 5), (2, 3), (5, 6)]
    # Merged groups re-enter as one candidate with summed counts: {1,2}-3 = 30 + 10.
    assert [s.matches for s in steps] == [50, 45, 40, 37]
    assert steps[2].group_a == [1, 2] and steps[2].group_b == [3]
    assert steps[3].group == [4, 5, 6]


def test_link_between_clusters_merges_them_last():
    counts = dict(TWO_CLUSTERS)
    counts[(3, 4)] = 8
    counts[(6, 1)] = 4  # reversed key order is fine; sums with nothing else
    steps = plan_merge_steps(counts, SINGLETONS, min_matches=5)
    assert len(steps) == 5
    last = steps[-1]
    assert (last.map_a, last.map_b) == (3, 4) and last.matches == 12
    assert last.group == [1, 2, 3, 4, 5, 6]


def test_counts_are_summed_over_existing_groups():
    # Neither robot pair reaches 5 alone, the groups together do.
    counts = {(1, 3): 3, (2, 3): 3, (1, 2): 40}
    assert plan_merges(counts, [[1, 2], [3]], min_matches=5) == [(1, 3)]
    assert plan_merges(counts, [[1], [2], [3]], min_matches=5) == [(1, 2), (1, 3)]
    # Pairs inside one group are loop closures, not merges.
    assert plan_merges({(1, 2): 40}, [[1, 2]], min_matches=1) == []


def test_reference_group_is_the_one_with_the_smallest_robot():
    assert plan_merges({(5, 2): 9}, [[2], [5]]) == [(2, 5)]
    # Tie between {1}-{2} and {3}-{4}: the world group's merge goes first.
    assert plan_merges({(3, 4): 7, (1, 2): 7}, [[1], [2], [3], [4]]) == [(1, 2), (3, 4)]


def test_nothing_to_merge_and_bad_input():
    assert plan_merges({}, SINGLETONS) == []
    assert plan_merges(TWO_CLUSTERS, SINGLETONS, min_matches=100) == []
    with pytest.raises(MergeOrderError):
        plan_merges({(1, 7): 3}, SINGLETONS)
    with pytest.raises(MergeOrderError):
        plan_merges({(1, 2): -1}, SINGLETONS)
    with pytest.raises(MergeOrderError):
        plan_merges({(1, 1): 3}, SINGLETONS)
    with pytest.raises(MergeOrderError):
        plan_merges({}, [[1, 2], [2]])
    with pytest.raises(MergeOrderError):
        plan_merges({}, SINGLETONS, min_matches=0)
