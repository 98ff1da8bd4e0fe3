"""Merged groups of maps (union-find) and the chaining that turns one accepted keyframe-to-
keyframe constraint into a map-to-map transform.

Each group's frame is the map with its smallest map id, so the group holding robot 1 (the master)
is expressed in robot 1's first map, which the server publishes as ``world``.
"""

from __future__ import annotations

import numpy as np

from ..errors import CoopSlamError, GeometryError
from ..geometry import check_se3, invert
from ..ids import MapId


class GroupError(CoopSlamError):
    """Unknown robot or invalid transform handed to the merge groups."""


def chain_map_transform(
    T_mapA_camA: np.ndarray, T_camA_camB: np.ndarray, T_mapB_camB: np.ndarray
) -> np.ndarray:
    """``T_mapA_mapB`` from keyframe poses in their own maps and the verified relative pose."""
    return T_mapA_camA @ T_camA_camB @ invert(T_mapB_camB)


class MergeGroups:
    """Union-find over map ids (see coop_slam.ids) with, for each map, ``T_root_map``: the map in
    its group's frame. It starts with the robots' first maps (map id = robot id)."""

    def __init__(self, map_ids=()):
        self._parent: dict[int, int] = {}
        self._T_root_map: dict[int, np.ndarray] = {}
        for mid in map_ids:
            self.add_map(mid)

    def add_map(self, map_id: MapId) -> None:
        if map_id not in self._parent:
            self._parent[map_id] = map_id
            self._T_root_map[map_id] = np.eye(4)

    def _check(self, map_id: int) -> None:
        if map_id not in self._parent:
            raise GroupError(f"robot {map_id} is unknown to the team map (known: {self.robots})")

    @property
    def robots(self) -> list[int]:
        return sorted(self._parent)

    def root(self, map_id: int) -> int:
        self._check(map_id)
        # Groups are re-rooted eagerly in merge(), so every robot points at its root directly.
        return self._parent[map_id]

    def same_group(self, a: int, b: int) -> bool:
        return self.root(a) == self.root(b)

    def members(self, map_id: int) -> list[int]:
        r = self.root(map_id)
        return sorted(k for k, p in self._parent.items() if p == r)

    def groups(self) -> list[list[int]]:
        roots = sorted({p for p in self._parent.values()})
        return [self.members(r) for r in roots]

    def T_root_map(self, map_id: int) -> np.ndarray:
        """Robot's map expressed in its group's frame (identity for a group root)."""
        self._check(map_id)
        return self._T_root_map[map_id].copy()

    def T_mapA_mapB(self, a: int, b: int) -> np.ndarray:
        """Current transform between two robots' maps; they must be in one group."""
        if not self.same_group(a, b):
            raise GroupError(f"robots {a} and {b} are not merged")
        return invert(self._T_root_map[a]) @ self._T_root_map[b]

    def merge(self, a: int, b: int, T_mapA_mapB: np.ndarray) -> list[int]:
        """Join b's group to a's with the given constraint; returns the merged group's members.

        Merging robots already in one group is refused (that is a loop closure, not a merge).
        """
        try:
            T_mapA_mapB = check_se3(T_mapA_mapB, "T_mapA_mapB")
        except GeometryError as exc:
            raise GroupError(f"merge of robots {a} and {b}: {exc}") from None
        ra, rb = self.root(a), self.root(b)
        if ra == rb:
            raise GroupError(f"robots {a} and {b} are already in one group")
        # T_ra_rb: b's group frame expressed in a's group frame.
        T_ra_rb = self._T_root_map[a] @ T_mapA_mapB @ invert(self._T_root_map[b])
        new_root, old_root = (ra, rb) if ra < rb else (rb, ra)
        T_new_old = T_ra_rb if new_root == ra else invert(T_ra_rb)
        for rid, parent in list(self._parent.items()):
            if parent == old_root:
                self._parent[rid] = new_root
                self._T_root_map[rid] = T_new_old @ self._T_root_map[rid]
        return self.members(new_root)

    def set_T_root_map(self, map_id: int, T_root_map: np.ndarray) -> None:
        """Replace a robot's transform after global optimization (group membership unchanged)."""
        self._check(map_id)
        try:
            self._T_root_map[map_id] = check_se3(T_root_map, f"T_root_map of robot {map_id}")
        except GeometryError as exc:
            raise GroupError(str(exc)) from None
