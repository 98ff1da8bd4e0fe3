"""Merge-order selection in the style of DSM-SLAM: which maps to merge first.

Input is an overlap table (robot pair -> number of verified or candidate keyframe matches) and the
current merge groups (:meth:`coop_slam.team.groups.MergeGroups.groups`). Maps are clustered by
their shared matches with a greedy agglomeration: the pair of groups with the most matches is
merged first, the merged group re-enters as one candidate whose match counts to every other group
are the sums of its members', and so on while some pair reaches ``min_matches``. A cluster that
does not overlap the first one grows on its own until a link to it appears, so the plan can end
with several groups. Pairs inside one group are loop closures, not merges, and are ignored.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import CoopSlamError


class MergeOrderError(CoopSlamError):
    """Inconsistent overlap table or groups (unknown robot, robot in two groups, negative count)."""


@dataclass
class MergeStep:
    map_a: int  # map of the reference group (smallest map id of the two groups)
    map_b: int  # map of the joining group; (map_a, map_b) has the most matches between them
    matches: int  # summed matches between the two groups
    group_a: list[int]  # members before the merge
    group_b: list[int]

    @property
    def group(self) -> list[int]:
        return sorted(self.group_a + self.group_b)


def _check(match_counts: dict[tuple[int, int], int], groups: list[list[int]]) -> dict:
    """Group index of each robot, after checking the inputs."""
    group_of: dict[int, int] = {}
    for g, members in enumerate(groups):
        for r in members:
            if r in group_of:
                raise MergeOrderError(f"robot {r} is listed in two groups")
            group_of[r] = g
    for (a, b), n in match_counts.items():
        if a == b:
            raise MergeOrderError(f"overlap table pairs robot {a} with itself")
        for r in (a, b):
            if r not in group_of:
                raise MergeOrderError(
                    f"robot {r} of the overlap table is in no group " f"(groups: {groups})"
                )
        if n < 0:
            raise MergeOrderError(f"negative match count {n} for robots {a} and {b}")
    return group_of


def plan_merge_steps(
    match_counts: dict[tuple[int, int], int], groups: list[list[int]], min_matches: int = 1
) -> list[MergeStep]:
    """Ordered merges (see the module docstring). Ties go to the group pair with the smallest robot
    ids, so the world group (robot 1) wins them and the plan is deterministic."""
    if min_matches < 1:
        raise MergeOrderError(f"min_matches must be >= 1, got {min_matches}")
    group_of = _check(match_counts, groups)
    # Robot-pair counts, symmetric ((a, b) and (b, a) are summed), and the group of each robot.
    pair_counts: dict[tuple[int, int], int] = {}
    for (a, b), n in match_counts.items():
        key = (min(a, b), max(a, b))
        pair_counts[key] = pair_counts.get(key, 0) + int(n)
    members = {g: sorted(m) for g, m in enumerate(groups) if m}
    steps: list[MergeStep] = []
    while True:
        # Group-pair totals: few groups (robots of one team), so a full recount per step is cheap.
        totals: dict[tuple[int, int], int] = {}
        for (a, b), n in pair_counts.items():
            ga, gb = group_of[a], group_of[b]
            if ga != gb and n > 0:
                key = (min(ga, gb), max(ga, gb))
                totals[key] = totals.get(key, 0) + n
        candidates = [(n, key) for key, n in totals.items() if n >= min_matches]
        if not candidates:
            return steps
        n, (g1, g2) = min(
            candidates,
            key=lambda c: (
                -c[0],
                min(members[c[1][0]] + members[c[1][1]]),
                sorted(members[c[1][0]] + members[c[1][1]]),
            ),
        )
        ga, gb = (g1, g2) if members[g1][0] < members[g2][0] else (g2, g1)
        # The robot pair carrying most matches between the two groups is the one to verify.
        ra, rb = min(
            (
                (a, b) if group_of[a] == ga else (b, a)
                for (a, b), c in pair_counts.items()
                if c > 0 and {group_of[a], group_of[b]} == {ga, gb}
            ),
            key=lambda p: (-pair_counts[(min(p), max(p))], p),
        )
        steps.append(MergeStep(ra, rb, n, list(members[ga]), list(members[gb])))
        for r in members[gb]:
            group_of[r] = ga
        members[ga] = sorted(members[ga] + members.pop(gb))


def plan_merges(
    match_counts: dict[tuple[int, int], int], groups: list[list[int]], min_matches: int = 1
) -> list[tuple[int, int]]:
    """Ordered (map_a, map_b) merges; map_a's group keeps its frame."""
    return [(s.map_a, s.map_b) for s in plan_merge_steps(match_counts, groups, min_matches)]
