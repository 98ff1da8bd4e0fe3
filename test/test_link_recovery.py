"""A keyframe link on a real ROS master (its own, on a free port): one message that cannot be
serialized, published by rospy as is, ends a plain subscriber's link for good; the server's link
watch subscribes again and the messages after it arrive; published through the client's guard,
it is refused and no link breaks."""

import os
import re
import socket
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.slow  # ROS nodes

HERE = os.path.dirname(os.path.abspath(__file__))
NODE = os.path.join(HERE, "link_recovery_node.py")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def master(tmp_path):
    """A rosmaster of this test's own, stopped (by its pid) on every way out."""
    if "ROS_PACKAGE_PATH" not in os.environ:
        pytest.fail("the catkin workspace is not set up: run through scripts/test")
    port = _free_port()
    env = dict(
        os.environ,
        ROS_MASTER_URI=f"http://127.0.0.1:{port}",
        ROS_HOSTNAME="127.0.0.1",
        ROS_LOG_DIR=str(tmp_path / "log"),
        ROS_HOME=str(tmp_path),
    )
    proc = subprocess.Popen(
        ["rosmaster", "--core", "-p", str(port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(1.0)
        yield env
    finally:
        proc.kill()
        proc.wait()


def _run(env, tmp_path, pub_mode: str) -> tuple[dict[str, str], str]:
    """Both subscribers and the publisher; returns each subscriber's output and the
    publisher's."""
    subs, outs = {}, {}
    try:
        for mode in ("watch", "plain"):
            fh = open(tmp_path / f"sub_{mode}.txt", "w")
            subs[mode] = (
                subprocess.Popen(
                    [sys.executable, NODE, "sub", mode],
                    env=env,
                    stdout=fh,
                    stderr=subprocess.STDOUT,
                ),
                fh,
            )
        time.sleep(1.5)
        pub = subprocess.run(
            [sys.executable, NODE, "pub", pub_mode],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        time.sleep(1.0)
    finally:
        for mode, (proc, fh) in subs.items():
            proc.kill()
            proc.wait()
            fh.close()
            outs[mode] = (tmp_path / f"sub_{mode}.txt").read_text()
    return outs, pub.stdout + pub.stderr


def _got(text: str) -> set[int]:
    return {int(q) for q in re.findall(r"^got (\d+)$", text, re.M)}


def test_a_dropped_link_is_subscribed_again_and_a_guarded_publisher_never_drops_it(
    master, tmp_path
):
    outs, pub = _run(master, tmp_path, "raw")
    assert "raised" in pub and "done" in pub, pub
    assert max(_got(outs["plain"])) < 5, outs["plain"]  # rospy never reconnects by itself
    assert "link on /robot_1/keyframes dropped" in outs["watch"], outs["watch"]
    assert len(_got(outs["watch"]) & set(range(6, 41))) >= 20, outs["watch"]

    (tmp_path / "guarded").mkdir()
    outs, pub = _run(master, tmp_path / "guarded", "guarded")
    assert "refused: OverflowError" in pub, pub
    want = set(range(1, 41)) - {5}
    for mode in ("watch", "plain"):
        assert _got(outs[mode]) == want, outs[mode]
    assert "dropped" not in outs["watch"]
