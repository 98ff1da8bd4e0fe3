"""scripts/print_markers: a robot's marker sheet at its true size, in the clients' dictionary,
id = robot id; an id the dictionary lacks is refused with what to do."""

import re

import cv2
import numpy as np
import pytest

from coop_slam.markers import MarkerConfig
from coop_slam.tools.print_markers import MARGIN_M, TEXT_M, MarkerSheetError, main, marker_image


def test_a_marker_sheet_prints_the_black_square_at_its_configured_size(tmp_path):
    cfg = tmp_path / "client.yaml"
    cfg.write_text("markers:\n  marker_size_m: 0.18\n  dictionary: DICT_5X5_100\n")
    assert main(["--robots", "3,7", "--config", str(cfg), "--out", str(tmp_path / "m")]) == 0
    pdf = (tmp_path / "m" / "marker_robot_7.pdf").read_bytes()
    box = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", pdf)
    width_m, height_m = (float(v) / 72 * 0.0254 for v in box.groups())
    assert width_m == pytest.approx(0.18 + 2 * MARGIN_M, abs=1e-4)
    assert height_m == pytest.approx(0.18 + 2 * MARGIN_M + TEXT_M, abs=1e-4)
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
