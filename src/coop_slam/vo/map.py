"""Keyframes and map points of one robot's map segment.

Map points live in growable numpy arrays indexed by their id (ids are positive, unique per robot
and increasing, as keyframe messages require), so projection, culling and statistics are array
operations. Each point also has a small ``{keyframe_id: keypoint_index}`` dict of observations; each
keyframe's ``map_point_ids`` is the inverse relation. ``check_consistency`` verifies that the two
agree (no dangling references), which local mapping and keyframe culling must preserve.

The map is not thread-safe by itself: the owner (``VisualOdometry``) holds ``Map.lock`` around every
access from the tracking thread and the local-mapping thread.
"""

from __future__ import annotations

import itertools
import threading
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np

from ..descriptors import most_distinctive
from .dense_depth import resolved


@dataclass
class MapKeyframe:
    """A keyframe of the client's own map (its pose, keypoints and observed map points); what it
    sends the server is a :class:`coop_slam.wire.record.KeyframeRecord` made from it
    (:mod:`coop_slam.uplink.records`). N keypoints, M observed map points."""

    keyframe_id: int
    stamp_s: float
    map_segment: int
    T_map_cam: np.ndarray  # (4, 4) camera optical frame in the robot's map frame
    uv_px: np.ndarray  # (N, 2) float32 keypoint position at level 0 [px]
    size_px: np.ndarray  # (N,) float32 keypoint diameter [px]
    angle_deg: np.ndarray  # (N,) float32 OpenCV orientation, -1 = none
    octaves: np.ndarray  # (N,) uint8 pyramid level
    descriptors: np.ndarray  # (N, 32) uint8 ORB descriptors
    depths_m: np.ndarray  # (N,) float32 depth along the optical axis [m], 0 = none
    map_point_ids: np.ndarray  # (N,) uint32, 0 = none
    covisible_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    covisible_weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))
    # (M, 3) float32 positions of the observed map points in the map frame, in the order of the
    # non-zero map_point_ids. Filled in the snapshots handed out in events; empty in the live map.
    map_points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    # The frame's depth image for the dense map (vo.dense_depth); pending in the live map until
    # the first snapshot
    depth_image: bytes | Future = b""
    # Internal: the keypoints as FrameFeatures (KD-tree for projection search); not in snapshots.
    features: object = field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.uv_px)

    def keypoints_flat(self) -> np.ndarray:
        """(4N,) float32 ``u, v, size, angle`` per keypoint (a keyframe record's keypoints)."""
        return (
            np.column_stack([self.uv_px, self.size_px, self.angle_deg]).astype(np.float32).ravel()
        )

    def covisibility(self) -> dict[int, int]:
        return {int(k): int(w) for k, w in zip(self.covisible_ids, self.covisible_weights)}


class MapPoints:
    """Struct-of-arrays store of map points, indexed by id (slot 0 unused: id 0 means "none")."""

    def __init__(self, capacity: int = 4096):
        self._alloc(capacity)
        self.obs: dict[int, dict[int, int]] = {}
        self.next_id = 1

    def _alloc(self, cap: int) -> None:
        old = getattr(self, "xyz", None)
        arrays = {
            "xyz": np.zeros((cap, 3)),
            "desc": np.zeros((cap, 32), np.uint8),
            "angle": np.full(cap, -1.0, np.float32),
            "normal": np.zeros((cap, 3)),
            "max_dist": np.zeros(cap),
            "visible": np.zeros(cap, np.int32),
            "found": np.zeros(cap, np.int32),
            "created_kf_seq": np.zeros(cap, np.int64),
            "alive": np.zeros(cap, bool),
        }
        for name, arr in arrays.items():
            if old is not None:
                prev = getattr(self, name)
                arr[: len(prev)] = prev
            setattr(self, name, arr)

    def add(self, xyz, desc, angle, normal, max_dist, kf_seq: int) -> np.ndarray:
        n = len(xyz)
        ids = np.arange(self.next_id, self.next_id + n)
        if self.next_id + n > len(self.xyz):
            self._alloc(max(2 * len(self.xyz), self.next_id + n + 1))
        self.next_id += n
        self.xyz[ids] = xyz
        self.desc[ids] = desc
        self.angle[ids] = angle
        self.normal[ids] = normal
        self.max_dist[ids] = max_dist
        self.visible[ids] = 1
        self.found[ids] = 1
        self.created_kf_seq[ids] = kf_seq
        self.alive[ids] = True
        for i in ids:
            self.obs[int(i)] = {}
        return ids

    def is_alive(self, ids: np.ndarray) -> np.ndarray:
        ids = np.asarray(ids, dtype=np.int64)
        ok = (ids > 0) & (ids < self.next_id)
        out = np.zeros(len(ids), bool)
        out[ok] = self.alive[ids[ok]]
        return out

    def alive_ids(self) -> np.ndarray:
        return np.flatnonzero(self.alive[: self.next_id])

    def kill(self, pid: int) -> None:
        self.alive[pid] = False
        self.obs.pop(pid, None)


class Map:
    """Keyframes and map points of one map segment, with covisibility."""

    def __init__(self, segment: int, first_point_id: int = 1):
        self.segment = segment
        self.keyframes: dict[int, MapKeyframe] = {}
        self.points = MapPoints()
        self.points.next_id = first_point_id
        self.first_keyframe_id = 0
        self.kf_seq = 0  # keyframes inserted so far (creation clock of map points)
        # Incremented when the map is moved as a whole (server corrections): a local BA computed
        # on the poses before is stale and must not be applied.
        self.epoch = 0
        self.lock = threading.RLock()

    # --- keyframes ------------------------------------------------------------------------------
    def add_keyframe(self, kf: MapKeyframe) -> None:
        if not self.keyframes:
            self.first_keyframe_id = kf.keyframe_id
        self.keyframes[kf.keyframe_id] = kf
        self.kf_seq += 1
        ids = kf.map_point_ids
        for idx in np.flatnonzero(ids):
            self.points.obs[int(ids[idx])][kf.keyframe_id] = int(idx)

    def remove_keyframe(self, kf_id: int) -> list[int]:
        """Remove a keyframe and its observations; returns the ids of keyframes whose covisibility
        changed. Points left without observations are removed."""
        kf = self.keyframes.pop(kf_id)
        neighbours = [int(k) for k in kf.covisible_ids if int(k) in self.keyframes]
        for idx in np.flatnonzero(kf.map_point_ids):
            pid = int(kf.map_point_ids[idx])
            obs = self.points.obs.get(pid)
            if obs is None:
                continue
            obs.pop(kf_id, None)
            if not obs:
                self.points.kill(pid)
        for k in neighbours:
            self._set_edge(k, kf_id, 0)
        return neighbours

    def update_covisibility(self, kf_id: int, propagate: bool = True) -> None:
        """Recompute a keyframe's covisibility from its points' observations (ORB-SLAM's
        UpdateConnections); with ``propagate`` also set the reverse edge in each neighbour."""
        kf = self.keyframes[kf_id]
        obs = self.points.obs
        others = [k for p in kf.map_point_ids[kf.map_point_ids > 0].tolist() for k in obs[p]]
        ids, counts = np.unique(np.asarray(others, dtype=np.int64), return_counts=True)
        keep = (ids != kf_id) & np.isin(ids, list(self.keyframes))
        ids, counts = ids[keep], counts[keep]
        order = np.lexsort((ids, -counts))
        old = set(kf.covisible_ids.tolist())
        kf.covisible_ids = ids[order].astype(np.uint32)
        kf.covisible_weights = np.minimum(counts[order], 65535).astype(np.uint16)
        if propagate:
            for k, w in zip(kf.covisible_ids.tolist(), kf.covisible_weights.tolist()):
                self._set_edge(k, kf_id, w)
            for k in old - set(kf.covisible_ids.tolist()):
                self._set_edge(k, kf_id, 0)

    def _set_edge(self, kf_id: int, other: int, weight: int) -> None:
        """Set (weight > 0) or drop the covisibility edge kf_id -> other, keeping the order (by
        weight, descending; a changed edge goes after the others of its weight)."""
        kf = self.keyframes.get(kf_id)
        if kf is None:
            return
        # Python lists: a keyframe has tens of edges, and numpy's per-call cost made a new
        # keyframe's edges (one call per neighbour) cost ~2.5 ms of the tracking thread.
        ids, w = kf.covisible_ids.tolist(), kf.covisible_weights.tolist()
        if other in ids:
            at = ids.index(other)
            if weight > 0 and w[at] == weight:
                return
            del ids[at], w[at]
        elif weight <= 0:
            return
        if weight > 0:
            pos = 0
            while pos < len(w) and w[pos] >= weight:
                pos += 1
            ids.insert(pos, other)
            w.insert(pos, min(weight, 65535))
        kf.covisible_ids = np.array(ids, dtype=np.uint32)
        kf.covisible_weights = np.array(w, dtype=np.uint16)

    def observation_table(self, pids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat (row, keyframe_id, keypoint_idx) arrays of all observations of ``pids`` (row = index
        into pids), for vectorized statistics."""
        obs = self.points.obs
        # fromiter over the dicts' keys and values rather than tuples: this runs on every keyframe
        # with the map lock held (docs/tuning.md).
        dicts = [obs[p] for p in np.asarray(pids, dtype=np.int64).tolist()]
        counts = np.fromiter(map(len, dicts), np.int64, len(dicts))
        n = int(counts.sum())
        kf_ids = np.fromiter(itertools.chain.from_iterable(dicts), np.int64, n)
        idx = np.fromiter(itertools.chain.from_iterable([d.values() for d in dicts]), np.int64, n)
        return np.repeat(np.arange(len(dicts), dtype=np.int64), counts), kf_ids, idx

    def gather(self, kf_ids: np.ndarray, idx: np.ndarray, attr: str) -> np.ndarray:
        """``keyframes[kf_ids[j]].<attr>[idx[j]]`` for all j, one fancy index per keyframe (the
        rows grouped by one sort: a mask per keyframe costs keyframes x rows)."""
        kf_ids = np.asarray(kf_ids)
        if len(kf_ids) == 0:
            return np.zeros(0)
        order = np.argsort(kf_ids, kind="stable")
        sorted_ids = kf_ids[order]
        starts = np.flatnonzero(np.r_[True, sorted_ids[1:] != sorted_ids[:-1]])
        first = getattr(self.keyframes[int(sorted_ids[0])], attr)
        out = np.empty((len(kf_ids),) + first.shape[1:], dtype=first.dtype)
        for a, b in zip(starts.tolist(), np.r_[starts[1:], len(order)].tolist()):
            rows = order[a:b]
            out[rows] = getattr(self.keyframes[int(sorted_ids[a])], attr)[idx[rows]]
        return out

    def best_covisible(self, kf_id: int, n: int, min_weight: int = 1) -> list[int]:
        kf = self.keyframes.get(kf_id)
        if kf is None:
            return []
        out = []
        for k, w in zip(kf.covisible_ids, kf.covisible_weights):
            if w >= min_weight and int(k) in self.keyframes:
                out.append(int(k))
                if len(out) >= n:
                    break
        return out

    # --- observations -----------------------------------------------------------------------------
    def add_observation(self, pid: int, kf_id: int, idx: int) -> None:
        self.keyframes[kf_id].map_point_ids[idx] = pid
        self.points.obs[pid][kf_id] = idx

    def erase_observation(self, pid: int, kf_id: int) -> None:
        obs = self.points.obs.get(pid)
        if obs is None or kf_id not in obs:
            return
        idx = obs.pop(kf_id)
        kf = self.keyframes.get(kf_id)
        if kf is not None and kf.map_point_ids[idx] == pid:
            kf.map_point_ids[idx] = 0
        if not obs:
            self.points.kill(pid)

    def remove_point(self, pid: int) -> None:
        for kf_id, idx in list(self.points.obs.get(pid, {}).items()):
            kf = self.keyframes.get(kf_id)
            if kf is not None and kf.map_point_ids[idx] == pid:
                kf.map_point_ids[idx] = 0
        self.points.kill(pid)

    def replace_point(self, old: int, new: int) -> None:
        """Merge point ``old`` into ``new`` (fusion of duplicates)."""
        if old == new or not self.points.alive[old] or not self.points.alive[new]:
            return
        new_obs = self.points.obs[new]
        for kf_id, idx in self.points.obs[old].items():
            kf = self.keyframes.get(kf_id)
            if kf is None:
                continue
            if kf_id in new_obs:
                kf.map_point_ids[idx] = 0  # the keyframe already sees the survivor elsewhere
            else:
                kf.map_point_ids[idx] = new
                new_obs[kf_id] = idx
        self.points.visible[new] += self.points.visible[old]
        self.points.found[new] += self.points.found[old]
        self.points.kill(old)

    # --- statistics -------------------------------------------------------------------------------
    def update_point_stats(self, pids, scales: np.ndarray, max_obs: int = 8) -> None:
        """Mean viewing direction, scale-invariance distance and most distinctive descriptor (the
        one with the least median Hamming distance to the others), from up to ``max_obs`` newest
        observations of each point."""
        pts = self.points
        pids = np.asarray([int(p) for p in pids], dtype=np.int64)
        pids = pids[pts.is_alive(pids)] if len(pids) else pids
        if len(pids) == 0:
            return
        n = len(pids)
        row, kf_ids, idx = self.observation_table(pids)
        # Newest observations first within each point; keep max_obs of them.
        order = np.lexsort((-kf_ids, row))
        row, kf_ids, idx = row[order], kf_ids[order], idx[order]
        start = np.r_[0, np.flatnonzero(np.diff(row)) + 1]
        rank = np.arange(len(row)) - np.repeat(start, np.diff(np.r_[start, len(row)]))
        keep = rank < max_obs
        row, kf_ids, idx, rank = row[keep], kf_ids[keep], idx[keep], rank[keep]
        uniq, inv = np.unique(kf_ids, return_inverse=True)
        centres = np.array([self.keyframes[int(k)].T_map_cam[:3, 3] for k in uniq])[inv]
        ray = pts.xyz[pids[row]] - centres
        dist = np.linalg.norm(ray, axis=1)
        normals = np.zeros((n, 3))
        np.add.at(normals, row, ray / np.maximum(dist, 1e-9)[:, None])
        norm = np.linalg.norm(normals, axis=1, keepdims=True)
        octave = self.gather(kf_ids, idx, "octaves").astype(int)
        newest = rank == 0
        max_dist = pts.max_dist[pids].copy()
        max_dist[row[newest]] = dist[newest] * scales[octave[newest]]
        descs = np.zeros((n, max_obs, 32), np.uint8)
        angles = np.full((n, max_obs), -1.0, np.float32)
        valid = np.zeros((n, max_obs), bool)
        descs[row, rank] = self.gather(kf_ids, idx, "descriptors")
        angles[row, rank] = self.gather(kf_ids, idx, "angle_deg")
        valid[row, rank] = True
        best = most_distinctive(descs.view(np.uint64), valid)  # compiled, without Python's lock
        has = valid.any(1)
        pts.normal[pids[has]] = normals[has] / np.maximum(norm[has], 1e-12)
        pts.max_dist[pids] = max_dist
        pts.desc[pids[has]] = descs[np.arange(n), best][has]
        pts.angle[pids[has]] = angles[np.arange(n), best][has]

    # --- snapshots and checks ---------------------------------------------------------------------
    def snapshot(self, kf_id: int) -> MapKeyframe:
        """Deep copy of a keyframe with ``map_points_xyz`` filled in (for events)."""
        kf = self.keyframes[kf_id]
        ids = kf.map_point_ids
        nz = ids[ids > 0].astype(np.int64)
        kf.depth_image = resolved(kf.depth_image)
        return replace(
            kf,
            T_map_cam=kf.T_map_cam.copy(),
            uv_px=kf.uv_px.copy(),
            size_px=kf.size_px.copy(),
            angle_deg=kf.angle_deg.copy(),
            octaves=kf.octaves.copy(),
            descriptors=kf.descriptors.copy(),
            depths_m=kf.depths_m.copy(),
            map_point_ids=ids.copy(),
            covisible_ids=kf.covisible_ids.copy(),
            covisible_weights=kf.covisible_weights.copy(),
            map_points_xyz=self.points.xyz[nz].astype(np.float32),
            features=None,
        )

    def check_consistency(self) -> list[str]:
        """Problems in the keyframe <-> map point relation (empty list = consistent)."""
        problems = []
        pts = self.points
        for kf_id, kf in self.keyframes.items():
            for idx in np.flatnonzero(kf.map_point_ids):
                pid = int(kf.map_point_ids[idx])
                if pid >= pts.next_id or not pts.alive[pid]:
                    problems.append(f"keyframe {kf_id} kp {idx} -> removed point {pid}")
                elif pts.obs[pid].get(kf_id) != idx:
                    problems.append(
                        f"keyframe {kf_id} kp {idx} -> point {pid} without the observation"
                    )
            if len(np.unique(kf.map_point_ids[kf.map_point_ids > 0])) != int(
                (kf.map_point_ids > 0).sum()
            ):
                problems.append(f"keyframe {kf_id} observes a point twice")
        for pid in pts.alive_ids():
            obs = pts.obs.get(int(pid))
            if not obs:
                problems.append(f"point {pid} alive without observations")
                continue
            for kf_id, idx in obs.items():
                kf = self.keyframes.get(kf_id)
                if kf is None:
                    problems.append(f"point {pid} observed by removed keyframe {kf_id}")
                elif kf.map_point_ids[idx] != pid:
                    problems.append(
                        f"point {pid} obs ({kf_id}, {idx}) not mirrored by the keyframe"
                    )
        return problems
