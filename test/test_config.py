"""The configuration files and their one loader: config/*.yaml document the defaults (they must
not drift from the config classes), and a wrong file, section or key is named."""

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
def test_config_files_hold_the_config_classes_defaults(name):
    path = os.path.join(REPO, "config", name)
    with open(path, encoding="utf-8") as fh:
        assert set(yaml.safe_load(fh)) == set(SECTIONS[name]), f"{name}: unexpected sections"
    for section, cls in SECTIONS[name].items():
        assert load_yaml_config(cls, path, section) == cls(), f"{name}: {section} != defaults"


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
    flat.write_text("n_features: 500\n")  # vo keys without their section
    with pytest.raises(ConfigError, match="under 'vo:'"):
        load_yaml_config(VoConfig, str(flat), "vo")
    typo = tmp_path / "typo.yaml"
    typo.write_text("server:\n  rendezvous:\n    window: 1.0\n")
    with pytest.raises(ConfigError, match="rendezvous.window"):
        load_yaml_config(ServerConfig, str(typo), "server")
