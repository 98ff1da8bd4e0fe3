"""Procedural, seeded textures for the synthetic world, and their mip-map pyramids.

Every surface gets its own texture from its own seed, so places look different from each other (a
place recognizer must be able to tell them apart) and the same seed always gives the same pixels.
Textures mix shapes at several physical scales (0.05-0.6 m) so that ORB finds corners from close
up (fine scales) as well as from across a room (coarse scales).
"""

from __future__ import annotations

import string

import cv2
import numpy as np

from ..errors import CoopSlamError

# Texture sizes are rounded up to this multiple so that every pyramid level halves exactly and the
# texel -> surface mapping stays exact at every level.
SIZE_MULTIPLE = 32
MAX_LEVELS = 6
_TEXT_CHARS = np.array(list(string.ascii_uppercase + string.digits))


class TextureError(CoopSlamError):
    """A texture cannot be made (invalid size, seed or marker id)."""


def round_size(length_m: float, px_per_m: float) -> int:
    """Texture side [px] for ``length_m`` metres at ``px_per_m``, a multiple of SIZE_MULTIPLE."""
    if not (length_m > 0 and px_per_m > 0):
        raise TextureError(f"texture side {length_m} m at {px_per_m} px/m must be positive")
    n = int(np.ceil(length_m * px_per_m / SIZE_MULTIPLE))
    return max(1, n) * SIZE_MULTIPLE


def _rng(seed) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed))


def _palette(rng: np.random.Generator, n: int, style: str) -> np.ndarray:
    """(n, 3) BGR colours: a random hue family per surface plus a few contrasting accents."""
    hue0 = rng.uniform(0, 180)
    hues = (hue0 + rng.normal(0, 18, n)) % 180
    accents = rng.random(n) < 0.3
    hues[accents] = rng.uniform(0, 180, accents.sum())
    sat = rng.uniform(40, 230, n)
    val = rng.uniform(25, 250, n)
    if style == "ceiling":  # ceilings are pale and less saturated
        sat *= 0.4
        val = 120 + val * 0.5
    hsv = np.stack([hues, sat, val], axis=1).astype(np.uint8)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0].astype(int)


def _low_frequency(
    rng: np.random.Generator, h: int, w: int, cell_px: float, amp: float
) -> np.ndarray:
    """Smooth random field (h, w) float32 with amplitude ``amp``, features ~``cell_px`` wide."""
    gh = max(2, int(np.ceil(h / cell_px)) + 1)
    gw = max(2, int(np.ceil(w / cell_px)) + 1)
    grid = rng.uniform(-amp, amp, (gh, gw)).astype(np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)


def surface_texture(width_px: int, height_px: int, px_per_m: float, seed, style: str = "wall"):
    """BGR uint8 texture of a surface; ``style`` is 'wall', 'floor', 'ceiling', 'box' or 'poster'.

    Shapes are placed by their physical size (``px_per_m``) so the density of corners per square
    metre is the same on every surface whatever its texture resolution.
    """
    if width_px <= 0 or height_px <= 0:
        raise TextureError(f"texture size {width_px}x{height_px} must be positive")
    rng = _rng(seed)
    h, w = int(height_px), int(width_px)
    colours = _palette(rng, 8, style)
    base = colours[0].astype(np.float32)
    img = np.empty((h, w, 3), np.float32)
    img[:] = base
    # Large soft blotches: the 'paint' of the surface, so plain areas are not perfectly flat.
    img += _low_frequency(rng, h, w, 0.8 * px_per_m, 30.0)[..., None]
    img = np.clip(img, 0, 255).astype(np.uint8)

    area_m2 = (h / px_per_m) * (w / px_per_m)
    # (physical size [m], shapes per m^2): few large shapes, many small ones.
    if style == "floor":
        scales = ((0.5, 0.8), (0.2, 4.0), (0.08, 18.0), (0.04, 30.0))
    elif style == "ceiling":
        scales = ((0.6, 0.5), (0.25, 2.0), (0.1, 6.0))
    elif style == "poster":
        scales = ((0.25, 6.0), (0.12, 25.0), (0.05, 60.0))
    else:
        scales = ((0.6, 0.8), (0.3, 3.0), (0.15, 10.0), (0.07, 30.0), (0.035, 40.0))
    for size_m, density in scales:
        count = int(rng.poisson(density * area_m2))
        size_px = size_m * px_per_m
        xs = rng.uniform(-0.2 * size_px, w, count)
        ys = rng.uniform(-0.2 * size_px, h, count)
        ws = size_px * rng.uniform(0.4, 1.6, count)
        hs = size_px * rng.uniform(0.4, 1.6, count)
        kinds = rng.random(count)
        cols = colours[rng.integers(0, len(colours), count)]
        # Alternate dark/bright shapes so edges keep contrast whatever the base colour.
        shade = rng.choice([0.35, 1.0, 1.6], count)
        thick = np.maximum(1, (size_px * rng.uniform(0.04, 0.15, count))).astype(int)
        for k in range(count):
            col = tuple(int(c) for c in np.clip(cols[k] * shade[k], 0, 255))
            x0, y0 = int(xs[k]), int(ys[k])
            x1, y1 = int(xs[k] + ws[k]), int(ys[k] + hs[k])
            if kinds[k] < 0.55:
                cv2.rectangle(img, (x0, y0), (x1, y1), col, -1)
            elif kinds[k] < 0.7:
                cv2.rectangle(img, (x0, y0), (x1, y1), col, int(thick[k]))
            elif kinds[k] < 0.85:
                centre = ((x0 + x1) // 2, (y0 + y1) // 2)
                axes = (max(1, (x1 - x0) // 2), max(1, (y1 - y0) // 2))
                cv2.ellipse(
                    img, centre, axes, float(rng.uniform(0, 180)), 0, 360, col, -1, cv2.LINE_AA
                )
            elif kinds[k] < 0.93:
                cv2.line(
                    img, (x0, y0), (x1, int(ys[k] - hs[k] * 0.5)), col, int(thick[k]), cv2.LINE_AA
                )
            else:
                # Printed text: many small high-contrast corners, like signs and labels.
                text = "".join(rng.choice(_TEXT_CHARS, int(rng.integers(2, 6))))
                scale = max(0.3, hs[k] / 30.0)
                cv2.putText(
                    img,
                    text,
                    (x0, y1),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    scale,
                    col,
                    max(1, int(scale * 2)),
                    cv2.LINE_AA,
                )

    # Fine grain (~1 cm) so close-up views keep some texture between the shapes.
    grain = _low_frequency(rng, h, w, max(2.0, 0.012 * px_per_m), 10.0)
    out = cv2.add(img.astype(np.int16), grain.astype(np.int16)[..., None].repeat(3, axis=2))
    return np.clip(out, 0, 255).astype(np.uint8)


def paste_poster(texture: np.ndarray, poster: np.ndarray, x_px: int, y_px: int) -> None:
    """Copy ``poster`` into ``texture`` (in place, clipped), its top-left corner at (x_px, y_px)."""
    h, w = texture.shape[:2]
    ph, pw = poster.shape[:2]
    x0, y0 = max(0, x_px), max(0, y_px)
    x1, y1 = min(w, x_px + pw), min(h, y_px + ph)
    if x1 <= x0 or y1 <= y0:
        return
    texture[y0:y1, x0:x1] = poster[y0 - y_px : y1 - y_px, x0 - x_px : x1 - x_px]


def poster_texture(width_px: int, height_px: int, px_per_m: float, seed) -> np.ndarray:
    """A framed high-contrast 'poster' (the patch that aliasing scenarios copy between places)."""
    tex = surface_texture(width_px, height_px, px_per_m, seed, style="poster")
    border = max(2, int(0.02 * px_per_m))
    cv2.rectangle(tex, (0, 0), (width_px - 1, height_px - 1), (20, 20, 20), border)
    return tex


def _aruco_dictionary():
    aruco = cv2.aruco
    return aruco.getPredefinedDictionary(aruco.DICT_4X4_50)


def aruco_marker_image(marker_id: int, side_px: int) -> np.ndarray:
    """Grey uint8 image of ArUco DICT_4X4_50 marker ``marker_id`` (black border included)."""
    if not 0 <= marker_id < 50:
        raise TextureError(f"ArUco DICT_4X4_50 has ids 0-49, got {marker_id}")
    dictionary = _aruco_dictionary()
    aruco = cv2.aruco
    if hasattr(aruco, "generateImageMarker"):  # OpenCV >= 4.7
        return aruco.generateImageMarker(dictionary, marker_id, side_px, borderBits=1)
    return aruco.drawMarker(dictionary, marker_id, side_px, borderBits=1)


def marker_face_layout(
    face_w_m: float, face_h_m: float, marker_m: float, centre_from_top_m: float
) -> tuple[int, int, int, int, int]:
    """Texel layout (width, height, marker x0, marker y0, marker side) of a robot body side.

    The marker is 6 modules wide (4x4 bits + border); the scale gives whole texels per module and
    the marker starts on a texel edge, so its corners lie exactly where the geometry says.
    """
    module_px = 20
    side = 6 * module_px
    px_per_m = side / marker_m
    w = round(face_w_m * px_per_m)
    h = round(face_h_m * px_per_m)
    x0 = round(0.5 * face_w_m * px_per_m - side / 2)
    y0 = round(centre_from_top_m * px_per_m - side / 2)
    if x0 < 0 or y0 < 0 or x0 + side > w or y0 + side > h:
        raise TextureError(
            f"a {marker_m} m marker does not fit on a {face_w_m} x {face_h_m} m face"
        )
    return w, h, x0, y0, side


def marker_face_texture(
    marker_id: int,
    face_w_m: float,
    face_h_m: float,
    marker_m: float,
    centre_from_top_m: float,
    body_bgr=(70, 70, 75),
) -> np.ndarray:
    """Texture of one robot body side: body colour, a white square and the marker in its middle."""
    w, h, x0, y0, side = marker_face_layout(face_w_m, face_h_m, marker_m, centre_from_top_m)
    tex = np.empty((h, w, 3), np.uint8)
    tex[:] = body_bgr
    margin = round(0.2 * side)  # white quiet zone around the marker (> 1 module)
    tex[max(0, y0 - margin) : y0 + side + margin, max(0, x0 - margin) : x0 + side + margin] = 255
    tex[y0 : y0 + side, x0 : x0 + side] = aruco_marker_image(marker_id, side)[..., None]
    return tex


def mip_pyramid(texture: np.ndarray, min_side: int = 8) -> list[np.ndarray]:
    """Pre-filtered levels (level 0 = full resolution) used to avoid aliasing at a distance."""
    levels = [np.ascontiguousarray(texture)]
    while len(levels) < MAX_LEVELS and min(levels[-1].shape[:2]) >= 2 * min_side:
        h, w = levels[-1].shape[:2]
        if h % 2 or w % 2:
            break  # odd sizes would shift texel centres between levels
        levels.append(cv2.pyrDown(levels[-1]))
    return levels
