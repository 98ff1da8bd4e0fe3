"""The recorded RViz view framed on the run's map (coop_slam.tools.framing, scripts/demo's per-run
RViz config): orbit-view fitting against RViz's camera maths, ground truth moved into `world`,
depth back-projection, and the config copy."""

from __future__ import annotations

import math
import os
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from coop_slam.geometry import R_BASE_OPTICAL as R_BODY_OPTICAL
from coop_slam.tools import framing as F

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TEMPLATE = os.path.join(REPO, "rviz", "coop_slam.rviz")
ASPECT = 16.0 / 9.0


def _se3(R=None, t=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _box(lo, hi):
    return np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )


def test_eye_is_rviz_orbit_camera():
    # OrbitViewController::updateCamera: eye = focal + d (cos yaw cos pitch, sin yaw cos pitch,
    # sin pitch)
    v = F.OrbitView((1.0, 2.0, 0.5), 10.0, 1.15, 4.712389)
    expected = np.array([1.0, 2.0, 0.5]) + 10.0 * np.array(
        [math.cos(4.712389) * math.cos(1.15), math.sin(4.712389) * math.cos(1.15), math.sin(1.15)]
    )
    np.testing.assert_allclose(v.eye(), expected, atol=1e-12)
    # the focal point is the picture's centre, world z points up on the screen
    np.testing.assert_allclose(F.project(v, [v.focal]), [[0.0, 0.0]], atol=1e-12)
    above = F.project(v, [np.add(v.focal, [0.0, 0.0, 1.0])])[0]
    assert above[1] > 0 and abs(above[0]) < 1e-12


def test_fit_closed_form():
    """Two points at +-w along screen x at the focal point: distance = w / (fill tan(h/2))."""
    w, fill, fov = 3.0, 0.9, math.pi / 4
    v = F.fit_orbit_view(
        [[-w, 0.0, 0.0], [w, 0.0, 0.0]], pitch=1.15, yaws=(1.5 * math.pi,), fill=fill, fov=fov
    )
    np.testing.assert_allclose(v.focal, (0.0, 0.0, 0.0), atol=1e-9)
    assert v.distance == pytest.approx(w / (fill * math.tan(fov / 2) * ASPECT), rel=1e-9)
    np.testing.assert_allclose(np.abs(F.project(v, [[w, 0, 0]])), [[fill, 0.0]], atol=1e-9)


@pytest.mark.parametrize(
    "lo, hi",
    [((-1.4, 0.0, 0.0), (8.6, 6.0, 2.5)), ((0.9, -3.0, -0.6), (3.3, 1.4, 1.5))],
    ids=["12m-world", "3m-kitchen"],
)
def test_fit_fills_and_centres(lo, hi):
    pts = _box(lo, hi)
    v = F.fit_orbit_view(pts)
    uv = F.project(v, pts)
    assert np.all(np.abs(uv) <= F.FILL + 1e-6)  # everything inside the picture
    # filled on the limiting side, centred on both
    assert max(uv[:, 0].max(), uv[:, 1].max()) == pytest.approx(F.FILL, abs=1e-3)
    assert uv[:, 0].max() + uv[:, 0].min() == pytest.approx(0.0, abs=0.02)
    assert uv[:, 1].max() + uv[:, 1].min() == pytest.approx(0.0, abs=0.02)


def test_same_shape_fills_the_same_at_any_size():
    kitchen = _box((0.0, 0.0, 0.0), (3.0, 2.0, 1.0))
    world = kitchen * 4.0
    vk, vw = F.fit_orbit_view(kitchen), F.fit_orbit_view(world)
    assert vw.distance == pytest.approx(4.0 * vk.distance, rel=1e-6)
    np.testing.assert_allclose(F.project(vk, kitchen), F.project(vw, world), atol=1e-6)
    assert vk.distance < 8.0  # the old fixed view: 18 m


def test_yaw_turns_for_the_long_side():
    long_x = _box((0.0, 0.0, 0.0), (10.0, 3.0, 0.5))
    long_y = _box((0.0, 0.0, 0.0), (3.0, 10.0, 0.5))
    assert F.fit_orbit_view(long_x).yaw == pytest.approx(F.DEFAULT_YAW_RAD)
    # a quarter turn: the long side across the wide picture, and closer
    v = F.fit_orbit_view(long_y)
    assert v.yaw == pytest.approx(F.DEFAULT_YAW_RAD - math.pi / 2)
    assert v.distance < F.fit_orbit_view(long_y, yaws=(F.DEFAULT_YAW_RAD,)).distance * 0.95
    # a square: the preferred yaw
    square = _box((0.0, 0.0, 0.0), (5.0, 5.0, 0.5))
    assert F.fit_orbit_view(square).yaw == pytest.approx(F.DEFAULT_YAW_RAD)


def test_fit_rejects_nothing_to_frame():
    with pytest.raises(F.FramingError):
        F.fit_orbit_view(np.zeros((0, 3)))
    with pytest.raises(F.FramingError):
        F.fit_orbit_view([[np.nan, 0.0, 0.0]])


def test_ground_truth_in_world():
    """world = robot 1's map = its body at its first frame: T_base_cam @ inv(G1_0) @ G."""
    T_base_cam = _se3(R_BODY_OPTICAL, (0.1, 0.0, 0.5))
    G0 = _se3(_rot_z(0.7) @ R_BODY_OPTICAL, (5.0, -2.0, 0.5))  # level camera in the dataset
    ahead = G0 @ _se3(t=(0.0, 0.0, 1.0))  # 1 m along its optical axis
    aside = _se3(_rot_z(0.7 + math.pi / 2) @ R_BODY_OPTICAL, (5.0, -2.0, 0.5)) @ _se3(
        t=(0.0, 0.0, 2.0)
    )
    gts = {2: (np.zeros(1), aside[None]), 1: (np.zeros(3), np.stack([G0, ahead, ahead]))}
    T = F.T_world_gt(gts, T_base_cam)
    poses = F.world_camera_poses(gts, T)
    assert poses.shape == (4, 4, 4)  # robot 1's three poses, then robot 2's
    np.testing.assert_allclose(poses[0], T_base_cam, atol=1e-12)
    # forward = base x; robot 2 looks left of robot 1 (base +y), 2 m
    np.testing.assert_allclose(poses[1][:3, 3], [1.1, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(poses[3][:3, 3], [0.1, 2.0, 0.5], atol=1e-12)
    # the optical axis of robot 1's first camera runs along world x, level
    np.testing.assert_allclose(poses[0][:3, 2], [1.0, 0.0, 0.0], atol=1e-12)


def test_ground_truth_needs_the_world_robot():
    G = np.eye(4)[None]
    with pytest.raises(F.FramingError, match="robot 1"):
        F.T_world_gt({1: (np.zeros(0), np.zeros((0, 4, 4))), 2: (np.zeros(1), G)})
    with pytest.raises(F.FramingError):
        F.T_world_gt({})
    # frames without ground truth (NaN) are skipped
    nan_first = np.stack([np.full((4, 4), np.nan), _se3(t=(1.0, 0.0, 0.0))])
    T = F.T_world_gt({1: (np.zeros(2), nan_first)})
    np.testing.assert_allclose(T[:3, 3], [-1.0, 0.0, 0.0])


def test_backproject_and_look_ahead():
    K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]])
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:24] = 9.0  # beyond the clients' 6 m: left out
    pts = F.backproject(depth, K, _se3(t=(0.0, 0.0, 1.0)), step=8)
    assert len(pts) == 3 * 8  # rows 28, 36, 44 x 8 columns
    np.testing.assert_allclose(pts[:, 2], 3.0)
    assert pts[:, 0].min() == pytest.approx((4 - 32) * 2.0 / 100.0)
    ahead = F.look_ahead_points(np.eye(4)[None], 2.0, (0.5, 0.25))
    np.testing.assert_allclose(ahead[0], [0.0, 0.0, 2.0])
    np.testing.assert_allclose(np.abs(ahead[1:]), [[1.0, 0.5, 2.0]] * 4)


def test_seen_depth_points_and_framing_points():
    K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]])
    frames = [SimpleNamespace(depth_path=f"d{i}.png") for i in range(5)]
    poses = np.stack([_se3(t=(float(i), 0.0, 0.0)) for i in range(5)])
    poses[2] = np.nan  # no ground truth: skipped
    seq = SimpleNamespace(
        frames=frames,
        camera=SimpleNamespace(K=K),
        frame_poses=lambda: poses,
        load_depth_m=lambda f: np.full((48, 64), 1.5, np.float32),
    )
    pts, used = F.seen_depth_points([SimpleNamespace(sequence=seq)], np.eye(4), frames=3)
    assert used == 3  # frames 0, 3 (middle of the four with ground truth), 4
    np.testing.assert_allclose(np.unique(pts[:, 2]), [1.5])
    assert pts[:, 0].min() < 0.0 < 4.0 < pts[:, 0].max()
    both = F.framing_points(poses[[0, 4]], pts)
    np.testing.assert_allclose(both[:2], [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    assert len(both) <= 2 + len(pts)
    # without depth: camera positions and 5 look-ahead points each
    assert len(F.framing_points(poses[[0, 4]])) == 2 + 10


def test_framed_config(tmp_path):
    default = F.template_view(TEMPLATE)
    assert default == F.OrbitView((0.0, 0.3, 0.0), 18.0, 1.15, 4.712389, 0.785398)
    view = F.OrbitView((1.25, -0.5, 0.4), 5.2, 1.15, math.pi)
    out = F.framed_config(
        TEMPLATE, tmp_path / "video" / "rviz_view.rviz", view, "note.", axes_scale=0.5
    )
    text = out.read_text()
    assert text.startswith("# coop_slam.rviz")
    cfg = yaml.safe_load(text)
    with open(TEMPLATE) as fh:
        template = yaml.safe_load(fh)
    current = cfg["Visualization Manager"]["Views"]["Current"]
    assert current["Class"] == "rviz/Orbit"
    assert current["Distance"] == pytest.approx(5.2)
    assert current["Focal Point"] == {"X": 1.25, "Y": -0.5, "Z": 0.4}
    assert current["Yaw"] == pytest.approx(math.pi, abs=1e-6)
    assert current["Pitch"] == pytest.approx(1.15)
    # everything else as in the package's config
    for key in ("Near Clip Distance", "Target Frame", "Focal Shape Size"):
        assert current[key] == template["Visualization Manager"]["Views"]["Current"][key]
    # the robots' axes scaled, everything else as in the package's config
    displays = cfg["Visualization Manager"]["Displays"]
    tf = next(d for d in displays if d["Class"] == "rviz/TF")
    pose = next(d for d in displays[-1]["Displays"] if d["Class"] == "rviz/Pose")
    assert (tf["Marker Scale"], pose["Axes Length"], pose["Axes Radius"]) == (1.5, 0.2, 0.02)
    template_displays = template["Visualization Manager"]["Displays"]
    next(d for d in template_displays if d["Class"] == "rviz/TF")["Marker Scale"] = 1.5
    for group in template_displays:
        for d in group.get("Displays", ()):
            if d["Class"] == "rviz/Pose":
                for key in F._SCALED_KEYS["rviz/Pose"]:
                    d[key] = round(d[key] * 0.5, 4)
    cfg["Visualization Manager"]["Views"] = template["Visualization Manager"]["Views"] = None
    assert cfg == template
    # a viewer on the station of --hosts: the robots' own topics are off, the team map's on
    station = yaml.safe_load(
        F.framed_config(TEMPLATE, tmp_path / "s.rviz", view, station_only=True).read_text()
    )
    shown = {}

    def walk(displays):
        for d in displays or ():
            if "Topic" in d:
                shown[d["Topic"]] = d["Enabled"]
            walk(d.get("Displays"))

    walk(station["Visualization Manager"]["Displays"])
    assert shown["/team_map/cloud"] and not shown["/robot_1/local_map"]
    assert not any(on for topic, on in shown.items() if topic.startswith("/robot_"))
    # not an orbit view: refused
    bad = tmp_path / "bad.rviz"
    bad.write_text(
        "Visualization Manager:\n  Views:\n    Current:\n      Class: rviz/TopDownOrtho\n"
    )
    with pytest.raises(F.FramingError, match="Orbit"):
        F.framed_config(bad, tmp_path / "x.rviz", view)


def test_demo_writes_framed_config_or_falls_back(tmp_path, capsys):
    from coop_slam.tools.demo import _framed_rviz_config

    base_cam = [0.1, 0.0, 0.5, -0.5, 0.5, -0.5, 0.5]  # the synthetic robots' mounting
    G = np.stack([_se3(R_BODY_OPTICAL, (float(x), float(x) / 2, 0.5)) for x in range(13)])
    inputs = SimpleNamespace(gts={1: (np.zeros(13), G), 2: (np.zeros(0), np.zeros((0, 4, 4)))})
    path = _framed_rviz_config(str(tmp_path), None, inputs, base_cam)
    assert path == str(tmp_path / "video" / "rviz_view.rviz")
    with open(path) as fh:
        cfg = yaml.safe_load(fh)
    current = cfg["Visualization Manager"]["Views"]["Current"]
    assert 0.0 < current["Distance"] < 18.0
    tf = next(d for d in cfg["Visualization Manager"]["Displays"] if d["Class"] == "rviz/TF")
    assert tf["Marker Scale"] == pytest.approx(3.0 * current["Distance"] / 18.0, abs=1e-3)
    assert "RViz view framed on the ground-truth cameras" in capsys.readouterr().out
    inputs.gts = {1: (np.zeros(0), np.zeros((0, 4, 4))), 2: (np.zeros(13), G)}
    assert _framed_rviz_config(str(tmp_path / "b"), None, inputs, base_cam) is None
    out = capsys.readouterr().out
    assert "default view" in out and "no ground truth of robot 1" in out
