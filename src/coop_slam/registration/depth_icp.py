"""Two keyframes registered on their depth alone: point-to-plane ICP between their decimated depth
images' points, for views ORB cannot match (a scene seen from directions far apart, plain walls)
but whose geometry overlaps.

The reference keyframe's points come with normals from its image grid (the cross product of the
neighbouring pixels' points: no neighbour search). Gauss-Newton on point-to-plane residuals with a
Huber kernel, from the caller's seed (the team map's prediction), nearest neighbours within a gate
that shrinks from ``start_gate_m`` to ``end_gate_m``. The result is refused when the overlap is
small (``min_overlap`` of the moving points paired at the end), the residual large, the iterations
did not settle, or the geometry leaves a direction unconstrained -- one wall, a corridor's two
walls and floor sliding along it: its covariance (the normal equations' inverse scaled by the
residual variance and by ``inflate``, as neighbouring depth pixels' errors are not independent)
then exceeds ``max_sigma_trans_m`` / ``max_sigma_rot_deg`` in its weakest direction."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..config import require
from ..geometry import exp_so3
from .camera import RegistrationError


@dataclass
class DepthIcpConfig:
    """Point-to-plane ICP between two keyframes' depth images (``server.links.depth_icp``)."""

    max_iterations: int = 20  # Gauss-Newton steps at most
    start_gate_m: float = 0.15  # nearest-neighbour gate of the first iteration [m] ...
    end_gate_m: float = 0.04  # ... shrinking to this one [m]
    huber_m: float = 0.01  # Huber kernel width [m]
    min_overlap: float = 0.25  # share of the moving points paired at the end
    # Settled when a step at the final gate moves less than this [m] and this [rad]: real depth
    # re-pairs a few points every step, so steps do not shrink to nothing.
    settle_m: float = 0.001
    settle_rad: float = 0.001
    max_rms_m: float = 0.02  # RMS point-to-plane residual of the pairs at the end [m]
    max_sigma_trans_m: float = 0.02  # the weakest direction's translation sigma [m] ...
    max_sigma_rot_deg: float = 1.0  # ... and rotation sigma [deg]
    inflate: float = 10.0  # covariance inflation (correlated errors of neighbouring pixels)
    min_points: int = 200  # points each side needs
    max_points: int = 1000  # moving points used (an even sample beyond): ~8 ms a pair

    def validate(self) -> None:
        require(self.max_iterations >= 1, "depth_icp.max_iterations must be >= 1")
        require(0 < self.end_gate_m <= self.start_gate_m, "depth_icp: need 0 < end <= start gate")
        require(self.huber_m > 0 and self.max_rms_m > 0, "depth_icp: huber_m, max_rms_m > 0")
        require(0 < self.min_overlap <= 1, "depth_icp.min_overlap must be in (0, 1]")
        require(self.max_sigma_trans_m > 0, "depth_icp.max_sigma_trans_m must be > 0 [m]")
        require(self.max_sigma_rot_deg > 0, "depth_icp.max_sigma_rot_deg must be > 0 [deg]")
        require(self.inflate >= 1, "depth_icp.inflate must be >= 1")


@dataclass
class DepthIcpResult:
    accepted: bool
    reason: str
    T_a_b: np.ndarray  # b's camera in a's (the last estimate, also when refused)
    overlap: float = 0.0
    rms_m: float = np.inf
    sigma_rot_deg: float = np.inf
    sigma_trans_m: float = np.inf
    n_pairs: int = 0


def grid_normals(points_grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3), unit normals (N, 3)) of an organized (h, w, 3) point grid (NaN = none):
    the normal of a pixel from its four neighbours, where they all exist and lie within 10 % of
    its depth of it (not across a depth edge)."""
    p = points_grid
    dx, dy = p[1:-1, 2:] - p[1:-1, :-2], p[2:, 1:-1] - p[:-2, 1:-1]
    n = np.cross(dx, dy)
    centre = p[1:-1, 1:-1]
    z = centre[..., 2]
    near = (np.abs(dx[..., 2]) < 0.2 * z) & (np.abs(dy[..., 2]) < 0.2 * z)
    norm = np.linalg.norm(n, axis=-1)
    ok = np.isfinite(norm) & (norm > 0) & near & np.isfinite(z)
    n = n[ok] / norm[ok, None]
    pts = centre[ok]
    # Normals towards the camera (the origin).
    flip = np.einsum("ij,ij->i", n, pts) > 0
    n[flip] *= -1
    return pts, n


def register_depth(
    points_a: np.ndarray,
    normals_a: np.ndarray,
    points_b: np.ndarray,
    T_a_b_seed: np.ndarray,
    config: DepthIcpConfig | None = None,
) -> DepthIcpResult:
    """b's points (N, 3, its camera frame) onto a's surfaces (points and normals, a's camera
    frame), from ``T_a_b_seed``; see the module."""
    cfg = config or DepthIcpConfig()
    if len(points_a) < cfg.min_points or len(points_b) < cfg.min_points:
        return DepthIcpResult(False, "too few depth points", np.array(T_a_b_seed, float))
    if len(points_b) > cfg.max_points:
        points_b = points_b[np.linspace(0, len(points_b) - 1, cfg.max_points).astype(int)]
    tree = cKDTree(points_a)
    T = np.array(T_a_b_seed, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise RegistrationError("depth ICP: the seed must be a finite 4x4 transform")
    settled = False
    for it in range(cfg.max_iterations):
        gate = cfg.start_gate_m * (cfg.end_gate_m / cfg.start_gate_m) ** min(
            1.0, it / max(1, cfg.max_iterations // 2)
        )
        moved = points_b @ T[:3, :3].T + T[:3, 3]
        dist, idx = tree.query(moved, distance_upper_bound=gate)
        paired = np.isfinite(dist)
        if paired.sum() < cfg.min_points:
            return DepthIcpResult(False, "the depth does not overlap", T, float(paired.mean()))
        p, q, n = moved[paired], points_a[idx[paired]], normals_a[idx[paired]]
        r = np.einsum("ij,ij->i", n, p - q)
        w = np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12))
        J = np.hstack([np.cross(p, n), n])
        H = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r
        delta = np.linalg.lstsq(H, -g, rcond=None)[0]  # (a free direction: not moved along)
        step = np.eye(4)
        step[:3, :3] = exp_so3(delta[:3])
        step[:3, 3] = delta[3:]
        T = step @ T
        if (
            gate <= cfg.end_gate_m * 1.0001
            and np.linalg.norm(delta[3:]) < cfg.settle_m
            and np.linalg.norm(delta[:3]) < cfg.settle_rad
        ):
            settled = True
            break
    moved = points_b @ T[:3, :3].T + T[:3, 3]
    dist, idx = tree.query(moved, distance_upper_bound=cfg.end_gate_m)
    paired = np.isfinite(dist)
    overlap = float(paired.mean())
    p, q, n = moved[paired], points_a[idx[paired]], normals_a[idx[paired]]
    r = np.einsum("ij,ij->i", n, p - q)
    rms = float(np.sqrt(np.mean(r**2))) if len(r) else np.inf
    J = np.hstack([np.cross(p, n), n])
    out = DepthIcpResult(False, "", T, overlap, rms, n_pairs=int(paired.sum()))
    eig, vec = np.linalg.eigh(J.T @ J)
    if eig[0] > 1e-12 * max(eig[-1], 1e-300):
        cov = (vec / eig) @ vec.T * (rms**2) * cfg.inflate
        out.sigma_rot_deg = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])))
        out.sigma_trans_m = float(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1]))
    if not settled:
        out.reason = "ICP did not settle"
    elif overlap < cfg.min_overlap:
        out.reason = f"overlap {overlap:.2f} < {cfg.min_overlap}"
    elif rms > cfg.max_rms_m:
        out.reason = f"residual {100 * rms:.1f} cm > {100 * cfg.max_rms_m:.1f} cm"
    elif out.sigma_trans_m > cfg.max_sigma_trans_m or out.sigma_rot_deg > cfg.max_sigma_rot_deg:
        out.reason = (
            f"the geometry leaves a direction free (sigma {100 * out.sigma_trans_m:.1f} cm, "
            f"{out.sigma_rot_deg:.2f} deg)"
        )
    else:
        out.accepted, out.reason = True, "ok"
    return out
