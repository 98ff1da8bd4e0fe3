"""The configuration files and their one loader: config/*.yaml hold overrides of the defaults the
classes define (docs/configuration.md lists them all, generated from the classes), and a wrong
file, section or key is named."""

import os

import pytest
import yaml

from coop_slam.config import load_yaml_config
from coop_slam.errors import ConfigError
from coop_slam.markers import MarkerConfig
from coop_slam.team.config import ServerConfig
from coop_slam.uplink.config import UplinkConfig
from coop_slam.vo.config import VoConfig
from helpers import REPO

SECTIONS = {  # file -> section -> config class
    "server.yaml": {"server": ServerConfig},
    "client.yaml": {"vo": VoConfig, "markers": MarkerConfig, "uplink": UplinkConfig},
}


@pytest.mark.parametrize("name", sorted(SECTIONS))
def test_config_files_load_their_sections(name):
    path = os.path.join(REPO, "config", name)
    with open(path, encoding="utf-8") as fh:
        assert set(yaml.safe_load(fh)) == set(SECTIONS[name]), f"{name}: unexpected sections"
    for section, cls in SECTIONS[name].items():
        load_yaml_config(cls, path, section)


def test_the_configuration_page_is_generated_from_the_classes_and_documents_every_key():
    from coop_slam.tools.config_reference import PAGE, render

    text = render()
    with open(PAGE, encoding="utf-8") as fh:
        assert fh.read() == text, "docs/configuration.md: run scripts/python_tool config_reference"
    undocumented = [
        row for row in text.splitlines() if row.startswith("| `") and row.endswith("|  |")
    ]
    assert not undocumented, f"keys without a note in their class: {undocumented[:5]}"


def test_per_camera_values_resolve_and_a_bad_one_is_named():
    """A monocular camera's values (VoConfig.sensors.mono) resolve onto the sections; a ground
    robot's monocular camera keeps the common local BA window; an unknown key is named."""
    from coop_slam.config import with_values

    cfg = VoConfig()
    mono = cfg.for_sensor("mono")
    assert (mono.keyframes.ref_ratio, mono.ba.window) == (0.9, 16)
    assert cfg.for_sensor("rgbd").keyframes.ref_ratio == cfg.keyframes.ref_ratio == 0.75
    ground = with_values(cfg, {"planar": {"enabled": True}}).for_sensor("mono")
    assert ground.ba.window == cfg.ba.window and ground.keyframes.ref_ratio == 0.9
    stereo = with_values(cfg, {"sensors": {"stereo": {"features": {"n_features": 2000}}}})
    assert stereo.for_sensor("stereo").features.n_features == 2000
    assert stereo.for_sensor("mono").keyframes.ref_ratio == 0.9  # merged with the defaults
    with pytest.raises(ConfigError, match="vo.sensors.mono.keyframes.ref_rato"):
        with_values(cfg, {"sensors": {"mono": {"keyframes": {"ref_rato": 0.5}}}})
    with pytest.raises(ConfigError, match="unknown camera kind"):
        with_values(cfg, {"sensors": {"lidar": {}}})


def test_overrides_change_single_keys_of_a_section(tmp_path):
    path = os.path.join(REPO, "config", "server.yaml")
    cfg = load_yaml_config(ServerConfig, path, "server", {"rendezvous": {"window_s": 3.0}})
    assert cfg.rendezvous.window_s == 3.0
    assert cfg.rendezvous.min_separation_m == ServerConfig().rendezvous.min_separation_m
    assert load_yaml_config(ServerConfig, "", "server", {"robots": [3]}).robots == [3]


def test_bad_files_and_keys_are_named(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_yaml_config(VoConfig, str(tmp_path / "nope.yaml"), "vo")
    bad = tmp_path / "bad.yaml"
    bad.write_text("vo: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_yaml_config(VoConfig, str(bad), "vo")
    flat = tmp_path / "flat.yaml"
    flat.write_text("features:\n  n_features: 500\n")  # vo keys without their section
    with pytest.raises(ConfigError, match="under 'vo:'"):
        load_yaml_config(VoConfig, str(flat), "vo")
    old = tmp_path / "old.yaml"
    old.write_text("vo:\n  n_features: 500\n")  # a key of before the sections: named
    with pytest.raises(ConfigError, match="unknown config key.s. vo.n_features for VoConfig"):
        load_yaml_config(VoConfig, str(old), "vo")
    typo = tmp_path / "typo.yaml"
    typo.write_text("server:\n  rendezvous:\n    window: 1.0\n")
    with pytest.raises(ConfigError, match="rendezvous.window"):
        load_yaml_config(ServerConfig, str(typo), "server")


@pytest.mark.parametrize(
    "text, named",
    [
        ("vo:\n  tracking: {search_radius_px: .inf}\n", "search radii must be finite"),
        ("vo:\n  mapping: {fuse_radius_px: .inf}\n", "fuse_radius_px must be finite"),
        ("vo:\n  mapping: {fuse_radius_px: 0.0}\n", "fuse_radius_px must be finite and > 0"),
    ],
)
def test_projection_search_radii_must_be_finite(tmp_path, text, named):
    """An infinite radius would find no candidate (the search's grid cannot span it)."""
    path = tmp_path / "vo.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=named):
        load_yaml_config(VoConfig, str(path), "vo")
