"""Merge groups (union-find) and map-transform chaining."""

import numpy as np
import pytest

from coop_slam.geometry import invert, se3_from_quat, transform_error
from coop_slam.team.groups import GroupError, MergeGroups, chain_map_transform


def _rand_T(rng):
    return se3_from_quat(rng.normal(size=3), rng.normal(size=4))


def test_chaining_recovers_map_transform():
    rng = np.random.default_rng(0)
    T_world_mapA, T_world_mapB = _rand_T(rng), _rand_T(rng)
    T_mapA_camA, T_mapB_camB = _rand_T(rng), _rand_T(rng)
    T_camA_camB = invert(T_world_mapA @ T_mapA_camA) @ (T_world_mapB @ T_mapB_camB)
    est = chain_map_transform(T_mapA_camA, T_camA_camB, T_mapB_camB)
    dt, dr = transform_error(est, invert(T_world_mapA) @ T_world_mapB)
    assert dt < 1e-9 and dr < 1e-6


def test_groups_grow_and_root_is_smallest_id():
    rng = np.random.default_rng(1)
    T_world_map = {r: _rand_T(rng) for r in (1, 2, 3, 4)}
    rel = lambda a, b: invert(T_world_map[a]) @ T_world_map[b]  # noqa: E731
    g = MergeGroups([1, 2, 3, 4])
    assert g.groups() == [[1], [2], [3], [4]]
    g.merge(3, 4, rel(3, 4))  # a group without the master grows on its own
    assert g.groups() == [[1], [2], [3, 4]]
    g.merge(2, 3, rel(2, 3))
    assert g.root(4) == 2
    g.merge(4, 1, rel(4, 1))  # joining the master's group re-roots everything to robot 1
    assert g.groups() == [[1, 2, 3, 4]]
    for r in (2, 3, 4):
        dt, dr = transform_error(g.T_root_map(r), rel(1, r))
        assert dt < 1e-9 and dr < 1e-6
    assert np.allclose(g.T_mapA_mapB(3, 2), rel(3, 2))
    with pytest.raises(GroupError, match="already in one group"):
        g.merge(1, 2, rel(1, 2))
    with pytest.raises(GroupError, match="unknown"):
        g.root(9)
    with pytest.raises(GroupError, match="NaN"):
        MergeGroups([1, 2]).merge(1, 2, np.full((4, 4), np.nan))
