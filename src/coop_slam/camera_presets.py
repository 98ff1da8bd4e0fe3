"""Camera presets: what differs for a known camera (features, keyframe rule, depth units, ranges),
as ORB-SLAM ships settings per camera, in ``config/cameras/<name>.yaml``.

A preset has the client configuration's sections (``vo``, ``markers``, ``uplink``), layered over
the client's YAML and under its node parameters, and a ``camera`` block: ``description``, the
``sensor`` it is for, and the ``depth_scale`` of its driver's 16UC1 depth images (units per
metre). ``client.launch camera:=NAME`` (or a YAML path) picks one; ``scripts/demo`` picks the
preset of a dataset folder by itself (:func:`preset_for_dataset`).
"""

from __future__ import annotations

import os
from typing import Any

from .config import merge_overrides, read_yaml_mapping
from .errors import ConfigError

PRESETS_DIR = os.path.normpath(
    os.path.join(os.path.dirname(os.path.realpath(__file__)), "..", "..", "config", "cameras")
)
SECTIONS = ("vo", "markers", "uplink")
CAMERA_KEYS = ("description", "sensor", "depth_scale")


def preset_names() -> list[str]:
    if not os.path.isdir(PRESETS_DIR):
        return []
    return sorted(f[:-5] for f in os.listdir(PRESETS_DIR) if f.endswith(".yaml"))


def load_preset(name_or_path: str) -> dict[str, Any]:
    """A preset by name (``config/cameras/NAME.yaml``) or path; ``""`` = none (empty)."""
    if not name_or_path:
        return {}
    path = name_or_path
    if not (name_or_path.endswith((".yaml", ".yml")) or os.sep in name_or_path):
        path = os.path.join(PRESETS_DIR, f"{name_or_path}.yaml")
        if not os.path.isfile(path):
            raise ConfigError(
                f"unknown camera preset '{name_or_path}'; presets: {', '.join(preset_names())} "
                "(or a YAML file's path)"
            )
    data = read_yaml_mapping(path, "camera preset")
    unknown = sorted(set(data) - set(SECTIONS) - {"camera"})
    if unknown:
        raise ConfigError(
            f"camera preset {path}: unknown section(s) {unknown}; sections: camera, "
            f"{', '.join(SECTIONS)}"
        )
    camera = data.get("camera") or {}
    bad = sorted(set(camera) - set(CAMERA_KEYS))
    if bad:
        raise ConfigError(f"camera preset {path}: unknown camera key(s) {bad}; {CAMERA_KEYS}")
    return data


def layered(preset: dict, section: str, overrides: dict | None) -> dict:
    """A section's overrides: the preset's, with the node's own on top."""
    return merge_overrides(dict(preset.get(section) or {}), dict(overrides or {}))


def preset_for_dataset(folder: str) -> str:
    """The preset of a dataset folder, by its layout and name ('' when none fits)."""
    name = os.path.basename(os.path.normpath(folder)).lower()
    parts = os.path.normpath(folder).lower().split(os.sep)
    if os.path.isfile(os.path.join(folder, "calib.txt")) and os.path.isdir(
        os.path.join(folder, "image_0")
    ):
        return "kitti"
    if os.path.isdir(os.path.join(folder, "mav0")) or "euroc" in name:
        return "euroc"
    for k in (1, 2, 3):
        if any(f"freiburg{k}" in p for p in parts):
            return f"tum_fr{k}"
    if "kitchen" in name or "7scenes" in name or "7-scenes" in name:
        return "kinect_v1"
    return ""
