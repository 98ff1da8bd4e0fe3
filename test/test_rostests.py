"""Runs every rostest launch file in test/rostest/ (each with its own master) as one pytest case."""
import glob
import os
import shutil
import subprocess

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROSTESTS = sorted(glob.glob(os.path.join(HERE, "rostest", "*.test")))


@pytest.mark.parametrize("launch_file", ROSTESTS, ids=[os.path.basename(p) for p in ROSTESTS])
def test_rostest(launch_file, tmp_path):
    if shutil.which("rostest") is None or "ROS_PACKAGE_PATH" not in os.environ:
        pytest.fail("rostest or the catkin workspace is not set up: run through scripts/test")
    env = dict(os.environ, ROS_LOG_DIR=str(tmp_path / "log"), ROS_HOME=str(tmp_path))
    # Without --text rostest's exit status and summary are exact (node output goes to the logs).
    proc = subprocess.run(["rostest", launch_file], env=env, capture_output=True, text=True,
                          timeout=1500)
    out = proc.stdout + proc.stderr
    ok = proc.returncode == 0 and "RESULT: SUCCESS" in out
    if not ok:
        logs = sorted(glob.glob(str(tmp_path / "log" / "**" / "*.log"), recursive=True))
        tails = "\n".join(f"--- {p}\n{open(p, errors='replace').read()[-3000:]}" for p in logs[-4:])
        pytest.fail(f"rostest {os.path.basename(launch_file)} failed:\n{out[-4000:]}\n{tails}")
