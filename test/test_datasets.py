"""Readers (TUM, KITTI), splitter and playback schedule."""

import os
import shutil

import numpy as np
import pytest

from coop_slam.datasets import (
    DatasetError,
    parse_ranges,
    read_kitti,
    read_tum,
    read_tum_trajectory,
    split_equal,
    split_ranges,
    write_tum_trajectory,
)
from coop_slam.geometry import se3_from_quat
from coop_slam.playback import PlaybackError, build_schedule, group_simultaneous, load_streams
from helpers import REDKITCHEN, TINY_TUM, write_kitti


def test_tum_reader_associates_and_loads():
    seq = read_tum(TINY_TUM)
    assert len(seq) == 12
    assert seq.camera.width == 80 and seq.camera.depth_scale == 5000.0
    f = seq.frames[3]
    assert f.depth_path.endswith(f"{f.stamp_s:.6f}.png")  # depth 3 ms later still associates
    depth = seq.load_depth_m(f)
    assert depth.dtype == np.float32 and np.allclose(depth, 1.06)
    assert seq.load_color(f).shape == (60, 80, 3)
    poses = seq.frame_poses()
    assert np.allclose(poses[:, 0, 3], 0.1 * np.arange(12))


def test_tum_reader_errors(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        read_tum(str(tmp_path / "nope"))
    shutil.copytree(TINY_TUM, tmp_path / "t")
    os.remove(tmp_path / "t" / "camera.yaml")
    with pytest.raises(DatasetError, match="camera.yaml"):
        read_tum(str(tmp_path / "t"))
    seq = read_tum(str(tmp_path / "t"), camera_file=os.path.join(TINY_TUM, "camera.yaml"))
    os.remove(seq.frames[0].color_path)
    with pytest.raises(DatasetError, match="not found"):
        seq.load_color(seq.frames[0])
    with open(seq.frames[1].color_path, "wb") as fh:
        fh.write(b"garbage")
    with pytest.raises(DatasetError, match="cannot decode"):
        seq.load_color(seq.frames[1])
    (tmp_path / "t" / "rgb.txt").write_text("1.0\n")
    with pytest.raises(DatasetError, match="rgb.txt:1"):
        read_tum(str(tmp_path / "t"), camera_file=os.path.join(TINY_TUM, "camera.yaml"))


def test_trajectory_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    poses = np.array([se3_from_quat(rng.normal(size=3), rng.normal(size=4)) for _ in range(5)])
    write_tum_trajectory(str(tmp_path / "t.txt"), np.arange(5) + 0.5, poses)
    stamps, back = read_tum_trajectory(str(tmp_path / "t.txt"))
    assert np.allclose(stamps, np.arange(5) + 0.5)
    assert np.allclose(back, poses, atol=1e-6)
    (tmp_path / "bad.txt").write_text("1 2 3 nan 0 0 0 1\n")
    with pytest.raises(DatasetError, match="bad.txt:1"):
        read_tum_trajectory(str(tmp_path / "bad.txt"))


def test_kitti_reader(tmp_path):
    seq_dir = write_kitti(str(tmp_path))
    seq = read_kitti(seq_dir)
    assert seq.camera.sensor == "stereo"
    assert seq.camera.baseline_m == pytest.approx(0.54)
    assert len(seq) == 5 and seq.load_right(seq.frames[2]).shape == (32, 64)
    assert np.allclose(seq.frame_poses()[:, 2, 3], 0.5 * np.arange(5))
    os.remove(os.path.join(seq_dir, "image_1", "000004.png"))
    with pytest.raises(DatasetError, match="stereo pairs"):
        read_kitti(seq_dir)


def test_split_ranges_and_equal():
    seq = read_tum(TINY_TUM)
    a, b = split_ranges(seq, "0-5,6-11")
    assert len(a) == 6 and len(b) == 6 and b.frames[0].index == 6
    assert np.allclose(b.frame_poses()[0, 0, 3], 0.6)  # ground truth stays with its frames
    parts = split_equal(seq, 3, overlap_frames=2)
    assert [p.frames[0].index for p in parts][0] == 0 and parts[-1].frames[-1].index == 11
    assert parts[0].frames[-1].index >= parts[1].frames[0].index + 1  # they overlap
    with pytest.raises(DatasetError, match="exceeds"):
        split_ranges(seq, "0-20")
    with pytest.raises(DatasetError, match="bad frame range"):
        parse_ranges("5-2")
    with pytest.raises(DatasetError, match="bad frame range"):
        parse_ranges("a-b")


def test_schedule_starts_robots_together_or_keeps_timing():
    src = load_streams(dataset=TINY_TUM, split="0-5,6-11")
    sched = build_schedule(src.streams)
    assert sched[0].play_s == pytest.approx(1.0) and sched[1].play_s == pytest.approx(1.0)
    assert [len(g) for g in group_simultaneous(sched)] == [2] * 6
    kept = build_schedule(src.streams, keep_timing=True)
    assert kept[0].play_s == pytest.approx(100.0) and kept[-1].play_s == pytest.approx(101.1)
    src = load_streams(dataset=TINY_TUM, split="0-5,6-11", start_offsets_s=[0.0, 2.0])
    sched = build_schedule(src.streams)
    assert min(s.play_s for s in sched if s.robot_id == 2) == pytest.approx(3.0)
    with pytest.raises(PlaybackError, match="start offsets"):
        load_streams(dataset=TINY_TUM, split="0-5,6-11", start_offsets_s=[1.0])
    with pytest.raises(PlaybackError, match="exactly one"):
        load_streams()


@pytest.mark.skipif(not os.path.isdir(REDKITCHEN), reason=f"shared data absent: {REDKITCHEN}")
def test_redkitchen_reads():
    seq = read_tum(REDKITCHEN)
    assert len(seq) == 600 and seq.camera.fx == 585.0
    poses = seq.frame_poses()
    assert np.all(np.isfinite(poses))
    depth = seq.load_depth_m(seq.frames[0])
    assert 0.3 < np.median(depth[depth > 0]) < 5.0
    robots = split_ranges(seq, "0-299,300-599")
    assert [len(r) for r in robots] == [300, 300]


def _pattern(xn, yn):
    """A smooth grey pattern on normalized (undistorted) image coordinates."""
    return 128.0 + 100.0 * np.sin(9.0 * xn) * np.cos(7.0 * yn)


def test_tum_reader_undistorts_images_of_a_camera_with_lens_distortion(tmp_path):
    import cv2

    from coop_slam.datasets import read_camera_distortion, read_camera_yaml

    shutil.copytree(TINY_TUM, tmp_path / "t")
    folder = tmp_path / "t"
    raw = read_camera_yaml(str(folder / "camera.yaml"))
    coeffs = np.array([0.15, -0.3, 0.002, -0.001, 0.1])
    with open(folder / "camera.yaml", "a", encoding="utf-8") as fh:
        fh.write("".join(f"d{i}: {c}\n" for i, c in enumerate(coeffs)))  # TUM's names
    # Raw images: every raw pixel shows the pattern at its undistorted ray.
    u, v = np.meshgrid(np.arange(raw.width, dtype=float), np.arange(raw.height, dtype=float))
    rays = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), raw.K, coeffs)
    xn, yn = rays[:, 0, 0].reshape(u.shape), rays[:, 0, 1].reshape(u.shape)
    seq = read_tum(str(folder))
    frame = seq.frames[0]
    grey = np.clip(_pattern(xn, yn), 0, 255).astype(np.uint8)
    cv2.imwrite(frame.color_path, cv2.merge([grey, grey, grey]))
    cv2.imwrite(frame.depth_path, np.round(5000 * (1.0 + 0.5 * xn)).astype(np.uint16))

    assert np.allclose(read_camera_distortion(str(folder / "camera.yaml")), coeffs)
    cam = seq.camera  # pinhole of the undistorted images
    u2, v2 = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    xn2, yn2 = (u2 - cam.cx) / cam.fx, (v2 - cam.cy) / cam.fy
    color = seq.load_color(frame)[..., 0].astype(float)
    inner = (slice(3, -3), slice(3, -3))
    err = np.abs(color - _pattern(xn2, yn2))[inner]
    assert err.mean() < 2.0, err.mean()
    # The same image read as if it had no distortion is clearly off: the test can tell.
    naive = np.abs(grey.astype(float) - _pattern((u - raw.cx) / raw.fx, (v - raw.cy) / raw.fy))
    assert naive[inner].mean() > 4 * err.mean()
    depth = seq.load_depth_m(frame)
    assert np.abs(depth - (1.0 + 0.5 * xn2))[inner].max() < 0.5 * 1.0 / cam.fx + 1e-3

    # Other spellings of the coefficients; bad ones are named.
    cam_file = tmp_path / "cam.yaml"
    with open(os.path.join(TINY_TUM, "camera.yaml"), encoding="utf-8") as fh:
        base = fh.read()
    cam_file.write_text(base + "distortion: [0.15, -0.3, 0.002, -0.001, 0.1]\n")
    assert np.allclose(read_camera_distortion(str(cam_file)), coeffs)
    cam_file.write_text(base + "k1: 0.15\nk2: -0.3\n")
    assert np.allclose(read_camera_distortion(str(cam_file)), [0.15, -0.3, 0, 0, 0])
    cam_file.write_text(base + "k1: 0.1\nd0: 0.1\n")
    with pytest.raises(DatasetError, match="twice"):
        read_camera_distortion(str(cam_file))
    for bad, match in (
        ("distortion: [0.1, 0.2]", "list of 4 or 5 numbers"),
        ("distortion: 0.1 0.2 0.3 0.4", "list of 4 or 5 numbers"),
        ("k1: true", "k1 must be a number"),
        ("d2: x", "p1 must be a number"),
    ):
        cam_file.write_text(base + bad + "\n")
        with pytest.raises(DatasetError, match=match):
            read_tum(str(folder), camera_file=str(cam_file))
    assert read_tum(TINY_TUM).undistort is None  # a camera file without distortion: as before


def test_tum_benchmark_folders_need_no_camera_file(tmp_path):
    for n, fx, undistorted in (("1", 517.3, True), ("3", 535.4, False)):
        folder = tmp_path / f"rgbd_dataset_freiburg{n}_desk"
        shutil.copytree(TINY_TUM, folder)
        os.remove(folder / "camera.yaml")
        seq = read_tum(str(folder))
        assert (seq.undistort is not None) == undistorted
        assert seq.camera.width == 640 and seq.camera.depth_scale == 5000.0
        if undistorted:  # cropped to what the raw image saw: a longer focal length
            assert seq.camera.fx > fx
            with pytest.raises(DatasetError, match="is 80x60, but the camera model .* is 640x480"):
                seq.load_color(seq.frames[0])
        else:
            assert seq.camera.fx == fx
    # Only the benchmark's own folder names: a renamed or resized copy needs its camera.yaml.
    shutil.copytree(tmp_path / "rgbd_dataset_freiburg3_desk", tmp_path / "freiburg3_half_size")
    with pytest.raises(DatasetError, match="camera.yaml"):
        read_tum(str(tmp_path / "freiburg3_half_size"))
