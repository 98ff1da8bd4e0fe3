"""``scripts/make_markers``: the ArUco markers to print and mount on one's own robots -- one PDF
page per robot, its marker's black square exactly ``markers.marker_size_m`` wide when printed at
100 % (no "fit to page"), in the dictionary the clients look for, id = robot id, with what to
check written under it."""

from __future__ import annotations

import argparse
import os
import sys

import cv2
import numpy as np

from ..config import load_yaml_config
from ..errors import CoopSlamError
from ..markers import MarkerConfig

MARGIN_M = 0.02  # the least white around the marker's black square [m]
TEXT_M = 0.05  # room for the label and the scale bar under it [m]
SCALE_BAR_M = 0.05  # a bar to check the print with a ruler [m]
INCH_M = 0.0254


class MarkerSheetError(CoopSlamError):
    """A marker cannot be made (an id outside the dictionary, a bad size or folder)."""


def marker_image(config: MarkerConfig, marker_id: int, side_px: int = 600) -> np.ndarray:
    """Grey uint8 image of marker ``marker_id`` of ``config.dictionary``, black square edge to
    edge (``side_px`` wide)."""
    aruco = cv2.aruco
    dictionary = aruco.getPredefinedDictionary(getattr(aruco, config.dictionary))
    count = dictionary.bytesList.shape[0]
    if not 0 <= marker_id < count:
        raise MarkerSheetError(
            f"robot {marker_id}: {config.dictionary} has marker ids 0-{count - 1} (a robot's "
            "marker id is its robot id): choose a larger dictionary (markers.dictionary)"
        )
    if hasattr(aruco, "generateImageMarker"):  # OpenCV >= 4.7
        return aruco.generateImageMarker(dictionary, marker_id, side_px, borderBits=1)
    return aruco.drawMarker(dictionary, marker_id, side_px, borderBits=1)


def quiet_zone_m(config: MarkerConfig) -> float:
    """White around the black square: one of the marker's cells at least. Seen against a
    darker body a thinner one (2 cm of a 25 cm marker) was not detected at all; one cell was at
    every size and background tried (test_make_markers)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, config.dictionary))
    return max(MARGIN_M, config.marker_size_m / (dictionary.markerSize + 2))


def write_sheet(path: str, config: MarkerConfig, robot_id: int) -> tuple[float, float]:
    """One robot's marker page (PDF) at its true size; returns the page (width, height) [m]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    size, margin = config.marker_size_m, quiet_zone_m(config)
    width, height = size + 2 * margin, size + 2 * margin + TEXT_M
    fig = plt.figure(figsize=(width / INCH_M, height / INCH_M))
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_xlim(0, width)
    ax.set_ylim(0, height)
    ax.axis("off")
    image = marker_image(config, robot_id)
    bottom = TEXT_M + margin  # the label under the quiet zone, not in it
    extent = (margin, margin + size, bottom, bottom + size)
    ax.imshow(image, cmap="gray", vmin=0, vmax=255, extent=extent, interpolation="nearest")
    fontsize = max(4.0, 0.12 * size / INCH_M * 10)
    ax.text(
        width / 2,
        0.75 * TEXT_M,
        f"robot_{robot_id}: {config.dictionary} id {robot_id}, black square {100 * size:g} cm "
        "- print at 100 %, measure it",
        ha="center",
        va="center",
        fontsize=fontsize,
    )
    x, y, z = config.base_marker()[:3, 3]
    ax.text(
        width / 2,
        0.45 * TEXT_M,
        f"mount: flat on the robot's front, centre at x {x:.3f}, y {y:.3f}, z {z:.3f} m in "
        "base_link (markers.T_base_marker)",
        ha="center",
        va="center",
        fontsize=0.8 * fontsize,
    )
    # A ruler check of the print's scale: the bar is SCALE_BAR_M long, ticks each centimetre.
    bar = min(SCALE_BAR_M, size)
    y0 = 0.2 * TEXT_M
    ax.plot([margin, margin + bar], [y0, y0], color="black", linewidth=1.5)
    for k in range(int(round(bar * 100)) + 1):
        ax.plot([margin + k / 100] * 2, [y0, y0 + 0.003], color="black", linewidth=0.6)
    ax.text(
        margin + bar + 0.005,
        y0,
        f"{100 * bar:g} cm",
        ha="left",
        va="center",
        fontsize=0.8 * fontsize,
    )
    fig.savefig(path)
    plt.close(fig)
    return width, height


def main(argv=None) -> int:
    """``scripts/make_markers --robots 1,2,3 [--config FILE] [--out DIR]``"""
    p = argparse.ArgumentParser(
        prog="scripts/make_markers",
        description="The ArUco markers to print and mount on your robots: one PDF per robot "
        "(marker id = robot id) at the size and in the dictionary of the clients' markers "
        "section. Print at 100 % and check the black square's side with a ruler: a marker "
        "printed smaller than configured puts the other robot too far away, silently.",
    )
    p.add_argument("--robots", required=True, help="robot ids, comma-separated: 1,2,3")
    p.add_argument("--config", help="client YAML (its markers section; default: the defaults)")
    p.add_argument("--out", default="markers", help="folder for the PDFs (default: ./markers)")
    args = p.parse_args(argv)
    try:
        try:
            robots = [int(r) for r in args.robots.split(",") if r.strip()]
        except ValueError:
            raise MarkerSheetError(f"--robots {args.robots}: expected ids like 1,2,3") from None
        config = load_yaml_config(MarkerConfig, args.config, "markers")
        config.validate()
        os.makedirs(args.out, exist_ok=True)
        for r in robots:
            path = os.path.join(args.out, f"marker_robot_{r}.pdf")
            w, h = write_sheet(path, config, r)
            print(
                f"[make_markers] {path}: {config.dictionary} id {r}, black square "
                f"{100 * config.marker_size_m:g} cm, page {100 * w:.1f} x {100 * h:.1f} cm"
            )
    except CoopSlamError as exc:
        print(f"[make_markers] ERROR: {exc}", file=sys.stderr)
        return 2
    print(
        "[make_markers] mount each flat on its robot's front, its centre where "
        "markers.T_base_marker says (in base_link), and set markers.body_size_m to the robot's "
        "size: both go into that robot's client configuration"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
