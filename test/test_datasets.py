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
