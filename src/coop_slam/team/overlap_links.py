"""Links where merged maps overlap: keyframes of different robots that the team map's current
estimate says see the same scene, checked by a guided registration.

Two uses, one mechanism:

- the **welding window** of a merge (ORB-SLAM's term): right after two groups are joined on one
  verified keyframe pair, the covisible neighbours of both matched keyframes are registered
  against the other side's keyframes that see the same scene, and every pair that holds goes
  into the pose graph with the first. The map transform then rests on a neighbourhood on each side,
  estimated jointly by the optimization, not on one pair's registration error;
- **links after a merge**: a new keyframe of a merged robot is registered against the keyframe of
  another robot of its group that sees most of the same scene. BoW retrieval misses most such
  pairs between robots: two robots rarely see a place from the same direction at the same
  distance, and the words of an ORB descriptor change with both.

The prediction picks the pair and seeds the registration (3D-3D with the predicted pose as one more
hypothesis, then descriptor ICP and BA; a similarity, unseeded, for a monocular keyframe); the
registration, not the prediction, is the constraint. Where ORB finds no match and both keyframes
brought depth images, the pair is registered on its depth instead (point-to-plane ICP from the
prediction, :mod:`coop_slam.registration.depth_icp`): views far apart, plain walls.
A result far from the prediction is refused: the estimate it contradicts rests on verified merges.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from ..config import require
from ..dense.depth_image import DepthImageError, decode
from ..dense.keyframe_points import points_grid
from ..geometry import invert, transform_error, transform_points
from ..ids import KeyframeKey
from ..registration.depth_icp import DepthIcpConfig, grid_normals, register_depth
from ..registration.relative_pose import RegistrationConfig, RelativePoseResult, estimate_3d3d
from .keyframe_store import KeyframeStore
from .map_scale import register_pair
from .results import TYPE_OVERLAP, Verified

log = logging.getLogger(__name__)

# Around a merge, partners may look this much further away from each other than the matched pair
# does [deg]: the window's keyframes turn a little against the pair's.
WELD_EXTRA_ANGLE_DEG = 20.0
# A merge's sweep scores this many b-side keyframes per pair it wants.
SWEEP_SAMPLES_PER_PAIR = 3


@dataclass
class OverlapLinkConfig:
    """Links between merged robots where the team map says their views overlap, and a merge's
    welding window."""

    enabled: bool = True  # link merged robots wherever the team map says their views overlap
    # A pair is tried when this share of one keyframe's 3D points would be seen by the other
    # (in front, inside its image, nearer than its own farthest point) ...
    min_shared: float = 0.3
    # ... from directions at most this far apart: beyond it ORB descriptors rarely match [deg].
    max_view_angle_deg: float = 40.0
    # Keyframes on each side of a merge's matched pair (their covisible neighbours, most covisible
    # first) registered against the other side right after the merge; 0 = no welding.
    weld_window: int = 3
    # Links a merge also looks for across the whole overlap of the two sides, per pair of maps
    # (see sweep); 0 = none. A late merge of maps whose views ORB rarely matches has only these
    # to be held by (issue #48's note).
    sweep_pairs: int = 16
    # A guided registration further than this from the prediction is refused [m], [deg].
    gate_trans_m: float = 0.15
    gate_rot_deg: float = 5.0
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    # Where ORB does not match and both keyframes brought depth images: register them on their
    # depth (coop_slam.registration.depth_icp), up to this range [m]; 0 = never.
    depth_max_m: float = 4.0
    # ... and pairs whose views are this far apart are tried when both have depth images [deg]
    # (geometry overlaps where descriptors no longer match)
    depth_max_view_angle_deg: float = 75.0
    depth_icp: DepthIcpConfig = field(default_factory=DepthIcpConfig)

    def validate(self) -> None:
        require(0 < self.min_shared <= 1, "links.min_shared must be in (0, 1]")
        require(0 < self.max_view_angle_deg <= 180, "links.max_view_angle_deg must be in (0, 180]")
        require(self.weld_window >= 0, "links.weld_window must be >= 0")
        require(self.sweep_pairs >= 0, "links.sweep_pairs must be >= 0")
        require(self.gate_trans_m > 0, "links.gate_trans_m must be > 0")
        require(self.gate_rot_deg > 0, "links.gate_rot_deg must be > 0")
        self.registration.validate()
        require(self.depth_max_m >= 0, "links.depth_max_m must be >= 0 [m] (0 = no depth links)")
        require(
            0 < self.depth_max_view_angle_deg <= 180,
            "links.depth_max_view_angle_deg must be in (0, 180]",
        )
        self.depth_icp.validate()


def shared_view(
    points_b: np.ndarray, T_a_b: np.ndarray, K_a: np.ndarray, size_a: tuple, far_a_m: float
) -> float:
    """Share of keyframe b's 3D points ``points_b`` (its camera frame) that keyframe a, at
    ``T_a_b`` (b's camera in a's), would see: in front, inside its image (``size_a`` = width,
    height [px]) and nearer than ``far_a_m`` (a's own farthest point)."""
    if len(points_b) == 0:
        return 0.0
    p = transform_points(T_a_b, points_b)
    z = p[:, 2]
    front = z > 1e-3
    uv = (p[front, :2] / z[front, None]) @ K_a[:2, :2].T + K_a[:2, 2]
    inside = (
        (uv[:, 0] >= 0)
        & (uv[:, 0] < size_a[0])
        & (uv[:, 1] >= 0)
        & (uv[:, 1] < size_a[1])
        & (z[front] <= far_a_m)
    )
    return float(inside.sum()) / len(points_b)


class OverlapLinks:
    """Finds and verifies keyframe pairs of different robots whose views overlap (see module doc).

    ``T_group_cam(key)`` is a keyframe's pose in its group frame at the current estimate."""

    def __init__(
        self,
        config: OverlapLinkConfig,
        store: KeyframeStore,
        T_group_cam: Callable[[KeyframeKey], np.ndarray],
    ):
        self.config = config
        self.store = store
        self._T_group_cam = T_group_cam
        self.verifications = 0
        self.depth_verifications = 0  # pairs ORB could not register, tried on their depth

    def _points(self, key: KeyframeKey) -> np.ndarray:
        view = self.store.view(key)
        return view.points_cam[view.has_point]

    def view_angle_deg(self, key_a: KeyframeKey, key_b: KeyframeKey) -> float:
        """Angle between two keyframes' optical axes at the current estimate [deg]."""
        cos = float(self._T_group_cam(key_a)[:3, 2] @ self._T_group_cam(key_b)[:3, 2])
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    def best_partners(
        self,
        key_b: KeyframeKey,
        candidates: Iterable[KeyframeKey],
        n: int = 1,
        max_angle_deg: float | None = None,
    ) -> list[KeyframeKey]:
        """Up to ``n`` of ``candidates`` that see most of keyframe b's scene, best first (each at
        least ``min_shared``, both ways; optical axes within ``max_angle_deg``, default
        ``max_view_angle_deg``)."""
        cfg = self.config
        T_g_b = self._T_group_cam(key_b)
        points_b = self._points(key_b)
        rec_b = self.store.record(key_b)
        max_angle = cfg.max_view_angle_deg if max_angle_deg is None else max_angle_deg
        cos_max = np.cos(np.radians(min(max_angle, 180.0)))
        # Both with depth images: their depth may register where descriptors do not match.
        cos_depth = np.cos(np.radians(max(max_angle, cfg.depth_max_view_angle_deg)))
        depth_b = cfg.depth_max_m > 0 and len(rec_b.depth_image) > 0
        scored = []
        for key_a in candidates:
            T_g_a = self._T_group_cam(key_a)
            rec_a = self.store.record(key_a)
            # Optical axes apart by more than the angle: no descriptor would match anyway.
            cos = float(T_g_a[:3, 2] @ T_g_b[:3, 2])
            if cos < cos_max and not (cos >= cos_depth and depth_b and len(rec_a.depth_image)):
                continue
            T_a_b = invert(T_g_a) @ T_g_b
            points_a = self._points(key_a)
            if len(points_a) == 0:
                continue
            far_a = float(np.max(points_a[:, 2]))
            share = shared_view(
                points_b, T_a_b, rec_a.camera.K, (rec_a.camera.width, rec_a.camera.height), far_a
            )
            if share < cfg.min_shared:
                continue
            far_b = float(np.max(points_b[:, 2])) if len(points_b) else 0.0
            back = shared_view(
                points_a,
                invert(T_a_b),
                rec_b.camera.K,
                (rec_b.camera.width, rec_b.camera.height),
                far_b,
            )
            if back < cfg.min_shared:
                continue
            scored.append((min(share, back), key_a))
        scored.sort(key=lambda sk: -sk[0])
        return [k for _, k in scored[:n]]

    def verify(self, key_a: KeyframeKey, key_b: KeyframeKey, stamp_s: float) -> Verified | None:
        """Registration of the pair seeded with the predicted relative pose; the verified match, or
        None when it fails or lies further than the gate from the prediction."""
        cfg = self.config
        T_pred = invert(self._T_group_cam(key_a)) @ self._T_group_cam(key_b)
        self.verifications += 1
        res = register_pair(
            self.store, key_a, key_b, cfg.registration, estimate_3d3d, T_init=T_pred
        )
        if not res.accepted:
            log.debug("overlap link %s - %s: %s", key_a, key_b, res.reason)
            res = self._on_depth(key_a, key_b, T_pred)
            if res is None:
                return None
        dt, dr = transform_error(res.T_a_b, T_pred)
        if dt > cfg.gate_trans_m or dr > cfg.gate_rot_deg:
            log.info(
                "overlap link %s - %s refused: %.3f m / %.2f deg from the prediction",
                key_a,
                key_b,
                dt,
                dr,
            )
            return None
        return Verified(TYPE_OVERLAP, key_a, key_b, res, stamp_s)

    def _on_depth(
        self, key_a: KeyframeKey, key_b: KeyframeKey, T_pred
    ) -> RelativePoseResult | None:
        """The pair registered on the keyframes' depth images (None: one has none, or it fails)."""
        cfg = self.config
        rec_a, rec_b = self.store.record(key_a), self.store.record(key_b)
        if cfg.depth_max_m == 0 or not (len(rec_a.depth_image) and len(rec_b.depth_image)):
            return None
        try:
            grid_a, grid_b = (
                points_grid(decode(rec.depth_image.tobytes()), rec.camera, 0.1, cfg.depth_max_m)
                for rec in (rec_a, rec_b)
            )
        except DepthImageError as exc:
            log.warning("depth link %s - %s: %s", key_a, key_b, exc)
            return None
        points_a, normals_a = grid_normals(grid_a)
        icp = register_depth(
            points_a, normals_a, grid_b[np.isfinite(grid_b[..., 2])], T_pred, cfg.depth_icp
        )
        self.depth_verifications += 1
        if not icp.accepted:
            log.debug("depth link %s - %s: %s", key_a, key_b, icp.reason)
            return None
        return RelativePoseResult(
            True,
            "depth",
            icp.T_a_b,
            n_inliers=icp.n_pairs,
            rmse_3d_m=icp.rms_m,
            sigma_rot_deg=icp.sigma_rot_deg,
            sigma_trans_m=icp.sigma_trans_m,
        )

    def window(self, key: KeyframeKey) -> list[KeyframeKey]:
        """The keyframe's covisible neighbours (same robot, stored), most covisible first, up to
        ``weld_window``."""
        rec = self.store.record(key)
        order = np.argsort(-np.asarray(rec.covisible_weights, float), kind="stable")
        out = []
        for i in order:
            k = (key[0], int(rec.covisible_ids[i]))
            if k != key and k in self.store and len(out) < self.config.weld_window:
                out.append(k)
        return out

    def weld(
        self,
        key_a: KeyframeKey,
        key_b: KeyframeKey,
        robots_a: set[int],
        robots_b: set[int],
        stamp_s: float,
        tried: set | None = None,
    ) -> list[Verified]:
        """Verified pairs around a merge's matched keyframes: each matched keyframe and its
        window, against the other side's keyframe that sees most of its scene and has not been
        paired yet (the matched pair itself excluded); ``tried`` collects the pairs tried. Call
        after the merge's first constraint is in the estimate."""
        found: list[Verified] = []
        tried = set() if tried is None else tried
        tried.add((key_a, key_b))
        if self.config.weld_window == 0:
            return found
        # The matched pair shows what angle this scene's features match across (robots facing
        # each other match on the side walls).
        max_angle = max(
            self.config.max_view_angle_deg,
            self.view_angle_deg(key_a, key_b) + WELD_EXTRA_ANGLE_DEG,
        )
        for own, others in ((key_b, robots_a), (key_a, robots_b)):
            candidates = [k for k in self.store.keys() if k[0] in others]
            for k in [own] + self.window(own):
                for partner in self.best_partners(k, candidates, n=3, max_angle_deg=max_angle):
                    # Pairs are oriented as the merge: a-side first.
                    pair = (partner, k) if own == key_b else (k, partner)
                    if pair in tried:
                        continue
                    tried.add(pair)
                    v = self.verify(*pair, stamp_s)
                    if v is not None:
                        found.append(v)
                    break
        return found

    def sweep(
        self, robots_a: set[int], robots_b: set[int], stamp_s: float, tried: set
    ) -> list[Verified]:
        """Pairs across the whole overlap of two just-merged sides, not only around the matched
        keyframes, for every pair of maps across them (else the map nearest to most of the other
        side's keyframes would take every link): see :meth:`_sweep_pair`. A merge late in a run
        has no new keyframes after it to link by."""
        found: list[Verified] = []
        if self.config.sweep_pairs == 0:
            return found
        for map_a in sorted(robots_a):
            for map_b in sorted(robots_b):
                found += self._sweep_pair({map_a}, {map_b}, stamp_s, tried)
        return found

    def _sweep_pair(
        self, robots_a: set[int], robots_b: set[int], stamp_s: float, tried: set
    ) -> list[Verified]:
        """b-side keyframes spread evenly over its arrival order, each against the a-side
        keyframe that sees most of its scene, until ``sweep_pairs`` hold (at most twice as many
        tried)."""
        cfg = self.config
        found: list[Verified] = []
        keys_a = [k for k in self.store.keys() if k[0] in robots_a]
        keys_b = [k for k in self.store.keys() if k[0] in robots_b]
        # Evenly spread samples bound the cost (each scores every a-side keyframe).
        n = min(len(keys_b), SWEEP_SAMPLES_PER_PAIR * cfg.sweep_pairs)
        attempts = 0
        for i in np.linspace(0, len(keys_b) - 1, n).round().astype(int) if n else []:
            if len(found) >= cfg.sweep_pairs or attempts >= 2 * cfg.sweep_pairs:
                break
            key_b = keys_b[i]
            for key_a in self.best_partners(key_b, keys_a):
                if (key_a, key_b) in tried:
                    continue
                tried.add((key_a, key_b))
                attempts += 1
                v = self.verify(key_a, key_b, stamp_s)
                if v is not None:
                    found.append(v)
        log.info(
            "links across the overlap of robots %s and %s: %d of %d pairs tried hold",
            sorted(robots_a),
            sorted(robots_b),
            len(found),
            attempts,
        )
        return found
