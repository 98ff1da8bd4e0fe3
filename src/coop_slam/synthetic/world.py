"""Geometry of the synthetic indoor world: textured planar quads and buildings (robot bodies:
:mod:`.bodies`).

Frames (REP-103): world z up; robot ``base_link`` x forward, y left, z up, on the floor (z = 0);
camera optical frame z forward, x right, y down. ``T_a_b`` maps points of frame b into frame a.

A building is a ring corridor (12 m x 8 m outside, 2 m wide) around two rooms (4 m x 3.8 m) joined
by doors, with pillars, cabinets and crates for corners and depth structure. A world holds one or
two buildings 30 m apart; walls are closed, so no camera ever sees from one building into another.
The 'kitchen' layout is one small cluttered room instead (4 m x 3.5 m, for hand-held cameras):
counters and wall cabinets, a fridge, an open shelf, a table and objects of many sizes on them.
Surfaces are split into tiles of at most 2 m so each tile picks its own mip level and its own
screen bounding box stays small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import CoopSlamError
from ..geometry import R_BASE_OPTICAL, se3
from . import textures

WALL_HEIGHT_M = 2.5
BUILDING_SIZE_M = (12.0, 8.0)
BUILDING_SPACING_M = 30.0
TILE_MAX_M = 2.0
PX_PER_M = {"wall": 200.0, "box": 200.0, "floor": 100.0, "ceiling": 60.0}

# Camera on the robot: 0.1 m forward, 0.5 m up, looking forward (optical z = base x).
DEFAULT_T_BASE_CAM = se3(R_BASE_OPTICAL, [0.1, 0.0, 0.5])
# A hand-held camera: base_link is the camera carrier itself (same origin, REP-103 axes), so the
# base moves in 6-DoF and T_world_cam = T_world_base @ HAND_HELD_T_BASE_CAM.
HAND_HELD_T_BASE_CAM = se3(R_BASE_OPTICAL, [0.0, 0.0, 0.0])
KITCHEN_SIZE_M = (4.0, 3.5)


class WorldError(CoopSlamError):
    """An invalid world description (unknown layout, bad marker size, robot id out of range)."""


@dataclass(frozen=True)
class Poster:
    """A texture patch pasted on a surface; ``seed`` decides its pixels (same seed, same poster)."""

    u_m: float  # left edge, metres from the surface's left edge
    v_m: float  # top edge, metres from the surface's top edge
    width_m: float
    height_m: float
    seed: tuple


@dataclass
class Surface:
    """A textured planar rectangle ``origin + s * edge_u + t * edge_v`` for s, t in [0, 1].

    Texture column x runs along ``edge_u`` and row y along ``edge_v``; the visible side is the one
    ``normal = edge_v x edge_u`` points to (seen from there, the texture is not mirrored).
    """

    name: str
    kind: str  # key of PX_PER_M: wall, box, floor, ceiling
    origin_world: np.ndarray
    edge_u_world: np.ndarray
    edge_v_world: np.ndarray
    seed: tuple
    posters: list[Poster] = field(default_factory=list)
    # Below 1, the texture's detail (what differs from its 15 cm blur) is toned down: plain
    # painted walls and cabinet doors, as real rooms have; posters keep their full contrast.
    contrast: float = 1.0

    @property
    def size_m(self) -> tuple[float, float]:
        return float(np.linalg.norm(self.edge_u_world)), float(np.linalg.norm(self.edge_v_world))

    @property
    def tiles(self) -> tuple[int, int]:
        w, h = self.size_m
        return max(1, math.ceil(w / TILE_MAX_M - 1e-9)), max(1, math.ceil(h / 2.5 - 1e-9))

    def texture_size(self) -> tuple[int, int]:
        """(width, height) [px] of the whole-surface texture: whole tiles of SIZE_MULTIPLE px."""
        w, h = self.size_m
        nu, nv = self.tiles
        ppm = PX_PER_M[self.kind]
        return nu * textures.round_size(w / nu, ppm), nv * textures.round_size(h / nv, ppm)

    def make_texture(self) -> np.ndarray:
        w_px, h_px = self.texture_size()
        w_m, h_m = self.size_m
        ppm = PX_PER_M[self.kind]
        tex = textures.surface_texture(w_px, h_px, ppm, self.seed, style=self.kind)
        if self.contrast < 1.0:
            base = cv2.GaussianBlur(tex, (0, 0), 0.15 * ppm)
            tex = cv2.addWeighted(tex, self.contrast, base, 1.0 - self.contrast, 0.0)
        sx, sy = w_px / w_m, h_px / h_m  # exact texels per metre along each edge
        for p in self.posters:
            pw, ph = round(p.width_m * sx), round(p.height_m * sy)
            poster = textures.poster_texture(pw, ph, ppm, p.seed)
            textures.paste_poster(tex, poster, round(p.u_m * sx), round(p.v_m * sy))
        return tex


class QuadModel:
    """Textured quads in a model frame (the world, or a robot's base_link), ready for rendering.

    ``texture_levels(i)`` returns the mip pyramid of quad ``i``; it is built on first use, so a
    renderer only pays for what it sees.
    """

    def __init__(self, origins, edges_u, edges_v, level_fn, names):
        self.origins = np.asarray(origins, float).reshape(-1, 3)
        self.edges_u = np.asarray(edges_u, float).reshape(-1, 3)
        self.edges_v = np.asarray(edges_v, float).reshape(-1, 3)
        n = np.cross(self.edges_v, self.edges_u)
        self.normals = n / np.linalg.norm(n, axis=1, keepdims=True)
        self.centres = self.origins + 0.5 * (self.edges_u + self.edges_v)
        self.radii = 0.5 * np.maximum(
            np.linalg.norm(self.edges_u + self.edges_v, axis=1),
            np.linalg.norm(self.edges_u - self.edges_v, axis=1),
        )
        self.names = list(names)
        self._level_fn = level_fn
        self._levels: dict[int, list[np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.origins)

    def texture_levels(self, i: int) -> list[np.ndarray]:
        levels = self._levels.get(i)
        if levels is None:
            levels = self._levels[i] = self._level_fn(i)
        return levels


class World:
    """Static textured quads of one or more buildings, and their 2D footprint (free-space tests)."""

    def __init__(
        self,
        surfaces: list[Surface],
        obstacles_xy: list[tuple],
        building_origins_xy,
        meta,
        building_size_m: tuple[float, float] = BUILDING_SIZE_M,
    ):
        self.surfaces = surfaces
        self.obstacles_xy = obstacles_xy  # (x0, y0, x1, y1) occupied rectangles
        self.building_origins_xy = [tuple(map(float, o)) for o in building_origins_xy]
        self.building_size_m = tuple(map(float, building_size_m))  # outer walls (x, y) [m]
        self.meta = meta
        origins, eus, evs, names, self._tile_of = [], [], [], [], []
        for si, s in enumerate(surfaces):
            nu, nv = s.tiles
            for j in range(nv):
                for i in range(nu):
                    origins.append(
                        s.origin_world + i / nu * s.edge_u_world + j / nv * s.edge_v_world
                    )
                    eus.append(s.edge_u_world / nu)
                    evs.append(s.edge_v_world / nv)
                    names.append(f"{s.name}[{i},{j}]")
                    self._tile_of.append((si, i, j))
        self._surface_textures: dict[int, np.ndarray] = {}
        self.quads = QuadModel(origins, eus, evs, self._tile_levels, names)

    def surface_texture(self, si: int) -> np.ndarray:
        tex = self._surface_textures.get(si)
        if tex is None:
            tex = self._surface_textures[si] = self.surfaces[si].make_texture()
        return tex

    def _tile_levels(self, q: int) -> list[np.ndarray]:
        si, i, j = self._tile_of[q]
        tex = self.surface_texture(si)
        nu, nv = self.surfaces[si].tiles
        th, tw = tex.shape[0] // nv, tex.shape[1] // nu
        return textures.mip_pyramid(tex[j * th : (j + 1) * th, i * tw : (i + 1) * tw])

    def is_free(self, xy, clearance_m: float = 0.0) -> np.ndarray:
        """Whether a disc of radius ``clearance_m`` at each (x, y) is in a building's free space."""
        xy = np.atleast_2d(np.asarray(xy, float))
        inside_any = np.zeros(len(xy), bool)
        bw, bh = self.building_size_m
        for ox, oy in self.building_origins_xy:
            inside_any |= (
                (xy[:, 0] >= ox + clearance_m)
                & (xy[:, 0] <= ox + bw - clearance_m)
                & (xy[:, 1] >= oy + clearance_m)
                & (xy[:, 1] <= oy + bh - clearance_m)
            )
        for x0, y0, x1, y1 in self.obstacles_xy:
            dx = np.maximum(np.maximum(x0 - xy[:, 0], xy[:, 0] - x1), 0.0)
            dy = np.maximum(np.maximum(y0 - xy[:, 1], xy[:, 1] - y1), 0.0)
            inside_any &= np.hypot(dx, dy) > clearance_m
        return inside_any

    def sample_points(self, spacing_m: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
        """(points_world (N, 3), normals_world (N, 3)): a regular grid over all static surfaces."""
        pts, nrm = [], []
        for s in self.surfaces:
            w, h = s.size_m
            step = spacing_m * (2.0 if s.kind in ("floor", "ceiling") else 1.0)
            nu, nv = max(1, round(w / step)), max(1, round(h / step))
            su, sv = np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv)
            p = (
                s.origin_world
                + su.reshape(-1, 1) * s.edge_u_world
                + sv.reshape(-1, 1) * s.edge_v_world
            )
            n = np.cross(s.edge_v_world, s.edge_u_world)
            pts.append(p)
            nrm.append(np.repeat((n / np.linalg.norm(n))[None], len(p), axis=0))
        return np.concatenate(pts), np.concatenate(nrm)


# --- building layout ---------------------------------------------------------------------------
def _wall(name, a_xy, b_xy, z0, z1, kind, seed, posters=(), contrast=1.0) -> Surface:
    """Vertical rectangle from a to b, visible from the right-hand side of the direction a -> b."""
    a = np.array([a_xy[0], a_xy[1], z1], float)
    b = np.array([b_xy[0], b_xy[1], z1], float)
    return Surface(
        name, kind, a, b - a, np.array([0.0, 0.0, z0 - z1]), seed, list(posters), contrast
    )


def _box(
    name, x0, y0, x1, y1, z0, z1, kind, seed, top=True, bottom=False, contrast=1.0
) -> list[Surface]:
    """Outward-facing sides (counter-clockwise = outside on the right), top and (for boxes that
    hang above the floor, seen from below) bottom of a cuboid."""
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    out = [
        _wall(
            f"{name}.side{k}",
            corners[k],
            corners[(k + 1) % 4],
            z0,
            z1,
            kind,
            seed + (k,),
            contrast=contrast,
        )
        for k in range(4)
    ]
    if top:
        out.append(
            Surface(
                f"{name}.top",
                kind,
                np.array([x0, y1, z1]),
                np.array([x1 - x0, 0.0, 0.0]),
                np.array([0.0, y0 - y1, 0.0]),
                seed + (4,),
                contrast=contrast,
            )
        )
    if bottom:  # normal edge_v x edge_u points down
        out.append(
            Surface(
                f"{name}.bottom",
                kind,
                np.array([x0, y0, z0]),
                np.array([x1 - x0, 0.0, 0.0]),
                np.array([0.0, y1 - y0, 0.0]),
                seed + (5,),
                contrast=contrast,
            )
        )
    return out


def _building(index: int, origin_xy, texture_key: tuple, poster_key: tuple) -> tuple[list, list]:
    """Surfaces and obstacle footprints of one ring building, lower-left corner at origin_xy."""
    ox, oy = origin_xy
    H = WALL_HEIGHT_M
    surfaces: list[Surface] = []
    obstacles: list[tuple] = []
    counter = iter(range(10_000))

    def seed():
        return texture_key + (next(counter),)

    def P(x, y):
        return (ox + x, oy + y)

    b = f"b{index}"
    # Outer walls, inward-facing (clockwise). Posters hang at camera height (z 0.3-1.2 m) on the
    # end walls of the corridors, where robots driving down a corridor face them head-on.
    vpos = H - 1.2

    def poster(slot, u):
        return Poster(u, vpos, 1.0, 0.9, poster_key + (slot,))

    outer = [
        ("west", (0, 0), (0, 8), [poster(0, 6.5)]),  # end of the north corridor
        ("north", (0, 8), (12, 8), [poster(1, 10.5)]),  # end of the east corridor
        ("east", (12, 8), (12, 0), [poster(2, 6.5)]),  # end of the south corridor
        ("south", (12, 0), (0, 0), [poster(3, 10.5)]),  # end of the west corridor
    ]
    for name, a, c, posters in outer:
        surfaces.append(_wall(f"{b}.{name}", P(*a), P(*c), 0.0, H, "wall", seed(), posters))
    # Inner block: walls 0.1 m thick with doors (1 m) into room A (south), room B (north) and
    # between the rooms (partition). Each wall piece is a box, so door jambs come for free.
    walls = [
        ("s1", 2.0, 2.0, 3.5, 2.1),
        ("s2", 4.5, 2.0, 10.0, 2.1),
        ("n1", 2.0, 5.9, 7.5, 6.0),
        ("n2", 8.5, 5.9, 10.0, 6.0),
        ("w", 2.0, 2.1, 2.1, 5.9),
        ("e", 9.9, 2.1, 10.0, 5.9),
        ("p1", 5.95, 2.1, 6.05, 3.5),
        ("p2", 5.95, 4.5, 6.05, 5.9),
    ]
    for name, x0, y0, x1, y1 in walls:
        (ax, ay), (cx, cy) = P(x0, y0), P(x1, y1)
        surfaces += _box(f"{b}.wall_{name}", ax, ay, cx, cy, 0.0, H, "wall", seed(), top=False)
        obstacles.append((ax, ay, cx, cy))
    # The north corridor side of the inner block carries a poster too (wall n1, facing north).
    for s in surfaces:
        if s.name == f"{b}.wall_n1.side2":  # side2 runs (x1, y1) -> (x0, y1): faces +y
            s.posters.append(poster(4, 2.0))
    # Pillars in the outer corners (full height), a pillar in room A; cabinets against outer walls;
    # crates in the rooms. Heights differ so silhouettes differ from place to place.
    solids = [
        ("pillar_sw", 0.1, 0.1, 0.45, 0.45, H, False),
        ("pillar_se", 11.55, 0.1, 11.9, 0.45, H, False),
        ("pillar_ne", 11.55, 7.55, 11.9, 7.9, H, False),
        ("pillar_nw", 0.1, 7.55, 0.45, 7.9, H, False),
        ("pillar_a", 4.7, 2.4, 5.0, 2.7, H, False),
        ("cabinet_s", 5.0, 0.02, 6.2, 0.27, 0.8, True),
        ("cabinet_n", 3.0, 7.73, 4.0, 7.98, 1.0, True),
        ("cabinet_e", 11.73, 3.5, 11.98, 4.5, 0.6, True),
        ("crate_a", 2.5, 4.6, 3.3, 5.4, 0.9, True),
        ("crate_b", 8.8, 2.4, 9.6, 3.2, 0.7, True),
        ("shelf_b", 6.4, 5.2, 7.2, 5.8, 1.2, True),
    ]
    for name, x0, y0, x1, y1, h, top in solids:
        (ax, ay), (cx, cy) = P(x0, y0), P(x1, y1)
        surfaces += _box(f"{b}.{name}", ax, ay, cx, cy, 0.0, h, "box", seed(), top=top)
        obstacles.append((ax, ay, cx, cy))
    bw, bh = BUILDING_SIZE_M
    surfaces.append(
        Surface(
            f"{b}.floor",
            "floor",
            np.array([ox, oy + bh, 0.0]),
            np.array([bw, 0.0, 0.0]),
            np.array([0.0, -bh, 0.0]),
            seed(),
        )
    )
    surfaces.append(
        Surface(
            f"{b}.ceiling",
            "ceiling",
            np.array([ox, oy, H]),
            np.array([bw, 0.0, 0.0]),
            np.array([0.0, bh, 0.0]),
            seed(),
        )
    )
    return surfaces, obstacles


# Texture detail of the kitchen's large surfaces (Surface.contrast): painted walls and cabinet
# fronts are plain, worktops and wood a little less so; appliances, books, boxes and posters keep
# their full detail. Corners then cluster on the clutter, as in a real kitchen.
PLAIN_CONTRAST, SMOOTH_CONTRAST = 0.35, 0.6


class _RoomBuilder:
    """A room's surfaces and obstacle footprints as they are added. Texture seeds are handed out
    in turn, so the order of the additions decides every texture."""

    def __init__(self, prefix: str, key: tuple):
        self.prefix, self.key = prefix, key
        self.surfaces: list[Surface] = []
        self.obstacles: list[tuple] = []
        self._counter = iter(range(10_000))

    def seed(self) -> tuple:
        return self.key + (next(self._counter),)

    def poster(self, u, v, w, h) -> Poster:
        return Poster(u, v, w, h, self.key + (500 + next(self._counter),))

    def solid(
        self, name, x0, y0, x1, y1, z0, z1, top=True, bottom=False, obstacle=False, contrast=1.0
    ):
        """A box (see :func:`_box`); ``obstacle``: its footprint is one too."""
        name = f"{self.prefix}.{name}"
        box = _box(name, x0, y0, x1, y1, z0, z1, "box", self.seed(), top, bottom, contrast)
        self.surfaces.extend(box)
        if obstacle:
            self.obstacles.append((x0, y0, x1, y1))


def _kitchen(seed: int) -> tuple[list, list]:
    """Surfaces and obstacle footprints of a kitchen of KITCHEN_SIZE_M with its corner at (0, 0).

    x east, y north. Counters (0.9 m) with wall cabinets above run along the south and west walls,
    a fridge stands in the south-east corner, an open shelf of books and a sideboard along the north
    wall, boxes and a radiator along the east wall, a table in the middle; the free floor around the
    table (x 1.3-3.3, y 1.2-2.5 with some margin) is where people walk. Every surface, door and
    object has its own texture seed: nothing repeats exactly (no aliasing between places).
    """
    H = WALL_HEIGHT_M
    W, D = KITCHEN_SIZE_M
    key = (int(seed), 2000)  # apart from the ring buildings' (seed, b) and posters' (seed, 1000+)
    room = _RoomBuilder("kitchen", key)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 2001]))
    _kitchen_walls(room)
    _kitchen_counters(room)
    _kitchen_worktop_things(room)
    _kitchen_shelf(room, rng)
    _kitchen_furniture(room)
    _kitchen_table(room)
    room.surfaces.append(
        Surface(
            "kitchen.floor",
            "floor",
            np.array([0.0, D, 0.0]),
            np.array([W, 0.0, 0.0]),
            np.array([0.0, -D, 0.0]),
            room.seed(),
            contrast=SMOOTH_CONTRAST,
        )
    )
    room.surfaces.append(
        Surface(
            "kitchen.ceiling",
            "ceiling",
            np.array([0.0, 0.0, H]),
            np.array([W, 0.0, 0.0]),
            np.array([0.0, D, 0.0]),
            room.seed(),
        )
    )
    return room.surfaces, room.obstacles


def _kitchen_walls(room: _RoomBuilder) -> None:
    """The walls, facing inwards (clockwise), with posters: tiles behind the south counter, a
    window (east), a calendar above the sideboard (north) and a picture beside the west cabinets."""
    H = WALL_HEIGHT_M
    W, D = KITCHEN_SIZE_M
    poster, plain = room.poster, PLAIN_CONTRAST
    walls = [
        ("west", (0, 0), (0, D), [poster(2.7, 0.7, 0.6, 0.6)]),
        ("north", (0, D), (W, D), [poster(2.55, 0.6, 0.5, 0.6)]),
        ("east", (W, D), (W, 0), [poster(0.9, 0.3, 1.2, 1.1)]),
        ("south", (W, 0), (0, 0), [poster(1.0, H - 1.5, 3.0, 0.55)]),
    ]
    for name, a, c, posters in walls:
        wall = _wall(f"kitchen.{name}", a, c, 0.0, H, "wall", room.seed(), posters, plain)
        room.surfaces.append(wall)


def _kitchen_counters(room: _RoomBuilder) -> None:
    """Counters along the south and west walls with wall cabinets above, and the fridge."""
    solid, plain, smooth = room.solid, PLAIN_CONTRAST, SMOOTH_CONTRAST
    # Counters: carcass, worktop with a 2-4 cm overhang, door fronts 2 cm proud of the carcass.
    solid("counter_s", 0.0, 0.0, 3.0, 0.58, 0.0, 0.86, top=False, contrast=plain)
    solid("worktop_s", 0.0, 0.0, 3.02, 0.62, 0.86, 0.9, bottom=True, obstacle=True, contrast=smooth)
    solid("counter_w", 0.0, 0.62, 0.58, 2.6, 0.0, 0.86, top=False, contrast=plain)
    solid(
        "worktop_w", 0.0, 0.62, 0.62, 2.62, 0.86, 0.9, bottom=True, obstacle=True, contrast=smooth
    )
    for k, x in enumerate((0.62, 1.22, 1.82, 2.42)):
        solid(f"door_s{k}", x + 0.01, 0.58, x + 0.57, 0.6, 0.1, 0.82, top=False, contrast=plain)
    for k, y in enumerate((0.66, 1.32, 1.98)):
        solid(f"door_w{k}", 0.58, y + 0.01, 0.6, y + 0.6, 0.1, 0.82, top=False, contrast=plain)
    # Wall cabinets (seen from below when the camera is low), with door fronts.
    solid("upper_s", 0.0, 0.0, 2.2, 0.34, 1.5, 2.2, top=False, bottom=True, contrast=plain)
    for k, x in enumerate((0.0, 0.55, 1.1, 1.65)):
        solid(
            f"upper_door_s{k}",
            x + 0.01,
            0.34,
            x + 0.54,
            0.36,
            1.52,
            2.18,
            top=False,
            contrast=plain,
        )
    solid("upper_w", 0.0, 0.8, 0.34, 2.4, 1.5, 2.2, top=False, bottom=True, contrast=plain)
    for k, y in enumerate((0.8, 1.34, 1.88)):
        solid(
            f"upper_door_w{k}",
            0.34,
            y + 0.01,
            0.36,
            y + 0.52,
            1.52,
            2.18,
            top=False,
            contrast=plain,
        )
    solid("fridge", 3.2, 0.02, 3.9, 0.68, 0.0, 1.9, obstacle=True, contrast=plain)
    solid("fridge_box", 3.3, 0.1, 3.7, 0.5, 1.9, 2.1)


def _kitchen_worktop_things(room: _RoomBuilder) -> None:
    """What stands on the worktops (z 0.9)."""
    # South: microwave, cutting board, kettle, toaster, cereal, jars.
    for name, x0, y0, x1, y1, h in (
        ("microwave", 0.7, 0.06, 1.2, 0.42, 0.3),
        ("board", 1.25, 0.02, 1.4, 0.05, 0.35),
        ("kettle", 1.45, 0.1, 1.65, 0.28, 0.25),
        ("toaster", 1.85, 0.08, 2.15, 0.26, 0.18),
        ("cereal", 2.35, 0.06, 2.55, 0.13, 0.3),
        ("jar_a", 2.65, 0.1, 2.75, 0.2, 0.12),
        ("jar_b", 2.8, 0.1, 2.9, 0.2, 0.15),
    ):
        room.solid(name, x0, y0, x1, y1, 0.9, 0.9 + h)
    # ... and west: dish rack, bottles, bread box.
    for name, x0, y0, x1, y1, h in (
        ("rack", 0.1, 1.0, 0.5, 1.4, 0.15),
        ("bottle_a", 0.15, 1.7, 0.22, 1.77, 0.3),
        ("bottle_b", 0.27, 1.72, 0.34, 1.79, 0.35),
        ("breadbox", 0.05, 2.0, 0.45, 2.35, 0.2),
    ):
        room.solid(name, x0, y0, x1, y1, 0.9, 0.9 + h)


def _kitchen_shelf(room: _RoomBuilder, rng: np.random.Generator) -> None:
    """Open shelf on the north wall: two sides, five boards, books and jars on the boards (their
    sizes and gaps drawn from ``rng``)."""
    solid, smooth = room.solid, SMOOTH_CONTRAST
    sy0, sy1 = 3.15, 3.5
    solid("shelf_side_a", 1.0, sy0, 1.03, sy1, 0.0, 1.7, contrast=smooth)
    solid("shelf_side_b", 2.17, sy0, 2.2, sy1, 0.0, 1.7, contrast=smooth)
    room.obstacles.append((1.0, sy0, 2.2, sy1))
    boards = (0.0, 0.42, 0.85, 1.28, 1.67)
    for k, z in enumerate(boards):
        solid(f"shelf_board{k}", 1.03, sy0, 2.17, sy1, z, z + 0.03, bottom=k > 0, contrast=smooth)
    for level, z in enumerate(boards[:4]):
        x = 1.06 + rng.uniform(0.0, 0.08)
        k = 0
        while True:
            w = rng.uniform(0.03, 0.09) if level < 3 else rng.uniform(0.08, 0.16)
            h = rng.uniform(0.16, 0.33) if level < 3 else rng.uniform(0.08, 0.2)
            if x + w > 2.14:
                break
            depth = rng.uniform(0.16, 0.26)
            solid(
                f"shelf_item{level}_{k}",
                x,
                sy1 - 0.02 - depth,
                x + w,
                sy1 - 0.02,
                z + 0.03,
                z + 0.03 + h,
            )
            x += w + (rng.uniform(0.0, 0.02) if rng.random() < 0.8 else rng.uniform(0.08, 0.2))
            k += 1


def _kitchen_furniture(room: _RoomBuilder) -> None:
    """The sideboard (north) and what is on it, boxes and a radiator (east), a chair and a bin
    (north-west)."""
    solid = room.solid
    solid("sideboard", 2.5, 3.05, 3.8, 3.5, 0.0, 0.85, obstacle=True, contrast=SMOOTH_CONTRAST)
    for name, x0, y0, x1, y1, z0, z1 in (
        ("pot", 2.6, 3.2, 2.8, 3.4, 0.85, 1.1),
        ("plant", 2.55, 3.15, 2.85, 3.45, 1.1, 1.45),
        ("radio", 3.0, 3.25, 3.35, 3.45, 0.85, 1.0),
        ("storage_box", 3.45, 3.1, 3.75, 3.4, 0.85, 1.15),
    ):
        solid(name, x0, y0, x1, y1, z0, z1)
    # East wall: stacked moving boxes and a radiator under the window.
    solid("boxes_a", 3.65, 1.3, 3.97, 1.72, 0.0, 0.38, obstacle=True)
    solid("boxes_b", 3.68, 1.36, 3.95, 1.66, 0.38, 0.6)
    solid("boxes_c", 3.72, 1.42, 3.9, 1.6, 0.6, 0.76)
    solid("radiator", 3.9, 2.05, 3.98, 2.95, 0.15, 0.7, obstacle=True)
    # North-west corner: a chair (seat, back, legs) and a bin.
    solid("chair_seat", 0.15, 2.75, 0.55, 3.15, 0.43, 0.47, bottom=True, obstacle=True)
    solid("chair_back", 0.15, 3.11, 0.55, 3.15, 0.47, 0.95)
    for k, (x, y) in enumerate(((0.16, 2.76), (0.51, 2.76), (0.16, 3.11), (0.51, 3.11))):
        solid(f"chair_leg{k}", x, y, x + 0.03, y + 0.03, 0.0, 0.43, top=False)
    solid("bin", 0.62, 3.15, 0.92, 3.45, 0.0, 0.5, obstacle=True)


def _kitchen_table(room: _RoomBuilder) -> None:
    """The table in the middle (top on four legs) and what is on it."""
    solid, smooth = room.solid, SMOOTH_CONTRAST
    tx0, ty0, tx1, ty1 = 1.9, 1.64, 2.7, 2.06
    solid("table_top", tx0, ty0, tx1, ty1, 0.72, 0.76, bottom=True, obstacle=True, contrast=smooth)
    for k, (x, y) in enumerate(
        (
            (tx0 + 0.03, ty0 + 0.03),
            (tx1 - 0.07, ty0 + 0.03),
            (tx1 - 0.07, ty1 - 0.07),
            (tx0 + 0.03, ty1 - 0.07),
        )
    ):
        solid(f"table_leg{k}", x, y, x + 0.04, y + 0.04, 0.0, 0.72, top=False)
    for name, x0, y0, x1, y1, z0, z1 in (
        ("bowl", 2.0, 1.7, 2.25, 1.95, 0.76, 0.86),
        ("book_a", 2.35, 1.69, 2.62, 1.88, 0.76, 0.81),
        ("book_b", 2.38, 1.71, 2.6, 1.86, 0.81, 0.84),
        ("mug", 2.5, 1.95, 2.58, 2.03, 0.76, 0.86),
    ):
        solid(name, x0, y0, x1, y1, z0, z1)


LAYOUTS = ("ring", "two_buildings", "two_buildings_aliased", "kitchen")


def build_world(layout: str = "ring", seed: int = 0) -> World:
    """The static world: 'ring' (one building), 'two_buildings' (two buildings whose textures all
    differ), 'two_buildings_aliased' (two buildings that share identical posters) or 'kitchen'
    (one small cluttered room for hand-held cameras)."""
    if layout not in LAYOUTS:
        raise WorldError(f"unknown world layout '{layout}'; use one of {LAYOUTS}")
    if layout == "kitchen":
        surfaces, obstacles = _kitchen(seed)
        meta = {"layout": layout, "seed": int(seed), "buildings": [[0.0, 0.0]]}
        return World(surfaces, obstacles, [(0.0, 0.0)], meta, building_size_m=KITCHEN_SIZE_M)
    n_buildings = 1 if layout == "ring" else 2
    surfaces, obstacles, origins = [], [], []
    for b in range(n_buildings):
        origin = (b * BUILDING_SPACING_M, 0.0)
        # Aliased worlds take the posters of building 0 for every building: identical patches at
        # different places. Everything else always has building-specific seeds.
        poster_key = (
            (int(seed), 1000) if layout == "two_buildings_aliased" else (int(seed), 1000 + b)
        )
        s, o = _building(b, origin, (int(seed), b), poster_key)
        surfaces += s
        obstacles += o
        origins.append(origin)
    meta = {"layout": layout, "seed": int(seed), "buildings": [list(o) for o in origins]}
    return World(surfaces, obstacles, origins, meta)
