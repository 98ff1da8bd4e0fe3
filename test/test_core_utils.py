"""Geometry helpers, the config loader, descriptor utilities and keyframe validation."""

from dataclasses import dataclass, field

import numpy as np
import pytest

from coop_slam.config import load_config, require
from coop_slam.descriptors import DescriptorError, hamming_matrix, hamming_rows, match_ratio
from coop_slam.errors import ConfigError
from coop_slam.geometry import (
    GeometryError,
    check_se3,
    invert,
    quat_from_se3,
    se3_from_quat,
    transform_error,
    transform_points,
)
from coop_slam.wire.record import KeyframeError
from helpers import make_keyframe


def test_se3_round_trip_and_error():
    T = se3_from_quat([1, 2, 3], [0.1, 0.2, 0.3, 0.9])
    t, q = quat_from_se3(T)
    assert np.allclose(se3_from_quat(t, q), T)
    assert np.allclose(invert(T) @ T, np.eye(4))
    p = np.array([[1.0, 0, 0]])
    assert np.allclose(transform_points(invert(T), transform_points(T, p)), p)
    dt, dr = transform_error(T, T)
    assert dt < 1e-12 and dr < 1e-6
    with pytest.raises(GeometryError):
        se3_from_quat([0, 0, 0], [0, 0, 0, 0])
    bad = T.copy()
    bad[0, 0] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        check_se3(bad)


@dataclass
class _Cfg:
    rate: float = 1.0
    name: str = "x"
    ids: list[int] = field(default_factory=list)

    def validate(self):
        require(self.rate > 0, "rate must be > 0")


def test_config_loader_types_and_unknown_keys():
    cfg = load_config(_Cfg, {"rate": 2, "ids": [1, 2]})
    assert cfg.rate == 2.0 and cfg.ids == [1, 2]
    with pytest.raises(ConfigError, match="unknown config key"):
        load_config(_Cfg, {"rte": 1})
    with pytest.raises(ConfigError, match="expected a number"):
        load_config(_Cfg, {"rate": "fast"})
    with pytest.raises(ConfigError, match="rate must be > 0"):
        load_config(_Cfg, {"rate": -1})


def test_descriptor_matching():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    b = a[::-1].copy()
    b[:, 0] ^= 3
    m = match_ratio(a, b)
    assert len(m) == 200 and np.all(m[:, 1] == 199 - m[:, 0])
    assert hamming_matrix(a[:1], b[-1:])[0, 0] == 2
    assert np.all(hamming_rows(a, b[::-1]) == 2)
    with pytest.raises(DescriptorError, match="multiple of 32"):
        hamming_matrix(np.zeros(33, np.uint8), a)


def test_keyframe_validation_accepts_good_and_names_problems():
    kf = make_keyframe()
    kf.validate(known_robots={1, 2})
    assert np.isnan(kf.points_cam()).sum() == 0
    assert np.isfinite(kf.map_points_per_keypoint()).all(axis=1).sum() == 25
    with pytest.raises(KeyframeError, match="unknown"):
        make_keyframe(robot_id=7).validate(known_robots={1, 2})
    kf = make_keyframe()
    kf.depths_m[3] = np.nan
    with pytest.raises(KeyframeError, match="depths_m contains NaN"):
        kf.validate()
    kf = make_keyframe()
    kf.descriptors = kf.descriptors[:-1]
    with pytest.raises(KeyframeError, match="descriptors"):
        kf.validate()
    kf = make_keyframe()
    kf.map_points = kf.map_points[:-1]
    with pytest.raises(KeyframeError, match="map_points"):
        kf.validate()
    kf = make_keyframe()
    kf.T_map_cam = np.full((4, 4), np.nan)
    with pytest.raises(KeyframeError, match="NaN"):
        kf.validate()


def test_throttled_progress_reports_the_first_and_last_call_and_not_every_one():
    from coop_slam.tools.progress import throttled

    seen = []
    progress = throttled(lambda done, total: seen.append(done), period_s=3600.0)
    for i in range(1, 101):
        progress(i, 100)
    assert seen == [1, 100]


def test_merge_overrides_changes_keys_not_sections():
    from coop_slam.config import merge_overrides

    values = {"global_ba": {"iterations": 10, "after_merge": True}, "optimize_every": 5}
    out = merge_overrides(values, {"global_ba": {"planar_motion": True}, "optimize_every": 2})
    assert out == {
        "global_ba": {"iterations": 10, "after_merge": True, "planar_motion": True},
        "optimize_every": 2,
    }
    assert values["global_ba"] == {"iterations": 10, "after_merge": True}  # input untouched
