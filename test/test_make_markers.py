"""scripts/make_markers: a robot's marker sheet at its true size, in the clients' dictionary,
id = robot id; an id the dictionary lacks is refused with what to do."""

import re

import cv2
import numpy as np
import pytest

from coop_slam.markers import MarkerConfig
from coop_slam.tools.make_markers import TEXT_M, MarkerSheetError, main, marker_image, quiet_zone_m


def test_a_marker_sheet_prints_the_black_square_at_its_configured_size(tmp_path):
    cfg = tmp_path / "client.yaml"
    cfg.write_text("markers:\n  marker_size_m: 0.18\n  dictionary: DICT_5X5_100\n")
    assert main(["--robots", "3,7", "--config", str(cfg), "--out", str(tmp_path / "m")]) == 0
    pdf = (tmp_path / "m" / "marker_robot_7.pdf").read_bytes()
    box = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", pdf)
    width_m, height_m = (float(v) / 72 * 0.0254 for v in box.groups())
    margin = quiet_zone_m(MarkerConfig(marker_size_m=0.18, dictionary="DICT_5X5_100"))
    assert margin == pytest.approx(0.18 / 7)  # one cell of a 5x5 marker (with its border)
    assert width_m == pytest.approx(0.18 + 2 * margin, abs=1e-4)
    assert height_m == pytest.approx(0.18 + 2 * margin + TEXT_M, abs=1e-4)
    # the image is the marker the clients detect as robot 7
    config = MarkerConfig(marker_size_m=0.18, dictionary="DICT_5X5_100")
    image = np.pad(marker_image(config, 7, 300), 60, constant_values=255)
    aruco = cv2.aruco
    dictionary = aruco.getPredefinedDictionary(aruco.DICT_5X5_100)
    if hasattr(aruco, "ArucoDetector"):
        _, ids, _ = aruco.ArucoDetector(dictionary).detectMarkers(image)
    else:
        _, ids, _ = aruco.detectMarkers(image, dictionary)
    assert ids is not None and ids.ravel().tolist() == [7]


def test_an_id_the_dictionary_lacks_is_refused(tmp_path, capsys):
    with pytest.raises(MarkerSheetError, match="ids 0-49"):
        marker_image(MarkerConfig(), 60)
    assert main(["--robots", "60", "--out", str(tmp_path)]) == 2
    assert "choose a larger dictionary" in capsys.readouterr().err
    assert main(["--robots", "one", "--out", str(tmp_path)]) == 2


@pytest.mark.parametrize("background", [180, 40])
@pytest.mark.parametrize("distance", [0.7, 1.6])
def test_a_printed_marker_seen_by_a_camera_is_placed_at_its_true_distance(background, distance):
    """The sheet's marker printed at the configured 0.18 m with its quiet zone, on a robot body
    (grey or dark) 0.7 or 1.6 m from a camera and turned 20 degrees, is detected as robot 4 at
    its true place."""
    from coop_slam.markers import MarkerDetector

    config = MarkerConfig(marker_size_m=0.18)
    side_px, margin = 600, quiet_zone_m(config)
    quiet = int(round(side_px * margin / config.marker_size_m))
    printed = np.pad(marker_image(config, 4, side_px), quiet, constant_values=255)
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    half = config.marker_size_m / 2 + margin
    corners_m = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    a = np.radians(20.0)  # the sheet turned 20 degrees about the vertical
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    pts = (R @ np.c_[corners_m, np.zeros(4)].T).T + [0.1, 0.05, distance]
    uv = (K @ pts.T).T
    uv = (uv[:, :2] / uv[:, 2:]).astype(np.float32)
    n = printed.shape[0]
    src = np.float32([[0, 0], [n, 0], [n, n], [0, n]])
    H = cv2.getPerspectiveTransform(src, uv)
    view = cv2.warpPerspective(printed, H, (640, 480), borderValue=background, flags=cv2.INTER_AREA)
    (seen,) = MarkerDetector(config).detect(view, K)
    assert seen.marker_id == 4
    assert np.linalg.norm(seen.T_cam_marker[:3, 3] - [0.1, 0.05, distance]) < 0.01 * distance


def test_the_sheets_label_and_scale_bar_stay_out_of_the_quiet_zone(tmp_path):
    from coop_slam.tools.make_markers import write_sheet

    config = MarkerConfig(marker_size_m=0.2)
    width_m, height_m = write_sheet(str(tmp_path / "sheet.png"), config, 3)
    sheet = cv2.imread(str(tmp_path / "sheet.png"), cv2.IMREAD_GRAYSCALE)
    px_per_m = sheet.shape[0] / height_m
    margin = quiet_zone_m(config)

    def band(lo_m, hi_m):  # rows between these heights above the page's bottom edge
        rows = sheet.shape[0] - 1 - np.arange(int(lo_m * px_per_m), int(hi_m * px_per_m))
        return sheet[rows]

    # white all round the black square, below it too (the label sits under the quiet zone)
    assert band(TEXT_M + 0.1 * margin, TEXT_M + 0.9 * margin).min() > 240
    assert band(height_m - 0.9 * margin, height_m - 0.1 * margin).min() > 240
    assert band(0.0, TEXT_M).min() < 50  # the label and the scale bar are there
