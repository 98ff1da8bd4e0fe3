"""scripts/record_rviz end to end: a roscore on a free port, a latched coloured team cloud in
`world` (plus a static TF world -> robot_1/map and a path of robot 1), a headless recording; checks
the MP4, that the final PNG shows the cloud, that no child process outlives the recorder, the clear
error without a master, and the stops on --until-topic and SIGINT."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(REPO, "scripts", "record_rviz")
MISSING = [b for b in ("Xvfb", "rviz", "ffmpeg") if shutil.which(b) is None]
pytestmark = [
    pytest.mark.slow,  # (scripts/test --quick leaves these out)
    pytest.mark.skipif(
        bool(MISSING),
        reason=f"{', '.join(MISSING)} not installed (Debian "
        "packages xvfb, rviz, ffmpeg in debian-packages.txt): cannot record",
    ),
]

BACKGROUND = (25, 25, 30)  # rviz/coop_slam.rviz Global Options / Background Color
FLOOR_RGB = (255, 200, 0)  # amber floor plane of the test cloud
BOX_RGB = (0, 220, 255)  # cyan box of the test cloud
ROBOT1_RGB = (230, 25, 75)  # robot_1's display colour in rviz/coop_slam.rviz

PUBLISHER = r"""
import sys
import numpy as np
import rospy
import tf2_ros
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import PointCloud2
from coop_slam.ros.convert import cloud_to_msg, pose_to_msg, transform_stamped

floor_rgb, box_rgb = %r, %r
rospy.init_node("test_record_publisher")
# 6 m x 4 m floor (5 cm grid) and a 1.2 m box standing on it at (2.5, 1.0)
gx, gy = np.meshgrid(np.arange(-3.0, 3.0, 0.05), np.arange(-2.0, 2.0, 0.05))
floor = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
rng = np.random.default_rng(0)
u = rng.uniform(-0.6, 0.6, (3000, 2))
face = rng.integers(0, 5, 3000)
box = np.zeros((3000, 3))
box[:, 0] = np.where(face == 0, -0.6, np.where(face == 1, 0.6, u[:, 0]))
box[:, 1] = np.where(
    face == 2, -0.6, np.where(face == 3, 0.6, np.where(face < 2, u[:, 0], u[:, 1]))
)
box[:, 2] = np.where(face == 4, 1.2, 0.6 + u[:, 1])
box += [2.5, 1.0, 0.0]
points = np.vstack([floor, box])
rgb = np.vstack([np.tile(floor_rgb, (len(floor), 1)), np.tile(box_rgb, (len(box), 1))])
stamp = rospy.Time.now()
cloud_pub = rospy.Publisher("/team_map/cloud", PointCloud2, queue_size=1, latch=True)
cloud_pub.publish(cloud_to_msg(points, "world", stamp, rgb))

c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
T = np.eye(4)
T[:2, :2] = [[c, -s], [s, c]]
T[:3, 3] = [-4.0, -2.5, 0.0]
tf_pub = tf2_ros.StaticTransformBroadcaster()
tf_pub.sendTransform(transform_stamped(T, "world", "robot_1/map", stamp))

path = Path()
path.header.frame_id = "robot_1/map"
path.header.stamp = stamp
for a in np.linspace(0, 1.5 * np.pi, 60):
    P = np.eye(4)
    P[:3, 3] = [1.5 * np.cos(a), 1.5 * np.sin(a), 0.5]
    ps = PoseStamped(pose=pose_to_msg(P))
    ps.header = path.header
    path.poses.append(ps)
path_pub = rospy.Publisher("/robot_1/path", Path, queue_size=1, latch=True)
path_pub.publish(path)
pose_pub = rospy.Publisher("/robot_1/pose", PoseStamped, queue_size=1, latch=True)
pose_pub.publish(path.poses[-1])
print("ready", flush=True)
rospy.spin()
""" % (
    FLOOR_RGB,
    BOX_RGB,
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _child_env(tmp, master_uri) -> dict:
    env = dict(
        os.environ,
        ROS_MASTER_URI=master_uri,
        ROS_HOME=str(tmp),
        ROS_LOG_DIR=str(tmp / "log"),
        PYTHONUNBUFFERED="1",
    )
    env.pop("DISPLAY", None)  # never draw on the developer's screen
    # the package as pytest imports it (sourced workspace, else src/ via conftest) comes last
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (env.get("PYTHONPATH"), os.path.join(REPO, "src")) if p
    )
    return env


def _stop_group(proc: subprocess.Popen, sig=signal.SIGINT, grace=10.0) -> None:
    for s, wait in ((sig, grace), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, s)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _master_up(uri: str, timeout=30.0) -> bool:
    import rosgraph

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        old = socket.getdefaulttimeout()
        socket.setdefaulttimeout(2.0)
        try:
            rosgraph.Master("/test_record_rviz", master_uri=uri).getPid()
            return True
        except Exception:  # noqa: BLE001 - not up yet
            time.sleep(0.3)
        finally:
            socket.setdefaulttimeout(old)
    return False


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


class Proc:
    """A child in its own process group; its output lines collected as they come."""

    def __init__(self, cmd, env):
        self.proc = subprocess.Popen(
            cmd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    @property
    def output(self) -> str:
        return "\n".join(self.lines)

    def wait_for_line(self, prefix: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not any(line.startswith(prefix) for line in self.lines):
            assert (
                self.proc.poll() is None
            ), f"{self.proc.args[:2]} exited before '{prefix}':\n{self.output}"
            assert time.monotonic() < deadline, f"no '{prefix}' within {timeout} s:\n{self.output}"
            time.sleep(0.1)


class Recording(Proc):
    """scripts/record_rviz ARGS."""

    def __init__(self, args, env):
        super().__init__([SCRIPT, *args], env)

    def finish(self, timeout: float) -> int:
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            _stop_group(self.proc, signal.SIGTERM, grace=30.0)  # the recorder's own cleanup first
            pytest.fail(f"recorder still running after {timeout} s:\n{self.output}")
        finally:
            self._reader.join(timeout=5)
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc.poll() is None:
            _stop_group(self.proc, signal.SIGTERM, grace=30.0)

    def child_pids(self) -> list[int]:
        return [int(p) for p in re.findall(r"\(.*?pid (\d+)\)", self.output)]


@pytest.fixture(scope="module")
def ros(tmp_path_factory):
    """(env for children, tmp dir): a roscore on a free port and the test cloud publisher."""
    if shutil.which("roscore") is None:
        pytest.fail("roscore not found: run through scripts/test (sources the catkin workspace)")
    tmp = tmp_path_factory.mktemp("record_rviz")
    env = _child_env(tmp, f"http://127.0.0.1:{_free_port()}")
    port = env["ROS_MASTER_URI"].rsplit(":", 1)[1]
    procs = []
    try:
        with open(tmp / "roscore.log", "wb") as log:
            procs.append(
                subprocess.Popen(
                    ["roscore", "-p", port],
                    env=env,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                )
            )
        log_tail = lambda: (tmp / "roscore.log").read_text(errors="replace")[-2000:]  # noqa: E731
        assert _master_up(env["ROS_MASTER_URI"]), f"roscore did not come up:\n{log_tail()}"
        pub = Proc([sys.executable, "-c", PUBLISHER], env)
        procs.append(pub.proc)
        pub.wait_for_line("ready", timeout=30)  # printed once everything is latched
        yield env, tmp
    finally:
        for proc in reversed(procs):
            _stop_group(proc)


def _count(img, rgb, tol=30) -> int:
    return int(np.count_nonzero(np.abs(img.astype(int) - rgb).max(axis=2) <= tol))


def test_record_shows_team_cloud(ros):
    cv2 = pytest.importorskip("cv2")
    env, tmp = ros
    out = tmp / "out"
    rec = Recording(["--headless", "--duration", "8", "--out", str(out)], env)
    try:
        status = rec.finish(timeout=75)
    finally:
        rec.kill()
    assert status == 0, rec.output
    for word in ("Xvfb on :", "rviz ready", "recording", "stop: 8 s recorded", "done"):
        assert word in rec.output, rec.output
    pids = rec.child_pids()
    assert len(pids) == 3, rec.output  # Xvfb, rviz, ffmpeg
    assert not [p for p in pids if _alive(p)], f"children left running: {pids}"

    mp4 = out / "rviz.mp4"
    assert mp4.is_file() and mp4.stat().st_size > 0
    if shutil.which("ffprobe"):
        probe = subprocess.run(
            [
                "ffprobe",
                "-v",
                "error",
                "-select_streams",
                "v:0",
                "-count_frames",
                "-show_entries",
                "stream=nb_read_frames,width,height,pix_fmt",
                "-of",
                "default=noprint_wrappers=1",
                str(mp4),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        info = dict(line.split("=", 1) for line in probe.stdout.split())
        assert int(info["nb_read_frames"]) > 0, probe.stdout + probe.stderr
        assert (info["width"], info["height"], info["pix_fmt"]) == ("1280", "720", "yuv420p")

    img = cv2.imread(str(out / "map.png"))
    assert img is not None, "map.png missing or unreadable"
    img = img[:, :, ::-1]  # RGB
    assert img.shape == (720, 1280, 3)
    colours, counts = np.unique(img.reshape(-1, 3), axis=0, return_counts=True)
    # the config is loaded: its dark background fills most of the screen
    # (rviz full screen, no panels)
    assert np.abs(colours[np.argmax(counts)].astype(int) - BACKGROUND).max() <= 5
    # the cloud is drawn: thousands of floor pixels, the box, and robot 1's path through the
    # static TF
    assert _count(img, FLOOR_RGB) > 2000, _count(img, FLOOR_RGB)
    assert _count(img, BOX_RGB) > 300, _count(img, BOX_RGB)
    assert _count(img, ROBOT1_RGB) > 50, _count(img, ROBOT1_RGB)


def test_no_master_fails_clearly(tmp_path):
    env = _child_env(tmp_path, f"http://127.0.0.1:{_free_port()}")  # nothing listens there
    rec = Recording(
        ["--headless", "--duration", "1", "--master-timeout", "2", "--out", str(tmp_path / "out")],
        env,
    )
    try:
        status = rec.finish(timeout=30)
    finally:
        rec.kill()
    assert status == 1, rec.output
    assert "no ROS master reachable" in rec.output and "roscore" in rec.output, rec.output
    assert not (tmp_path / "out" / "rviz.mp4").exists()


def test_stops_on_until_topic(ros):
    env, tmp = ros
    out = tmp / "until"
    rec = Recording(
        ["--headless", "--until-topic", "/player/done", "--warmup", "0", "--out", str(out)], env
    )
    try:
        rec.wait_for_line("[record] waiting for true on", timeout=60)
        time.sleep(1.0)
        subprocess.run(
            ["rostopic", "pub", "-1", "/player/done", "std_msgs/Bool", "true"],
            env=env,
            capture_output=True,
            timeout=30,
        )
        status = rec.finish(timeout=30)
    finally:
        rec.kill()
    assert status == 0, rec.output
    assert "stop: true on /player/done" in rec.output, rec.output
    assert (out / "rviz.mp4").stat().st_size > 0 and (out / "map.png").stat().st_size > 0
    assert not [p for p in rec.child_pids() if _alive(p)]


def test_sigint_stops_and_saves(ros):
    env, tmp = ros
    out = tmp / "sigint"
    rec = Recording(["--headless", "--warmup", "0", "--out", str(out)], env)
    try:
        rec.wait_for_line("[record] recording until Ctrl-C", timeout=60)
        time.sleep(1.5)
        os.killpg(rec.proc.pid, signal.SIGINT)  # as Ctrl-C in a terminal: the recorder's group only
        status = rec.finish(timeout=30)
    finally:
        rec.kill()
    assert status == 0, rec.output
    assert "stop: SIGINT received" in rec.output, rec.output
    assert (out / "rviz.mp4").stat().st_size > 0 and (out / "map.png").stat().st_size > 0
    assert not [p for p in rec.child_pids() if _alive(p)]
