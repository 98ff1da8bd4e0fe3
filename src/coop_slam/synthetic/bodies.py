"""Robot bodies of the synthetic world, the others a camera sees: a box on the floor centred on
base_link with the robot's ArUco marker (its id) on each of its four sides, in base_link.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import textures
from .world import QuadModel, WorldError

# Robot body: a box on the floor centred on base_link; markers on its four sides.
BODY_SIZE_M = (0.4, 0.4, 0.6)
MARKER_CENTRE_HEIGHT_M = 0.38
DEFAULT_MARKER_SIZE_M = 0.25


@dataclass(frozen=True)
class BodyFace:
    """One side of a robot body in base_link: the quad and its marker's corners."""

    origin_base: np.ndarray
    edge_u_base: np.ndarray
    edge_v_base: np.ndarray
    marker_corners_base: np.ndarray | None  # (4, 3) in ArUco order: TL, TR, BR, BL


def body_faces(marker_size_m: float = DEFAULT_MARKER_SIZE_M) -> list[BodyFace]:
    """Four marker sides (front, left, back, right) and the top of the robot body, in base_link."""
    sx, sy, sz = BODY_SIZE_M
    if not 0.05 <= marker_size_m <= 0.7 * min(sx, sy):
        raise WorldError(
            f"marker size {marker_size_m} m must be in [0.05, {0.7 * min(sx, sy):.2f}] m to fit "
            f"on the {sx} x {sy} m robot body with its white border"
        )
    hx, hy = sx / 2, sy / 2
    corners = [(hx, -hy), (hx, hy), (-hx, hy), (-hx, -hy)]  # counter-clockwise from front-right
    # Marker corners from the texel layout the texture uses, so geometry and pixels agree exactly.
    w_px, h_px, x0, y0, side = textures.marker_face_layout(
        sx, sz, marker_size_m, sz - MARKER_CENTRE_HEIGHT_M
    )
    faces = []
    for k in range(4):
        a, c = corners[k], corners[(k + 1) % 4]
        origin = np.array([a[0], a[1], sz])
        eu = np.array([c[0] - a[0], c[1] - a[1], 0.0])
        ev = np.array([0.0, 0.0, -sz])
        s0, s1 = x0 / w_px, (x0 + side) / w_px
        t0, t1 = y0 / h_px, (y0 + side) / h_px
        marker = np.array(
            [origin + s * eu + t * ev for s, t in ((s0, t0), (s1, t0), (s1, t1), (s0, t1))]
        )
        faces.append(BodyFace(origin, eu, ev, marker))
    faces.append(
        BodyFace(np.array([-hx, hy, sz]), np.array([sx, 0, 0.0]), np.array([0, -sy, 0.0]), None)
    )
    return faces


def body_model(robot_id: int, marker_size_m: float = DEFAULT_MARKER_SIZE_M) -> QuadModel:
    """Quads of robot ``robot_id``'s body in its base_link; the marker id is the robot id."""
    faces = body_faces(marker_size_m)
    sx, _sy, sz = BODY_SIZE_M
    side_tex = textures.marker_face_texture(
        robot_id, sx, sz, marker_size_m, sz - MARKER_CENTRE_HEIGHT_M
    )
    side_levels = textures.mip_pyramid(side_tex)
    top = np.full((64, 64, 3), (60, 60, 66), np.uint8)
    top[8:56, 8:56] = (170, 170, 170)  # a light panel so the top edge is visible
    top_levels = textures.mip_pyramid(top)

    def levels(i):
        return side_levels if i < 4 else top_levels

    return QuadModel(
        [f.origin_base for f in faces],
        [f.edge_u_base for f in faces],
        [f.edge_v_base for f in faces],
        levels,
        [f"robot_{robot_id}.{n}" for n in ("front", "left", "back", "right", "top")],
    )
