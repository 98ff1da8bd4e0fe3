"""scripts/demo's watch over the system it started: a node that gives up or dies stops the run
with that node's reason (tests without ROS: a log file and a stand-in for roslaunch)."""

import pytest

from coop_slam.errors import CoopSlamError
from coop_slam.tools.demo_launch import Launch, System, watch_nodes


class _Launch:
    def __init__(self, code=None):
        self.returncode = code

    def poll(self):
        return self.returncode


def _system(tmp_path, text, code=None):
    log = tmp_path / "roslaunch.log"
    log.write_text(text)
    return System(master=None, launches=[Launch(_Launch(code), str(log))])


def test_a_running_system_whose_nodes_are_fine_is_left_alone(tmp_path):
    system = _system(tmp_path, "[INFO] [1.0]: server: ready\nprocess[robot_1/client-3]: started\n")
    watch_nodes(system)
    watch_nodes(system)


def test_a_fatal_line_stops_the_run_with_the_nodes_reason(tmp_path):
    system = _system(tmp_path, "[INFO] [1.0]: server: opening\n")
    watch_nodes(system)
    with open(system.log_path, "a") as fh:
        fh.write("[FATAL] [2.0]: server: /x.map is not a coop_slam map file (file is not a")
    watch_nodes(system)  # half a line: read when it is whole
    with open(system.log_path, "a") as fh:
        fh.write(" database)\n")
    with pytest.raises(CoopSlamError, match=r"gave up: .*/x.map is not a coop_slam map file"):
        watch_nodes(system)


def test_roslaunch_exiting_early_names_the_node_that_died(tmp_path):
    text = (
        "process[robot_2/client-5]: started with pid [42]\n"
        "[robot_2/client-5] process has died [pid 42, exit code 1, cmd ...].\n"
        "REQUIRED process [robot_2/client-5] has died!\n"
        "Initiating shutdown!\n"
    )
    system = _system(tmp_path, text, code=1)
    with pytest.raises(CoopSlamError, match=r"exited early \(code 1\): .*robot_2/client-5"):
        watch_nodes(system)


def test_launch_arguments_carry_each_robots_mount_clock_and_camera_preset(tmp_path):
    """demo.launch gets robot k's own mount as the k-th of T_base_cams (the launch default for
    one without), the rehearsed clock offsets and the camera presets."""
    from coop_slam.tools.demo_args import parse_args
    from coop_slam.tools.demo_launch import launch_arguments
    from coop_slam.tools.faults import parse_faults

    args = parse_args(
        ["--scenario", "mounts", "--clock-offset", "2:0.3", "--camera-preset", "kinect_v1"]
    )
    mount_2 = [0.1, 0.0, 0.8, -0.4, 0.4, -0.5, 0.6]
    launch = launch_arguments(
        args,
        all_ids=[1, 2, 3],
        played_ids=[1, 2, 3],
        sensors=["rgbd"] * 3,
        base_cam=[],
        base_cams={2: mount_2},
        presets="kinect_v1",
        ground=True,
        faults=parse_faults("", [1, 2, 3]),
        map_path=str(tmp_path / "map.db"),
        bag_path=str(tmp_path / "run.bag"),
        record_ids=[1, 2, 3],
    )
    (mounts,) = [a for a in launch if a.startswith("T_base_cams:=")]
    per_robot = mounts.split(":=")[1].split(";")
    assert per_robot[0] == "" and per_robot[2] == ""  # the launch file's default
    assert [float(v) for v in per_robot[1].split(",")] == mount_2
    assert "clock_offsets:=2:0.3" in launch and "cameras:=kinect_v1" in launch
