"""Runs every rostest launch file in test/rostest/ (each with its own master) as one pytest case."""

import glob
import os
import shutil
import subprocess

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # (scripts/test --quick leaves these out)

HERE = os.path.dirname(os.path.abspath(__file__))
ROSTESTS = sorted(glob.glob(os.path.join(HERE, "rostest", "*.test")))


@pytest.mark.parametrize("launch_file", ROSTESTS, ids=[os.path.basename(p) for p in ROSTESTS])
def test_rostest(launch_file, tmp_path):
    if shutil.which("rostest") is None or "ROS_PACKAGE_PATH" not in os.environ:
        pytest.fail("rostest or the catkin workspace is not set up: run through scripts/test")
    env = dict(os.environ, ROS_LOG_DIR=str(tmp_path / "log"), ROS_HOME=str(tmp_path))
    # Without --text rostest's exit status and summary are exact (node output goes to the logs).
    args = []
    if os.path.basename(launch_file) == "server.test":  # a vocabulary of that test's world
        from helpers import cylinder_world, team_keyframes, team_vocabulary

        points, desc = cylinder_world(seed=3)
        kfs = team_keyframes(1, np.linspace(0, 2 * np.pi, 36, endpoint=False), points, desc)
        vocab_path = str(tmp_path / "vocabulary.npz")
        team_vocabulary(kfs).save(vocab_path)
        args.append(f"vocabulary:={vocab_path}")
    proc = subprocess.run(
        ["rostest", launch_file, *args], env=env, capture_output=True, text=True, timeout=1500
    )
    out = proc.stdout + proc.stderr
    ok = proc.returncode == 0 and "RESULT: SUCCESS" in out
    if not ok:
        logs = sorted(glob.glob(str(tmp_path / "log" / "**" / "*.log"), recursive=True))
        tails = "\n".join(f"--- {p}\n{open(p, errors='replace').read()[-3000:]}" for p in logs[-4:])
        pytest.fail(f"rostest {os.path.basename(launch_file)} failed:\n{out[-4000:]}\n{tails}")
