"""End to end through the README's main command: scripts/demo runs player, server and clients on a
scenario (lock-step, so results do not depend on machine speed) and its report is checked."""

import json
import os
import sqlite3
import subprocess
from types import SimpleNamespace

import pytest

from coop_slam.tools.demo import TEAM_MAP
from helpers import REDKITCHEN, REPO, evaluate_again

pytestmark = pytest.mark.slow  # (scripts/test --quick leaves these out)

# The rendezvous world's first 26 s: the robots meet face to face (~8 s) and see one scene
# together from 18.6 s (the operator's call at 20 s; co-observation alone merges at 23.9 s); the
# rest of the world adds nothing these tests check. One length for all of them renders one world.
RENDEZVOUS = ("--scenario", "rendezvous", "--duration", "26")
# The revisit world's first 34 s: robot 2 reaches robot 1's corridor and merges at 25.8 s (27.5 s
# with a monocular robot 1); the fault test keeps the whole world (a client killed at 32 s).
REVISIT = ("--scenario", "revisit", "--duration", "34")


def _demo(tmp_path, *args, timeout=1500):
    out = tmp_path / "out"
    # RViz recording is covered by test_record_rviz; here it would only slow the run down.
    proc = subprocess.run(
        [os.path.join(REPO, "scripts", "demo"), *args, "--no-record", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    log = out / "roslaunch.log"
    tail = log.read_text(errors="replace")[-4000:] if log.exists() else ""
    assert (
        proc.returncode == 0
    ), f"demo failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}\n{tail}"
    with open(out / "report.json") as fh:
        return json.load(fh), tail, out


def _unbudgeted(tmp_path) -> tuple:
    """Client arguments without a radio budget: every keyframe whole, as the server's precision
    and pose-graph sharing over all of a robot's keyframes assume (what the default budget costs
    is measured per run by scripts/demo; issue #49's note)."""
    path = tmp_path / "client.yaml"
    path.write_text("uplink: {budget_kBps: 0.0}\n")
    return ("--client-config", str(path))


def test_revisit_merges_by_place_recognition(tmp_path):
    report, log, out = _demo(tmp_path, *REVISIT, *_unbudgeted(tmp_path))
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0
    merge = report["merges"][0]
    assert merge["type"] == "place_recognition"
    # Bounds of a correct (not wrong) merge; the tighter accuracy targets are measured by
    # the demo and reported, not asserted here.
    assert merge["local_trans_err_m"] < 0.10 and merge["local_rot_err_deg"] < 2.0
    assert merge["latency_s"] < 5.0
    assert report["team_ate_rmse_m"] < 0.03  # the place-recognition issue's merge bound
    for robot in report["robots"]:
        assert robot["keyframes"] >= 10
        assert robot["ate_rmse_m"] < 0.005 * robot["path_length_m"]
        # Pose-graph sharing: each client publishes its keyframes where the team map has them
        # (2.5-2.9 mm apart when it only offset its odometry).
        assert robot["path_team_gap_m"] is not None and robot["path_team_gap_m"] < 0.001, robot
        assert robot["path_ate_rmse_m"] < 1.1 * robot["server_ate_rmse_m"] + 0.0005, robot
    # The dense map and its grid, scored against the world (issue #48's targets are measured by
    # the demo and reported; these are bounds a broken placement or band would not meet).
    assert report["grid_iou"] > 0.8 and report["grid_free_iou"] > 0.9, report
    assert report["dense_surface_rmse_m"] < 0.04
    for name in ("grid.pgm", "grid.yaml", "grid.png", "team_map_dense.ply", "dense.png"):
        assert (out / name).exists(), name


def test_a_monocular_robot_joins_an_rgbd_one_in_metres(tmp_path):
    """A mixed team on the revisit world: robot 1 carries a monocular camera (a map without
    metric scale), robot 2 an RGB-D one. They merge by a similarity; the server then holds robot
    1's map in metres (its scale within 2 %) and the team map is metric."""
    report, log, _ = _demo(tmp_path, *REVISIT, "--sensors", "mono,rgbd", *_unbudgeted(tmp_path))
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0
    merge = report["merges"][0]
    assert abs(merge["scale_err"]) < 0.03, merge  # the similarity, before any link refined it
    mono, rgbd = report["robots"]
    assert (mono["sensor"], rgbd["sensor"]) == ("mono", "rgbd")
    assert mono["ate_rmse_m"] is None and mono["ate_sim3_rmse_m"] < 0.01 * mono["path_length_m"]
    assert abs(mono["scale_error"]) < 0.02, mono
    assert report["team_ate_rmse_m"] < 0.02


def _server_config(tmp_path, **sections) -> str:
    import yaml

    path = tmp_path / "server.yaml"
    path.write_text(yaml.safe_dump({"server": sections}))
    return str(path)


@pytest.mark.parametrize("mode", ["marker_sighting", "co_observation", "operator"])
def test_rendezvous_merges_by_rendezvous(tmp_path, mode):
    """Each detection mode alone: marker sightings (the server's co-observation test and place
    recognition off), co-observation with no marker cue (clients do not look for markers), or an
    operator's call of the server's ~rendezvous service (no markers, no automatic test)."""
    if mode == "marker_sighting":
        cfg = _server_config(
            tmp_path, rendezvous={"auto": False}, place_recognition={"enabled": False}
        )
        extra = []
    elif mode == "operator":  # the robots see one scene together from 18.6 s into the run
        cfg = _server_config(
            tmp_path, rendezvous={"auto": False}, place_recognition={"enabled": False}
        )
        extra = ["--no-markers", "--rendezvous", "1,2@20"]
    else:
        cfg = _server_config(tmp_path, place_recognition={"enabled": False})
        extra = ["--no-markers"]
    report, log, _ = _demo(tmp_path, *RENDEZVOUS, "--server-config", cfg, *extra)
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0
    merge = report["merges"][0]
    assert merge["type"] == "rendezvous"
    assert merge["local_trans_err_m"] < 0.05 and merge["local_rot_err_deg"] < 2.0
    topics = report["topics"]
    if mode == "marker_sighting":
        assert topics["/robot_sightings"]["messages"] >= 1
    else:
        assert "/robot_sightings" not in topics


def test_a_stereo_team_is_at_least_as_good_as_its_parts(tmp_path):
    """Issue #47: on the rendezvous world a stereo team's map is at least as accurate as its
    robots' own maps placed perfectly (pooled; 0.49 against 0.80 cm when this test was written:
    the global BA had swung robot 2's first keyframes, 8.2 cm). A monocular team is not tested
    so: its robot 2 loses tracking in its turn on the spot near 17 s and starts a new map, and
    its team ATE was above pooled in 3 of 8 runs (0.38-0.71 cm against 0.49: issue #47's note)."""
    report, log, _ = _demo(tmp_path, *RENDEZVOUS, "--sensors", "stereo")
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0 and report["merges"][0]["type"] == "rendezvous"
    assert report["team_ate_rmse_m"] <= report["single_ate_pooled_m"], report


# Two buildings never share a view: 20 s build both maps. The look-alike buildings keep their whole
# 32 s, every poster seen by both robots.
@pytest.mark.parametrize("scenario,duration", [("disjoint", "20"), ("aliasing", "32")])
def test_no_merge_without_overlap(tmp_path, scenario, duration):
    report, _, out = _demo(tmp_path, "--scenario", scenario, "--duration", duration)
    assert report["merges"] == [] and report["groups"] == [[1], [2]]
    assert all(robot["keyframes"] >= 5 for robot in report["robots"])  # both maps still built
    topics = report["topics"]
    for r in (1, 2):  # both maps published, to the server and on the team map
        assert topics[f"/robot_{r}/keyframes"]["messages"] >= 5
        assert topics[f"/robot_{r}/local_map"]["messages"] >= 1
        assert topics[f"/team_map/robot_{r}/path"]["messages"] >= 1
    # The uplink holds a new keyframe back a second (uplink.hold_new_s): when the player is done
    # the held ones go too, so every keyframe the clients kept went to the server (their last
    # stats, sent after that flush, against the keyframes their messages add up to).
    import rosbag

    kept = {}
    with rosbag.Bag(str(out / "run.bag")) as bag:
        for topic, msg, _ in bag.read_messages(
            topics=["/robot_1/frame_stats", "/robot_2/frame_stats"]
        ):
            kept[topic] = msg.keyframes
    assert [kept[f"/robot_{r}/frame_stats"] for r in (1, 2)] == [
        robot["keyframes"] for robot in report["robots"]
    ]
    if scenario == "disjoint":  # scripts/evaluate re-derives the report from the recorded bag
        again = evaluate_again(out)
        assert again["groups"] == report["groups"] and again["robots"] == report["robots"]


@pytest.mark.skipif(not os.path.isdir(REDKITCHEN), reason=f"shared data absent: {REDKITCHEN}")
def test_redkitchen_two_robots_merge(tmp_path):
    report, log, _ = _demo(tmp_path, "--dataset", REDKITCHEN, "--split", "0-299,300-599")
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0
    assert report["team_ate_rmse_m"] < 0.04


def test_a_stereo_and_an_rgbd_robot_build_one_map_from_a_sensor_bag(tmp_path):
    """A mixed team on the rendezvous world, recorded as a sensor bag (written by
    scripts/export_bag): robot 1 carries a stereo camera (rectified pair, ROS stereo topics), robot
    2 an RGB-D camera. The bag runs through the same demo in lock-step; their maps merge, each
    tracks within 0.5 % of its path (accuracy from the ground-truth topics in the bag), robot 1's
    keyframes say they come from a stereo camera with its baseline, and scripts/evaluate
    re-derives the report from run.json + run.bag."""
    import rosbag

    from coop_slam.camera import SENSORS
    from coop_slam.playback import SYNTHETIC_STEREO_BASELINE_M

    bag = tmp_path / "rendezvous.bag"
    proc = subprocess.run(
        [os.path.join(REPO, "scripts", "export_bag"), *RENDEZVOUS, "--sensors", "stereo,rgbd"]
        + ["--out", bag],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report, log, out = _demo(tmp_path, "--bag", str(bag))
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0
    for robot in report["robots"]:
        assert robot["frames"] >= 380  # lock-step: every frame of the bag (26 s at 15 Hz) tracked
        assert robot["ate_rmse_m"] < 0.005 * robot["path_length_m"], robot
    assert report["team_ate_rmse_m"] < 0.03
    assert [robot["sensor"] for robot in report["robots"]] == ["stereo", "rgbd"]
    with open(out / "run.json") as fh:
        assert json.load(fh)["bag"] == str(bag)
    cameras = {}
    with rosbag.Bag(str(out / "run.bag")) as recorded:
        for topic, msg, _ in recorded.read_messages(
            topics=["/robot_1/keyframes", "/robot_2/keyframes"]
        ):
            if msg.kind == msg.KIND_KEYFRAME:  # (a whole keyframe carries its camera)
                camera = msg.keyframe[0].camera
                cameras[topic] = (camera.sensor_type, camera.baseline_m)
    stereo, rgbd = cameras["/robot_1/keyframes"], cameras["/robot_2/keyframes"]
    assert stereo[0] == SENSORS.index("stereo")
    assert abs(stereo[1] - SYNTHETIC_STEREO_BASELINE_M) < 1e-6
    assert rgbd[0] == SENSORS.index("rgbd")
    again = evaluate_again(out)
    assert again["robots"] == report["robots"] and again["merges"] == report["merges"]
    bag.unlink()


def test_demo_operator_requests_parse_and_bad_ones_are_named():
    from coop_slam.tools.demo_args import parse_args

    args = parse_args(
        ["--scenario", "rendezvous", "--rendezvous", "1,2@20", "--rendezvous", "2,1@3.5"]
    )
    assert args.rendezvous == [(1, 2, 20.0), (2, 1, 3.5)]
    for bad in ("1@20", "1,1@20", "1,2@-1", "1,2@nan", "a,b@1", "1,2"):
        with pytest.raises(SystemExit):
            parse_args(["--rendezvous", bad])


def test_demo_duration_is_a_scenario_length():
    from coop_slam.tools.demo_args import parse_args

    assert parse_args(["--scenario", "rendezvous", "--duration", "22.5"]).duration == 22.5
    for bad in (
        ["--duration", "0"],
        ["--duration", "inf"],
        ["--duration", "nan"],
        ["--bag", "x.bag", "--duration", "5"],
    ):
        with pytest.raises(SystemExit):
            parse_args(bad)
    from coop_slam.tools.export_bag import main as export_bag

    for bad in (["--scenario", "team", "--duration", "0"], ["--dataset", "x", "--duration", "5"]):
        with pytest.raises(SystemExit):
            export_bag([*bad, "--out", "never.bag"])


def test_a_kidnapped_robot_relocalizes_in_the_team_map(tmp_path):
    """Robot 2's camera goes dark while it drives into the east corridor, which only robot 1 has
    mapped: the server sends the team's local map there and robot 2 carries on in its own map (no
    new segment), placed right."""
    report, log, out = _demo(tmp_path, "--scenario", "kidnap")
    assert report["groups"] == [[1, 2]] and report["wrong_merges"] == 0
    text = (out / "roslaunch.log").read_text(errors="replace")
    assert "relocalized in the team map" in text and "new map segment" not in text
    robot_2 = report["robots"][1]
    # Its keyframes before the dark and after it, in one map: one SE(3) alignment fits them.
    assert robot_2["ate_rmse_m"] < 0.03


def test_kill_restart_and_a_lossy_radio_lose_no_keyframe(tmp_path):
    """The server killed (-9) and resumed from its map file, robot 2's client killed and started
    again (a new map segment), 10 % of the keyframe messages dropped on the way: no robot loses a
    keyframe it sent (kept until stored; robot 2's on its disk, sent first after the restart), none
    is stored twice, and robot 2's new segment merges back into one team map."""
    faults = "server-kill@15,client-kill:2@32,drop:0.1"
    report, log, out = _demo(tmp_path, "--scenario", "revisit", "--faults", faults)
    assert report["faults"]["spec"] == faults
    assert all(k["done"] for k in report["faults"]["kills"])
    robot_1, robot_2 = report["robots"]
    assert robot_1["keyframes_sent"] >= 10 and robot_1["keyframes_lost"] == 0, robot_1
    assert robot_2["keyframes_stored"] >= 10 and robot_2["keyframes_lost"] == 0, robot_2
    text = (out / "roslaunch.log").read_text(errors="replace")
    assert "already received as new" not in text
    db = sqlite3.connect(str(out / TEAM_MAP))
    twice = db.execute(
        "SELECT robot_id, keyframe_id FROM inputs WHERE kind='keyframe' AND action=0 "
        "GROUP BY robot_id, keyframe_id HAVING COUNT(*) > 1"
    ).fetchall()
    db.close()
    assert twice == []
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0
    # Robot 2 merged, then its new segment merged back.
    assert len([m for m in report["merges"] if 2 in m["robots"]]) >= 2, report["merges"]
    assert "resumed" in text


def test_a_later_session_extends_a_saved_map(tmp_path):
    """Robot 1 maps alone and saves the team map; a later session loads it, robot 2 alone
    localizes in it by place recognition: one team map, robot 1's keyframes kept."""
    saved = tmp_path / "revisit.map"
    first, _, _ = _demo(tmp_path / "day1", *REVISIT, "--only-robots", "1", "--save-map", str(saved))
    assert saved.stat().st_size > 0 and [r["id"] for r in first["robots"]] == [1]
    report, log, _ = _demo(
        tmp_path / "day2", *REVISIT, "--only-robots", "2", "--load-map", str(saved)
    )
    assert report["groups"] == [[1, 2]], log
    assert report["wrong_merges"] == 0
    merge = report["merges"][0]
    assert merge["robots"] == [1, 2] and merge["local_trans_err_m"] < 0.10
    loaded = next(r for r in report["robots"] if r["id"] == 1)
    assert loaded["keyframes_stored"] == first["robots"][0]["keyframes_stored"]


def test_fault_specs_are_read_and_bad_ones_named():
    from coop_slam.tools.faults import FaultError, parse_faults

    f = parse_faults("drop:0.1, client-kill:2@30,server-kill@25", [1, 2])
    assert [(k.node, k.robot_id, k.at_s) for k in f.kills] == [
        ("server", 0, 25.0),
        ("client", 2, 30.0),
    ]
    assert f.drop == 0.1
    for bad, why in (
        ("drop:1.5", "share"),
        ("client-kill:3@5", "robots"),
        ("reboot@3", "cannot read"),
    ):
        with pytest.raises(FaultError, match=why):
            parse_faults(bad, [1, 2])


def test_results_table_names_faults_sessions_and_live_runs():
    from coop_slam.tools.results_table import describe

    assert (
        describe({"scenario": "team", "faults": "drop:0.1"})
        == "`--scenario team --faults drop:0.1`"
    )
    assert describe({"scenario": "revisit", "only_robots": "2", "load_map": "/x.map"}) == (
        "`--scenario revisit --only-robots 2 --load-map ...`"
    )
    assert describe({"dataset": "/d/rk", "rate": 1.0}) == "`--dataset rk --rate 1.0`"
    assert describe({"scenario": "team", "pose_sharing": True}) == (
        "`--scenario team --pose-sharing`"
    )
    assert describe({"scenario": "rendezvous", "duration": 24.0}) == (
        "`--scenario rendezvous --duration 24`"
    )
    assert describe({"scenario": "team", "low_bandwidth": True}) == (
        "`--scenario team --low-bandwidth`"
    )


def test_results_table_gives_a_monocular_robots_sim3_ate_and_scale_errors():
    from coop_slam.tools.results_table import row

    report = {
        "robots": [
            {"sensor": "rgbd", "ate_rmse_m": 0.003, "path_ate_rmse_m": 0.0025},
            {"sensor": "mono", "ate_rmse_m": None, "ate_sim3_rmse_m": 0.008, "scale_error": 0.0073},
        ],
        "merges": [
            {
                "type": "place_recognition",
                "robots": [1, 2],
                "latency_s": 1.6,
                "local_trans_err_m": 0.02,
                "local_rot_err_deg": 0.25,
                "scale_err": -0.0074,
                "local_scale_err": 0.012,
            }
        ],
    }
    cells = row(report, {"scenario": "team"})
    assert cells[3] == "0.30 / 0.80 (Sim3, scale +0.7 %)"
    assert cells[6] == "0.25 / –"  # the clients' published paths
    assert cells[7].endswith("scale -0.7 % (+1.2 % local)")


class _FakeClock:
    """time.monotonic / time.sleep of the demo on a virtual clock, with the server's stats and
    robot 1's unacknowledged messages as functions of it."""

    def __init__(self, stats_at, unacked_at=lambda t: 0):
        self.now, self.stats_at, self.unacked_at = 0.0, stats_at, unacked_at
        self.run = SimpleNamespace(server_stats=stats_at(0.0), robots={})
        self._update()

    def _update(self):
        self.run.server_stats = self.stats_at(self.now)
        self.run.robots = {1: SimpleNamespace(unacked=self.unacked_at(self.now))}

    def monotonic(self):
        return self.now

    def sleep(self, s):
        self.now += s
        self._update()


@pytest.mark.parametrize(
    "stats_at, unacked_at, ends_at",
    [
        (lambda t: {"keyframes": 40, "idle": t >= 3.0}, lambda t: 0, 4.0),  # idle at 3 s, for 1 s
        (lambda t: {"keyframes": 40, "idle": True}, lambda t: 0, 2.0),  # idle: the minimum wait
        (lambda t: {"keyframes": min(40, int(t))}, lambda t: 0, 45.0),  # 5 s without a change
        (lambda t: {"keyframes": int(t)}, lambda t: 0, 180.0),  # busy without end: the cap
        # A client's messages sent again, stored at 12 s (its stats say so at once).
        (lambda t: {"keyframes": 40, "idle": True}, lambda t: 2 if t < 12.0 else 0, 12.0),
        # A client that never hears back (killed for good): at most SETTLE_UNACKED_S more.
        (lambda t: {"keyframes": 40, "idle": True}, lambda t: 2, 42.0),
        # ... while the server still works then: when it is quiet after that.
        (lambda t: {"keyframes": min(int(t), 50), "idle": t >= 50}, lambda t: 2, 51.0),
    ],
)
def test_demo_settles_when_the_server_says_idle(monkeypatch, stats_at, unacked_at, ends_at):
    from coop_slam.tools import demo

    clock = _FakeClock(stats_at, unacked_at)
    # The demo module's own name for time, not the time module everyone shares.
    monkeypatch.setattr(demo, "time", SimpleNamespace(monotonic=clock.monotonic, sleep=clock.sleep))
    demo._settle(clock, 2.0, lambda *_: None)
    assert abs(clock.now - ends_at) <= 0.5


def test_the_demo_stops_loudly_when_the_server_refuses_its_map_file(tmp_path):
    """--load-map of a file that is not a team map: the server refuses it (FATAL) and the demo
    stops at once with that reason and a non-zero exit status, instead of running on without a
    server."""
    bad = tmp_path / "corrupt.map"
    bad.write_bytes(os.urandom(5000))
    out = tmp_path / "out"
    proc = subprocess.run(
        [os.path.join(REPO, "scripts", "demo"), *REVISIT, "--load-map", str(bad), "--no-record"]
        + ["--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode != 0
    assert f"{bad} is not a coop_slam map file" in proc.stdout
    assert not (out / "report.json").exists()
