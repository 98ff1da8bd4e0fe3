"""Ground-truth overlap events between robots, from the scenario's poses and the world geometry.

Evaluation measures merge latency against these events, so they are defined from what the cameras
could see, not from the SLAM output:

- ``rendezvous`` (per robot pair): first time both robots observe the same scene simultaneously;
- ``revisit`` (per ordered pair a -> b): first time robot b views a place robot a saw at least
  ``min_revisit_gap_s`` earlier;
- ``marker_sightings`` (per ordered pair): first time robot a's camera sees robot b's marker well
  enough to detect it (never for hand-held cameras: nobody carries a marker);
- ``first_overlap`` (per pair): the earliest of all the above, the first moment a merge is possible.

Visibility: points sampled on every static surface are visible in a frame when they are in the
image, within the depth range, not seen at a grazing angle and not hidden (checked against a
low-resolution depth rendering). Two frames share a point only if they look at it from similar
directions (ORB descriptors do not match across much larger viewpoint changes); directions are
binned by azimuth so all frame pairs reduce to one sparse matrix product.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import sparse

from ..camera import CameraModel
from ..errors import CoopSlamError
from ..geometry import invert, transform_points
from .bodies import body_faces
from .render import DEFAULT_CAMERA, NoiseConfig, Renderer
from .scenarios import Scenario
from .world import World


class OverlapError(CoopSlamError):
    """Overlap computation given inconsistent inputs (trajectories of different lengths, ...)."""


@dataclass
class OverlapConfig:
    rate_hz: float = 5.0  # visibility evaluated at this rate (event times are this precise)
    point_spacing_m: float = 0.25
    min_range_m: float = 0.3
    max_range_m: float = 6.0  # beyond this an RGB-D camera gives little to match
    max_incidence_deg: float = 75.0
    azimuth_bins: int = 16  # view directions within one bin (22.5 deg) always count as shared
    min_shared_points: int = 40
    min_shared_fraction: float = 0.2  # of the smaller visible set
    min_revisit_gap_s: float = 2.0
    depth_width_px: int = 160  # occlusion test resolution
    occlusion_tol_m: float = 0.05
    marker_max_range_m: float = 5.0
    marker_min_side_px: float = 20.0
    marker_max_angle_deg: float = 60.0

    def validate(self):
        if self.rate_hz <= 0 or self.azimuth_bins < 4 or self.depth_width_px < 16:
            raise OverlapError(
                "overlap rate_hz must be > 0, azimuth_bins >= 4, depth_width_px >= 16"
            )


@dataclass
class OverlapEvents:
    """Event lists (times are frame stamps in seconds, as in the sequences' rgb.txt)."""

    rendezvous: list[dict] = field(default_factory=list)  # {robots: [a, b], stamp_s}
    revisit: list[dict] = field(default_factory=list)  # {robot, of_robot, stamp_s, earlier_stamp_s}
    marker_sightings: list[dict] = field(default_factory=list)  # {observer, target, stamp_s}
    first_overlap: list[dict] = field(default_factory=list)  # {robots: [a, b], stamp_s, kind}

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> OverlapEvents:
        if not isinstance(data, dict):
            raise OverlapError(f"overlap events must be a mapping, got {type(data).__name__}")
        known = {"rendezvous", "revisit", "marker_sightings", "first_overlap"}
        return cls(**{k: list(v or []) for k, v in data.items() if k in known})

    def rendezvous_time(self, a: int, b: int) -> float | None:
        return _lookup(self.rendezvous, lambda e: sorted(e["robots"]) == sorted([a, b]))

    def revisit_time(self, of_robot: int, robot: int) -> float | None:
        return _lookup(self.revisit, lambda e: e["of_robot"] == of_robot and e["robot"] == robot)

    def sighting_time(self, observer: int, target: int) -> float | None:
        return _lookup(
            self.marker_sightings, lambda e: e["observer"] == observer and e["target"] == target
        )

    def first_overlap_time(self, a: int, b: int) -> float | None:
        return _lookup(self.first_overlap, lambda e: sorted(e["robots"]) == sorted([a, b]))


def _lookup(events, pred):
    times = [e["stamp_s"] for e in events if pred(e)]
    return min(times) if times else None


def _lowres_camera(camera: CameraModel, width: int) -> CameraModel:
    s = width / camera.width
    return CameraModel(
        width=width,
        height=max(1, round(camera.height * s)),
        fx=camera.fx * s,
        fy=camera.fy * s,
        cx=(camera.cx + 0.5) * s - 0.5,
        cy=(camera.cy + 0.5) * s - 0.5,
    )


class _Visibility:
    """Per-frame visibility of the world's sample points, and marker sightings."""

    def __init__(self, world: World, camera: CameraModel, cfg: OverlapConfig):
        self.cfg = cfg
        self.camera = camera
        self.points_world, self.normals_world = world.sample_points(cfg.point_spacing_m)
        self.low_camera = _lowres_camera(camera, cfg.depth_width_px)
        self.renderer = Renderer(world, self.low_camera, NoiseConfig(enabled=False))
        self.cos_incidence = math.cos(math.radians(cfg.max_incidence_deg))

    def frame(self, T_world_cam: np.ndarray):
        """(features (K,) int: point * bins + azimuth bin, depth_lowres) of one camera pose."""
        cfg, cam = self.cfg, self.camera
        depth = self.renderer.render_depth(T_world_cam)
        points_cam = transform_points(invert(T_world_cam), self.points_world)
        z = points_cam[:, 2]
        ok = (z > cfg.min_range_m) & (z < cfg.max_range_m)
        u = cam.fx * points_cam[:, 0] / np.where(ok, z, 1.0) + cam.cx
        v = cam.fy * points_cam[:, 1] / np.where(ok, z, 1.0) + cam.cy
        ok &= (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
        to_cam = T_world_cam[:3, 3] - self.points_world
        dist = np.linalg.norm(to_cam, axis=1)
        ok &= np.einsum("ij,ij->i", to_cam, self.normals_world) > self.cos_incidence * dist
        idx = np.flatnonzero(ok)
        lo = self.low_camera
        s = lo.width / cam.width
        ui = np.clip(np.round((u[idx] + 0.5) * s - 0.5).astype(int), 0, lo.width - 1)
        vi = np.clip(np.round((v[idx] + 0.5) * s - 0.5).astype(int), 0, lo.height - 1)
        d = depth[vi, ui]
        seen = (d > 0) & (z[idx] <= d * 1.02 + cfg.occlusion_tol_m)
        idx = idx[seen]
        azimuth = np.arctan2(to_cam[idx, 1], to_cam[idx, 0])
        bins = (
            np.floor((azimuth + math.pi) / (2 * math.pi) * cfg.azimuth_bins).astype(int)
            % cfg.azimuth_bins
        )
        return idx * cfg.azimuth_bins + bins, depth

    def sees_marker(self, T_world_cam, depth_low, corners_world: np.ndarray) -> bool:
        """Whether a marker with these world corners (4, 3) is detectable in this frame."""
        cfg, cam = self.cfg, self.camera
        c_cam = transform_points(invert(T_world_cam), corners_world)
        z = c_cam[:, 2]
        if z.min() < cfg.min_range_m or z.max() > cfg.marker_max_range_m:
            return False
        uv = np.stack(
            [cam.fx * c_cam[:, 0] / z + cam.cx, cam.fy * c_cam[:, 1] / z + cam.cy], axis=1
        )
        margin = 3.0
        if (
            uv.min() < margin
            or (uv[:, 0] > cam.width - 1 - margin).any()
            or (uv[:, 1] > cam.height - 1 - margin).any()
        ):
            return False
        sides = np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1)
        if sides.min() < cfg.marker_min_side_px:
            return False
        normal = np.cross(corners_world[1] - corners_world[0], corners_world[3] - corners_world[0])
        normal /= np.linalg.norm(normal)
        centre = corners_world.mean(axis=0)
        to_cam = T_world_cam[:3, 3] - centre
        # Marker texture's normal points into the body (u x v); the visible side is the opposite.
        if -normal @ to_cam < math.cos(math.radians(cfg.marker_max_angle_deg)) * np.linalg.norm(
            to_cam
        ):
            return False
        # Not hidden by the static world: test the centre and points just inside the corners.
        probes = np.vstack([centre, centre + 0.8 * (corners_world - centre)])
        p_cam = transform_points(invert(T_world_cam), probes)
        lo = self.low_camera
        ui = np.clip(
            np.round(lo.fx * p_cam[:, 0] / p_cam[:, 2] + lo.cx).astype(int), 0, lo.width - 1
        )
        vi = np.clip(
            np.round(lo.fy * p_cam[:, 1] / p_cam[:, 2] + lo.cy).astype(int), 0, lo.height - 1
        )
        d = depth_low[vi, ui]
        return bool(np.all((d == 0) | (p_cam[:, 2] <= d * 1.02 + cfg.occlusion_tol_m)))


def compute_overlap(
    scenario: Scenario,
    world: World,
    camera: CameraModel = DEFAULT_CAMERA,
    cfg: OverlapConfig | None = None,
) -> OverlapEvents:
    """Overlap events of all robot pairs of ``scenario`` (see the module docstring)."""
    cfg = cfg or OverlapConfig()
    cfg.validate()
    trajs = scenario.trajectories
    n_frames = {len(t.stamps_s) for t in trajs}
    if len(n_frames) != 1:
        raise OverlapError("all robots of a scenario must share their timestamps")
    stamps = trajs[0].stamps_s
    step = max(1, round(scenario.rate_hz / cfg.rate_hz))
    frames = np.arange(0, len(stamps), step)
    t_s = stamps[frames]
    vis = _Visibility(world, camera, cfg)
    seen, counts, sightings = _observations(scenario, vis, frames)
    wide = _widened(seen, len(vis.points_world) * cfg.azimuth_bins, cfg.azimuth_bins)
    ids = [t.robot_id for t in trajs]
    events = OverlapEvents(
        rendezvous=_rendezvous_events(ids, seen, wide, counts, t_s, cfg),
        revisit=_revisit_events(ids, seen, wide, counts, t_s, cfg),
        marker_sightings=[
            {"observer": obs, "target": tgt, "stamp_s": stamp}
            for (obs, tgt), stamp in sorted(sightings.items())
        ],
    )
    events.first_overlap = _first_overlaps(ids, events)
    return events


def _observations(scenario: Scenario, vis: _Visibility, frames: np.ndarray):
    """What each robot sees at ``frames``: robot id -> sparse (frames, features) matrix of the
    sample points in view (see :meth:`_Visibility.frame`), robot id -> their count per frame, and
    (observer, target) -> stamp of the observer's first sighting of the target's marker."""
    cfg = vis.cfg
    trajs = scenario.trajectories
    stamps = trajs[0].stamps_s
    n_features = len(vis.points_world) * cfg.azimuth_bins
    # Hand-held cameras have no robot body (and so no marker) for the others to see.
    faces = [
        f.marker_corners_base
        for f in body_faces(scenario.marker_size_m)
        if f.marker_corners_base is not None and not scenario.hand_held
    ]

    seen, counts, sightings = {}, {}, {}
    for a in trajs:
        rows, cols = [], []
        for r, k in enumerate(frames):
            T_world_cam = a.poses_se3[k] @ scenario.mount(a.robot_id)
            feats, depth_low = vis.frame(T_world_cam)
            rows.append(np.full(len(feats), r))
            cols.append(feats)
            for b in trajs:
                key = (a.robot_id, b.robot_id)
                if b is a or key in sightings:
                    continue
                for corners_base in faces:
                    if vis.sees_marker(
                        T_world_cam, depth_low, transform_points(b.poses_se3[k], corners_base)
                    ):
                        sightings[key] = float(stamps[k])
                        break
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        seen[a.robot_id] = sparse.csr_matrix(
            (np.ones(len(rows), np.float32), (rows, cols)), shape=(len(frames), n_features)
        )
        counts[a.robot_id] = np.bincount(rows, minlength=len(frames)).astype(float)
    return seen, counts, sightings


def _widened(seen: dict, n_features: int, nb: int) -> dict:
    """``seen`` (robot id -> (frames, features) matrix, ``nb`` view directions per point) with
    each view direction widened by a bin each way, as 0/1."""
    # Widen one side by a bin each way: directions up to ~2 bins apart count as the same view.
    f = np.arange(n_features)
    neighbours = (f // nb * nb)[:, None] + ((f % nb)[:, None] + np.array([-1, 0, 1])) % nb
    widen = sparse.csr_matrix(
        (np.ones(neighbours.size, np.float32), (np.repeat(f, 3), neighbours.ravel())),
        shape=(n_features, n_features),
    )
    wide = {rid: (m @ widen).tocsr() for rid, m in seen.items()}
    return {rid: (m > 0).astype(np.float32) for rid, m in wide.items()}


def _overlapping(shared, count_a, count_b, cfg: OverlapConfig):
    """Whether frames with these counts of shared and of visible points look at one scene."""
    smaller = np.minimum(count_a, count_b)
    return (shared >= cfg.min_shared_points) & (
        shared >= cfg.min_shared_fraction * np.maximum(smaller, 1)
    )


def _rendezvous_events(ids, seen, wide, counts, t_s, cfg: OverlapConfig) -> list[dict]:
    """Per robot pair, the first frame time both robots look at one scene."""
    out = []
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            shared = np.asarray(seen[b].multiply(wide[a]).sum(axis=1)).ravel()
            hit = np.flatnonzero(_overlapping(shared, counts[a], counts[b], cfg))
            if len(hit):
                out.append({"robots": [a, b], "stamp_s": float(t_s[hit[0]])})
    return out


def _revisit_events(ids, seen, wide, counts, t_s, cfg: OverlapConfig) -> list[dict]:
    """Per ordered robot pair a -> b, the first frame time b looks at a scene a saw at least
    ``cfg.min_revisit_gap_s`` earlier (and when a saw it best)."""
    out = []
    for a in ids:
        for b in ids:
            if a == b:
                continue
            shared = (seen[b] @ wide[a].T).toarray()  # (frames of b, frames of a)
            ok = _overlapping(shared, counts[b][:, None], counts[a][None, :], cfg)
            ok &= t_s[None, :] <= t_s[:, None] - cfg.min_revisit_gap_s
            rows = np.flatnonzero(ok.any(axis=1))
            if len(rows):
                k = rows[0]
                j = int(np.argmax(np.where(ok[k], shared[k], -1)))
                out.append(
                    {
                        "robot": b,
                        "of_robot": a,
                        "stamp_s": float(t_s[k]),
                        "earlier_stamp_s": float(t_s[j]),
                    }
                )
    return out


def _first_overlaps(ids, events: OverlapEvents) -> list[dict]:
    """Per robot pair, the earliest of its rendezvous, revisits and marker sightings."""
    out = []
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            candidates = [
                ("rendezvous", events.rendezvous_time(a, b)),
                ("revisit", _min_or_none(events.revisit_time(a, b), events.revisit_time(b, a))),
                ("marker", _min_or_none(events.sighting_time(a, b), events.sighting_time(b, a))),
            ]
            candidates = [(t, kind) for kind, t in candidates if t is not None]
            if candidates:
                t, kind = min(candidates)
                out.append({"robots": [a, b], "stamp_s": t, "kind": kind})
    return out


def _min_or_none(*values):
    values = [v for v in values if v is not None]
    return min(values) if values else None
