"""New map points of a monocular keyframe from two views: the matching and geometry of ORB-SLAM's
CreateNewMapPoints and SearchForTriangulation, without the map.

:class:`~coop_slam.vo.local_mapping.LocalMapper` copies what it needs of each keyframe under the
map lock (:func:`triangulation_view`), finds the pairs that triangulate outside it
(:func:`triangulation_pairs`) and adds the points under the lock again.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..descriptors import hamming_rows
from ..geometry import invert, transform_points
from .config import VoConfig
from .initialization import fundamental_from_pose
from .map import Map
from .matching import rotation_consistent


def triangulation_view(vmap: Map, kf_id: int) -> dict:
    """What triangulation needs of one keyframe (copies; map lock held): its pose, free
    keypoints and median scene depth."""
    kf = vmap.keyframes[kf_id]
    free = np.flatnonzero(kf.map_point_ids == 0)
    pids = kf.map_point_ids[kf.map_point_ids > 0].astype(np.int64)
    pids = pids[vmap.points.is_alive(pids)]
    T_cam_map = invert(kf.T_map_cam)
    z = transform_points(T_cam_map, vmap.points.xyz[pids])[:, 2] if len(pids) else []
    return {
        "T_map_cam": kf.T_map_cam.copy(),
        "T_cam_map": T_cam_map,
        "idx": free,
        "uv": kf.uv_px[free].astype(float),
        "octave": kf.octaves[free].astype(int),
        "desc": kf.descriptors[free],
        "angle": kf.angle_deg[free],
        "median_depth": float(np.median(z)) if len(z) else float("nan"),
    }


def triangulation_pairs(a: dict, b: dict, config: VoConfig, K: np.ndarray, scales: np.ndarray):
    """(keypoint indices in keyframe a, in keyframe b, map points (M, 3)) of the free keypoints
    of two keyframes that match and triangulate, or None (ORB-SLAM's SearchForTriangulation and
    the checks of CreateNewMapPoints). ``a`` and ``b`` come from :func:`triangulation_view`,
    ``scales`` are the pyramid's level scales.

    Skipped when the baseline is below ``triangulation_min_baseline_ratio`` of b's median
    scene depth. Candidate pairs lie within the 95 % gate (1 dof) of each other's epipolar
    line and not next to b's epipole; the best descriptor (Hamming within
    ``triangulation_max_descriptor_distance``, ratio test against the next candidate) wins,
    each keypoint of b used once, rotation-histogram consistent. A match becomes a point when
    its rays meet at ``triangulation_min_parallax_deg`` or more, the DLT point lies in front
    of both cameras, reprojects within the 2-dof chi-square gate at the keypoints' octave in
    both, and its distances to the two cameras agree with the keypoints' pyramid levels."""
    if len(a["idx"]) == 0 or len(b["idx"]) == 0:
        return None
    c_a, c_b = a["T_map_cam"][:3, 3], b["T_map_cam"][:3, 3]
    baseline = float(np.linalg.norm(c_b - c_a))
    if not baseline > config.triangulation.min_baseline_ratio * b["median_depth"]:
        return None  # also when b has no points (NaN median)
    x_a = np.column_stack([a["uv"], np.ones(len(a["uv"]))])
    x_b = np.column_stack([b["uv"], np.ones(len(b["uv"]))])
    ia, ib = _epipolar_candidates(a, b, x_a, x_b, K, scales)
    if len(ia) == 0:
        return None
    ia, ib = _best_matches(a, b, ia, ib, config)
    if len(ia) == 0:
        return None
    ia, ib = _with_parallax(a, b, ia, ib, x_a, x_b, K, config)
    if len(ia) == 0:
        return None
    xyz, good = _triangulate(a, b, ia, ib, K, scales, config)
    if not good.any():
        return None
    return a["idx"][ia[good]], b["idx"][ib[good]], xyz[good]


def _epipolar_candidates(
    a: dict, b: dict, x_a: np.ndarray, x_b: np.ndarray, K: np.ndarray, scales: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint pairs (rows of a, rows of b) near each other's epipolar line, away from b's
    epipole."""
    c_a = a["T_map_cam"][:3, 3]
    T_ba = b["T_cam_map"] @ a["T_map_cam"]
    F = fundamental_from_pose(T_ba[:3, :3], T_ba[:3, 3], K)  # x_b^T F x_a = 0
    lines = x_a @ F.T  # epipolar line in b of each keypoint of a
    num = lines @ x_b.T  # (Na, Nb)
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = num**2 / (lines[:, :1] ** 2 + lines[:, 1:2] ** 2)
    sigma2_b = scales[b["octave"]] ** 2
    ok = d2 < 3.841 * sigma2_b[None, :]
    # Not next to the epipole (b's image of a's centre): every line passes through it.
    ep = K @ transform_points(b["T_cam_map"], c_a[None])[0]
    if ep[2] > 0:
        e2 = ((b["uv"] - ep[:2] / ep[2]) ** 2).sum(1)
        ok &= (e2 >= 100.0 * scales[b["octave"]])[None, :]
    return np.nonzero(ok)


def _best_matches(
    a: dict, b: dict, ia: np.ndarray, ib: np.ndarray, config: VoConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The candidate pairs that win on descriptor distance: close enough, clearly better than a's
    next candidate, the closest to their keypoint of b, rotation consistent (empty if none)."""
    dist = hamming_rows(a["desc"][ia], b["desc"][ib])
    keep = dist <= config.triangulation.max_descriptor_distance
    ia, ib, dist = ia[keep], ib[keep], dist[keep]
    if len(ia) == 0:
        return ia, ib
    # Best and second best candidate of each keypoint of a; ratio test between them.
    order = np.lexsort((dist, ia))
    ia, ib, dist = ia[order], ib[order], dist[order]
    first = np.r_[True, ia[1:] != ia[:-1]]
    best = np.flatnonzero(first)
    has_second = np.r_[~first[1:], False][best]
    second = np.where(has_second, dist[np.minimum(best + 1, len(dist) - 1)], 10**6)
    best = best[~(dist[best] > config.triangulation.ratio * second)]
    if len(best) == 0:
        return ia[best], ib[best]
    ia, ib, dist = ia[best], ib[best], dist[best]
    # Each keypoint of b once: the closest descriptor wins.
    order = np.lexsort((dist, ib))
    ia, ib = ia[order], ib[order]
    first = np.r_[True, ib[1:] != ib[:-1]]
    ia, ib = ia[first], ib[first]
    if len(ia) > 10:
        keep = rotation_consistent(a["angle"][ia], b["angle"][ib])
        ia, ib = ia[keep], ib[keep]
    return ia, ib


def _with_parallax(
    a: dict,
    b: dict,
    ia: np.ndarray,
    ib: np.ndarray,
    x_a: np.ndarray,
    x_b: np.ndarray,
    K: np.ndarray,
    config: VoConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs whose keypoint rays (map frame) meet at ``triangulation_min_parallax_deg`` or
    more."""
    K_inv = np.linalg.inv(K)
    ray_a = (x_a[ia] @ K_inv.T) @ a["T_map_cam"][:3, :3].T
    ray_b = (x_b[ib] @ K_inv.T) @ b["T_map_cam"][:3, :3].T
    cos_par = (ray_a * ray_b).sum(1) / (
        np.linalg.norm(ray_a, axis=1) * np.linalg.norm(ray_b, axis=1)
    )
    keep = (cos_par > 0) & (cos_par < np.cos(np.radians(config.triangulation.min_parallax_deg)))
    return ia[keep], ib[keep]


def _triangulate(
    a: dict,
    b: dict,
    ia: np.ndarray,
    ib: np.ndarray,
    K: np.ndarray,
    scales: np.ndarray,
    config: VoConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(DLT point of every pair (M, 3), whether it passes the checks (M,)): in front of both
    cameras, reprojected within the chi-square gate, at distances the octaves agree with."""
    c_a, c_b = a["T_map_cam"][:3, 3], b["T_map_cam"][:3, 3]
    P_a = K @ a["T_cam_map"][:3]
    P_b = K @ b["T_cam_map"][:3]
    X = cv2.triangulatePoints(P_a, P_b, a["uv"][ia].T.copy(), b["uv"][ib].T.copy())
    with np.errstate(divide="ignore", invalid="ignore"):
        xyz = (X[:3] / X[3]).T
    good = np.isfinite(xyz).all(1)
    xyz = np.where(good[:, None], xyz, 0.0)
    for view, idx in ((a, ia), (b, ib)):
        pc = transform_points(view["T_cam_map"], xyz)
        front = pc[:, 2] > 0
        z = np.where(front, pc[:, 2], 1.0)
        uv = pc[:, :2] / z[:, None] * [K[0, 0], K[1, 1]] + K[:2, 2]
        err2 = ((uv - view["uv"][idx]) ** 2).sum(1) / scales[view["octave"][idx]] ** 2
        good &= front & (err2 <= config.tracking.chi2_mono)
    # Scale consistency: the distance ratio to the two cameras matches the octave ratio.
    dist_a = np.linalg.norm(xyz - c_a, axis=1)
    dist_b = np.linalg.norm(xyz - c_b, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio_dist = dist_b / dist_a
    ratio_oct = scales[a["octave"][ia]] / scales[b["octave"][ib]]
    factor = 1.5 * config.features.scale_factor
    good &= (ratio_dist * factor >= ratio_oct) & (ratio_dist <= ratio_oct * factor)
    return xyz, good
