"""Camera presets: every one loads into the client's configuration, a dataset folder picks its
own, and a wrong name or section is refused by name."""

import os

import pytest

from coop_slam.camera_presets import layered, load_preset, preset_for_dataset, preset_names
from coop_slam.config import load_config
from coop_slam.errors import ConfigError
from coop_slam.markers import MarkerConfig
from coop_slam.uplink.config import UplinkConfig
from coop_slam.vo.config import VoConfig

SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")


@pytest.mark.parametrize("name", preset_names())
def test_every_preset_loads_into_the_clients_configuration(name):
    preset = load_preset(name)
    assert preset["camera"]["sensor"] in ("rgbd", "stereo", "mono")
    for section, cls in (("vo", VoConfig), ("markers", MarkerConfig), ("uplink", UplinkConfig)):
        load_config(cls, layered(preset, section, {}), prefix=f"{section}.")


def test_the_presets_named_by_the_issue_are_there():
    assert {
        "kitti",
        "euroc",
        "tum_fr1",
        "tum_fr2",
        "tum_fr3",
        "kinect_v1",
        "realsense_d435",
    } <= set(preset_names())


def test_the_nodes_own_values_go_over_the_presets():
    preset = load_preset("kitti")
    vo = load_config(VoConfig, layered(preset, "vo", {"features": {"n_features": 1500}}))
    assert vo.features.n_features == 1500 and vo.features.n_detect == 5000


def test_a_dataset_folder_picks_its_preset(tmp_path):
    kitti = tmp_path / "sequences" / "00"
    (kitti / "image_0").mkdir(parents=True)
    (kitti / "calib.txt").write_text("")
    (tmp_path / "rgbd_dataset_freiburg2_desk").mkdir()
    (tmp_path / "V1_01" / "mav0").mkdir(parents=True)
    assert preset_for_dataset(str(kitti)) == "kitti"
    assert preset_for_dataset(str(tmp_path / "rgbd_dataset_freiburg2_desk")) == "tum_fr2"
    assert preset_for_dataset(str(tmp_path / "V1_01")) == "euroc"
    assert preset_for_dataset(str(tmp_path / "redkitchen_0000_0599")) == "kinect_v1"
    assert preset_for_dataset(str(tmp_path)) == ""


def test_bad_presets_are_refused_by_name(tmp_path):
    with pytest.raises(ConfigError, match="unknown camera preset 'kiti'.*kitti"):
        load_preset("kiti")
    bad = tmp_path / "bad.yaml"
    bad.write_text("vo: {}\nlidar: {}\n")
    with pytest.raises(ConfigError, match="unknown section.*lidar"):
        load_preset(str(bad))
    bad.write_text("camera: {fps: 30}\n")
    with pytest.raises(ConfigError, match="unknown camera key.*fps"):
        load_preset(str(bad))
    assert load_preset("") == {}
