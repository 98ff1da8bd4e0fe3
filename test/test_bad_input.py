"""Bad input must not corrupt the server's state: a seeded barrage of malformed and absurd keyframes
between the valid keyframes of a small team, the memory a keyframe may cost, and how rejections
are logged."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import tracemalloc

import numpy as np
import pytest

from coop_slam.errors import CoopSlamError
from coop_slam.registration import matching
from coop_slam.ros.validation import MAX_REASONS, RejectCounter, reason_kind
from coop_slam.team.config import ServerConfig
from coop_slam.team.server import ServerError, TeamServer
from coop_slam.wire.record import (
    ACTION_NEW,
    ACTION_REMOVE,
    ACTION_UPDATE,
    ARRAY_FIELDS,
    MAX_COVISIBLE,
    MAX_KEYPOINTS,
    KeyframeError,
)
from helpers import cylinder_world, team_keyframes, team_vocabulary

N_BAD = 5000
SEED = 24


@pytest.fixture(scope="module")
def team():
    """Robot 1 turning on the spot, robot 2 looking where robot 1 looked (they merge), and a
    vocabulary of the scene."""
    points, desc = cylinder_world(seed=3)
    r1 = team_keyframes(1, np.linspace(0, 2 * np.pi, 20, endpoint=False), points, desc)
    r2 = team_keyframes(
        2, np.linspace(2.0, 3.0, 8), points, desc, offset=(0.2, 0.1), seed=100, t0=100.0
    )
    return r1 + r2, team_vocabulary(r1)


def _server(vocab) -> TeamServer:
    return TeamServer(ServerConfig(robots=[1, 2]), vocab)


def checksum(server: TeamServer) -> str:
    """Digest of the stored keyframes, the pose graph (estimates and factors), the groups and what
    the stitching found."""
    h = hashlib.sha256()
    for key in sorted(server.store.keys()):
        rec = server.store.record(key)
        h.update(repr((key, rec.stamp_s, rec.action, rec.map_segment, rec.camera)).encode())
        for name in ("T_map_cam", *ARRAY_FIELDS):
            h.update(np.ascontiguousarray(getattr(rec, name)).tobytes())
    for robot in server.graph.robots:
        for k, T in sorted(server.graph.keyframe_poses(robot).items()):
            h.update(repr(k).encode() + T.tobytes())
        h.update(server.groups.T_root_map(robot).tobytes())
    h.update(repr(server.graph.edges()).encode())
    h.update(repr(server.groups.groups()).encode())
    h.update(repr([(m.map_a, m.keyframe_a, m.map_b, m.keyframe_b) for m in server.merges]).encode())
    h.update(repr([(c.key_a, c.key_b) for c in server.constraints]).encode())
    return h.hexdigest()


# --- the barrage: each breaker makes a valid keyframe invalid on its own --------------------------
def _set_row(name, row_value):
    def breaker(kf, rng, stored):
        arr = np.array(getattr(kf, name), dtype=np.float64)  # 1e300 stays finite
        if name == "T_map_cam":
            arr[rng.integers(0, 3), 3] = row_value(rng)
        elif len(arr):
            idx = tuple(rng.integers(0, s) for s in arr.shape)
            arr[idx] = row_value(rng)
        else:
            return _wrong_length(kf, rng, stored)
        setattr(kf, name, arr)
        return f"{name}[...] = {arr.max() if arr.size else None}"

    return breaker


def _wrong_length(kf, rng, stored):
    name = rng.choice(
        [
            "keypoints",
            "octaves",
            "descriptors",
            "depths_m",
            "map_point_ids",
            "map_points",
            "covisible_weights",
        ]
    )
    arr = getattr(kf, name)
    k = int(rng.integers(1, 6))
    if len(arr) > k and rng.random() < 0.5:
        arr = arr[:-k]
    else:
        arr = np.concatenate(
            [arr, arr[:1].repeat(k, axis=0) if len(arr) else np.zeros(k, arr.dtype)]
        )
    setattr(kf, name, arr)
    return f"{name} of length {len(arr)}"


def _absurd_camera(kf, rng, stored):
    cam = kf.camera
    field, value = [
        ("fx", 1e-300),
        ("fy", 1e300),
        ("fx", 0.5),
        ("fy", 1e8),
        ("cx", 1e6),
        ("cy", -1e300),
        ("width", 100000),
        ("height", 1 << 31),
    ][rng.integers(0, 8)]
    kf.camera = dataclasses.replace(cam, **{field: value})
    return f"camera {field} = {value}"


def _absurd_value(kf, rng, stored):
    name, value = [
        ("T_map_cam", lambda r: 1e300),
        ("T_map_cam", lambda r: -3e5),
        ("map_points", lambda r: 1e300),
        ("map_points", lambda r: 2e5),
        ("depths_m", lambda r: 1e30),
        ("depths_m", lambda r: -1.0),
        ("depths_m", lambda r: 5000.0),
        ("keypoints", lambda r: 1e30),
        ("keypoints", lambda r: -1e30),
    ][rng.integers(0, 9)]
    return _set_row(name, value)(kf, rng, stored)


def _not_finite(kf, rng, stored):
    name = rng.choice(["T_map_cam", "map_points", "depths_m", "keypoints"])
    value = [np.nan, np.inf, -np.inf][rng.integers(0, 3)]
    return _set_row(name, lambda r: value)(kf, rng, stored)


def _keypoint_size_or_angle(kf, rng, stored):
    col, value = [(2, -0.5), (2, -3.0), (2, 1e30), (3, 1e30), (3, -90.0), (3, 400.0)][
        rng.integers(0, 6)
    ]
    kf.keypoints = kf.keypoints.copy()
    kf.keypoints[rng.integers(0, len(kf.keypoints)), col] = value
    return f"keypoint column {col} = {value}"


def _bad_stamp(kf, rng, stored):
    kf.stamp_s = [np.nan, np.inf, -1.0, 1e300, 1e11][rng.integers(0, 5)]
    return f"stamp {kf.stamp_s}"


def _bad_rotation(kf, rng, stored):
    kf.T_map_cam = kf.T_map_cam.copy()
    kf.T_map_cam[:3, :3] *= [1e-300, 1.5, 1e300][rng.integers(0, 3)]
    return "rotation scaled"


def _unknown_robot(kf, rng, stored):
    kf.robot_id = [0, -1, 3, 99, 65535, 1.5][rng.integers(0, 6)]
    return f"robot {kf.robot_id}"


def _bad_ids(kf, rng, stored):
    choice = rng.integers(0, 4)
    if choice == 0 and stored:  # out of order: an id the server already has, sent as new
        kf.robot_id, kf.keyframe_id = stored[rng.integers(0, len(stored))]
        kf.action = ACTION_NEW
    else:
        kf.keyframe_id = [0, -5, 1 << 40, 2.5][rng.integers(0, 4)]
    return f"keyframe id {kf.robot_id}/{kf.keyframe_id}"


def _huge(kf, rng, stored):
    """Consistent arrays, just too many of them."""
    n = int(rng.integers(MAX_KEYPOINTS + 1, 3 * MAX_KEYPOINTS))
    if rng.random() < 0.2:
        kf.covisible_ids = np.arange(MAX_COVISIBLE + 1, dtype=np.uint32)
        kf.covisible_weights = np.ones(MAX_COVISIBLE + 1, np.uint16)
        return "too many covisible keyframes"
    idx = rng.integers(0, len(kf.keypoints), n)
    kf.map_points = kf.map_points_per_keypoint()[idx][kf.map_point_ids[idx] != 0]
    for name in ("keypoints", "octaves", "descriptors", "depths_m", "map_point_ids"):
        setattr(kf, name, getattr(kf, name)[idx])
    return f"{n} keypoints"


def _wrong_type(kf, rng, stored):
    name, make = [
        ("descriptors", lambda: kf.descriptors.astype(np.int16)),
        ("descriptors", lambda: kf.descriptors.astype(float)),
        ("keypoints", lambda: kf.keypoints.astype(object)),
        ("keypoints", lambda: kf.keypoints[:, :3]),
        ("map_points", lambda: kf.map_points.ravel()),
        ("T_map_cam", lambda: kf.T_map_cam[:3]),
        ("T_map_cam", lambda: kf.T_map_cam.tolist()),
        ("depths_m", lambda: kf.depths_m.astype(np.complex128)),
        ("octaves", lambda: kf.octaves.astype(np.float32) + 0.5),
    ][rng.integers(0, 9)]
    value = make()
    setattr(kf, name, value)
    return f"{name} as {getattr(value, 'dtype', type(value))}"


def _bad_action(kf, rng, stored):
    kf.action = [3, 255, -1, 1.0][rng.integers(0, 4)]
    return f"action {kf.action}"


def _remove_with_big_arrays(kf, rng, stored):
    """A REMOVE (of a stored keyframe, when there is one) carrying far too much."""
    if stored and rng.random() < 0.5:
        kf.robot_id, kf.keyframe_id = stored[rng.integers(0, len(stored))]
    kf.action = ACTION_REMOVE
    name = rng.choice(["keypoints", "descriptors", "map_points", "covisible_ids"])
    n = 200_000 if name != "covisible_ids" else MAX_COVISIBLE + 1
    shape = {"keypoints": (n, 4), "descriptors": (n, 32), "map_points": (n, 3)}.get(name, (n,))
    dtype = {"descriptors": np.uint8, "covisible_ids": np.uint32}.get(name, np.float32)
    setattr(kf, name, np.zeros(shape, dtype))
    return f"REMOVE with {n} {name}"


BREAKERS = [  # applied in this order: those changing shapes and types last
    _absurd_camera,
    _absurd_value,
    _not_finite,
    _keypoint_size_or_angle,
    _bad_stamp,
    _bad_rotation,
    _unknown_robot,
    _bad_ids,
    _bad_action,
    _huge,
    _wrong_length,
    _wrong_type,
]


def bad_keyframe(valid, rng, stored):
    """A copy of a valid keyframe broken by one to three breakers, sent as new or as an update of a
    stored keyframe; or a REMOVE with big arrays. Returns (record, what was done)."""
    kf = copy.deepcopy(valid[rng.integers(0, len(valid))])
    if rng.random() < 0.3 and stored:  # an update of a stored keyframe
        kf.robot_id, kf.keyframe_id = stored[rng.integers(0, len(stored))]
        kf.action = ACTION_UPDATE
    breakers = sorted(rng.choice(len(BREAKERS), int(rng.integers(1, 4)), replace=False))
    done = [BREAKERS[i](kf, rng, stored) for i in breakers]
    if rng.random() < 0.08:  # last: a REMOVE skips the content checks the others rely on
        done.append(_remove_with_big_arrays(kf, rng, stored))
    return kf, "; ".join(done)


@pytest.mark.slow
def test_a_barrage_of_bad_keyframes_leaves_the_team_map_untouched(team):
    valid, vocab = team
    reference = _server(vocab)
    for kf in valid:
        reference.add_keyframe(copy.deepcopy(kf))
    assert reference.groups.groups() == [[1, 2]] and reference.merges

    server = _server(vocab)
    rng = np.random.default_rng(SEED)
    per_gap = -(-N_BAD // len(valid))
    kinds: dict[type, int] = {}
    reasons = []
    for kf in valid:
        before = checksum(server)
        for _ in range(per_gap):
            bad, what = bad_keyframe(valid, rng, sorted(server.store.keys()))
            try:
                server.add_keyframe(bad)
            except (KeyframeError, ServerError) as exc:
                kinds[type(exc)] = kinds.get(type(exc), 0) + 1
                reasons.append(str(exc))
            except Exception as exc:  # noqa: BLE001 (the test is that there is none)
                pytest.fail(f"{what}: uncaught {type(exc).__name__}: {exc}")
            else:
                pytest.fail(f"accepted: {what}")
            after = checksum(server)
            assert after == before, f"rejected message changed the server's state: {what}"
        server.add_keyframe(copy.deepcopy(kf))
    assert sum(kinds.values()) >= N_BAD and set(kinds) == {KeyframeError, ServerError}
    # The team map after the barrage is the one of a server that never saw it: same keyframes,
    # same merges, same optimized poses.
    assert checksum(server) == checksum(reference)
    assert server.groups.groups() == [[1, 2]] and len(server.merges) == len(reference.merges)
    server.optimize(full=True)
    reference.optimize(full=True)
    for robot in (1, 2):
        for k, T in reference.optimized_keyframes(robot).items():
            np.testing.assert_allclose(server.optimized_keyframes(robot)[k], T, atol=1e-9)

    # Logged as a node would (a rejection every 10 ms): every kind of reason at least once, then a
    # count per kind and period; far fewer lines than rejections.
    lines, now = [], [0.0]
    counter = RejectCounter("server", log=lambda f, *a: lines.append(f % a), clock=lambda: now[0])
    for reason in reasons:
        now[0] += 0.01
        counter.reject("/robot_1/keyframes", reason)
    counter.flush(force=True)
    kinds_seen = {reason_kind(r) for r in reasons}
    assert len(kinds_seen) < MAX_REASONS and counter.total == len(reasons)
    for kind in kinds_seen:
        assert any(reason_kind(line).endswith(kind) for line in lines), kind
    assert len(lines) < len(reasons) / 5
    assert sum(counter.reason_counts.values()) == len(reasons)


@pytest.mark.slow
def test_a_failing_pose_graph_step_is_survived_by_the_server(team, monkeypatch, caplog):
    """A pose graph whose optimizer throws once: the server logs why, keeps its map and optimizes
    normally afterwards."""
    valid, vocab = team
    server, reference = _server(vocab), _server(vocab)
    for kf in valid[:10]:
        server.add_keyframe(copy.deepcopy(kf))
        reference.add_keyframe(copy.deepcopy(kf))
    graph = server.graph
    real = type(graph).optimize_full

    def failing_once(self):
        monkeypatch.setattr(type(graph), "optimize_full", real)
        self._step_failed("full", RuntimeError("Indeterminant linear system (injected)"))

    before = checksum(server)
    monkeypatch.setattr(type(graph), "optimize_full", failing_once)
    with caplog.at_level("WARNING", logger="coop_slam.team.server"):
        server.optimize(full=True)
    assert "pose graph optimization failed" in caplog.text and "injected" in caplog.text
    assert checksum(server) == before
    for kf in valid[10:]:
        server.add_keyframe(copy.deepcopy(kf))
        reference.add_keyframe(copy.deepcopy(kf))
    assert server.groups.groups() == reference.groups.groups() == [[1, 2]]
    for robot in (1, 2):
        for k, T in reference.optimized_keyframes(robot).items():
            np.testing.assert_allclose(server.optimized_keyframes(robot)[k], T, atol=1e-3)


def _odd(kf, rng):
    """A valid keyframe made odd, still within bounds: the server takes it or refuses it (a
    duplicate), nothing else."""
    kf = copy.deepcopy(kf)
    choice = rng.integers(0, 8)
    if choice == 0:  # no keypoints at all
        for name in ("keypoints", "octaves", "descriptors", "depths_m", "map_point_ids"):
            setattr(kf, name, getattr(kf, name)[:0])
        kf.map_points = kf.map_points[:0]
    elif choice == 1:  # no depth (a monocular client)
        kf.depths_m[:] = 0.0
    elif choice == 2:  # every keypoint observing one map point
        kf.map_point_ids[kf.map_point_ids != 0] = 1
    elif choice == 3:  # an update of a keyframe the server never had
        kf.action, kf.keyframe_id = ACTION_UPDATE, kf.keyframe_id + 1000
    elif choice == 4:  # a remove of a keyframe the server may not have
        kf.action, kf.keyframe_id = ACTION_REMOVE, int(rng.integers(1, 3000))
    elif choice == 5:  # out of order, up to the largest id
        kf.keyframe_id = int(rng.integers(1, (1 << 32) - 1))
    elif choice == 6:
        kf.descriptors[:] = 0
    else:
        kf.stamp_s = float(rng.uniform(0, 1e9))
    return kf


def test_odd_but_valid_keyframes_in_any_order_are_taken_without_error(team):
    valid, vocab = team
    server = _server(vocab)
    rng = np.random.default_rng(SEED)
    for i in rng.permutation(len(valid)):
        for kf in [_odd(valid[i], rng) for _ in range(10)] + [copy.deepcopy(valid[i])]:
            try:
                server.add_keyframe(kf)
            except (KeyframeError, ServerError):
                pass  # a duplicate: an odd copy took the id first
    assert server.groups.groups() == [[1, 2]]
    server.optimize(full=True)
    assert server.graph.stats.mode == "full"
    for robot in (1, 2):
        assert all(np.all(np.isfinite(T)) for T in server.optimized_keyframes(robot).values())


# --- memory per keyframe --------------------------------------------------------------------------
def _inflate(kf, n, rng):
    """The keyframe with n keypoints (its own, repeated with a pixel of jitter)."""
    idx = rng.integers(0, kf.num_keypoints, n)
    points = kf.map_points_per_keypoint()
    kf.keypoints = kf.keypoints[idx].copy()
    kf.keypoints[:, :2] = np.clip(
        kf.keypoints[:, :2] + rng.uniform(-1, 1, (n, 2)), 0, [kf.camera.width - 1, 479]
    )
    for name in ("descriptors", "octaves", "depths_m", "map_point_ids"):
        setattr(kf, name, getattr(kf, name)[idx].copy())
    kf.map_points = points[idx][kf.map_point_ids != 0].astype(np.float32)
    return kf.validate()


def test_two_keyframes_at_the_keypoint_limit_cost_bounded_memory(team, monkeypatch):
    """Two robots sending keyframes of MAX_KEYPOINTS keypoints of one place: the server matches
    them block by block (it allocated the whole distance matrix: 20k x 20k, 6.5 GB)."""
    valid, vocab = team
    rng = np.random.default_rng(0)
    r1 = [copy.deepcopy(kf) for kf in valid if kf.robot_id == 1]
    r2 = [copy.deepcopy(kf) for kf in valid if kf.robot_id == 2][:2]
    _inflate(r1[7], MAX_KEYPOINTS, rng)  # yaw 2.2, where robot 2 looks
    _inflate(r2[-1], MAX_KEYPOINTS, rng)
    server = _server(vocab)
    for kf in r1 + r2[:-1]:
        server.add_keyframe(kf)
    sizes = []
    match_ratio = matching.match_ratio

    def spy(a, b, *args, **kwargs):
        sizes.append(len(a) * len(b))
        return match_ratio(a, b, *args, **kwargs)

    monkeypatch.setattr(matching, "match_ratio", spy)
    tracemalloc.start()
    try:
        server.add_keyframe(r2[-1])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert max(sizes) == MAX_KEYPOINTS**2  # the two big keyframes were matched
    assert peak < 200e6, f"{peak / 1e6:.0f} MB"


# --- how rejections are logged --------------------------------------------------------------------
def test_each_reason_is_logged_once_then_counted_per_period():
    lines, now = [], [0.0]
    counter = RejectCounter(
        "server", log_period_s=5.0, log=lambda f, *a: lines.append(f % a), clock=lambda: now[0]
    )
    for i in range(100):  # one reason, numbers aside
        counter.reject("/robot_1/keyframes", f"keyframe {i} of robot 1: stamp {-1.5 * i} s is bad")
    counter.reject("/robot_1/keyframes", "keyframe 7 of robot 1: 30001 keypoints exceed the limit")
    counter.reject("/robot_2/keyframes", "keyframe 7 of robot 2: stamp -1e+300 s is bad")
    assert len(lines) == 3  # each kind of reason at once, with the reason itself
    assert lines[0].endswith("keyframe 0 of robot 1: stamp -0.0 s is bad")
    assert "30001 keypoints" in lines[1] and "on /robot_2/keyframes" in lines[2]
    now[0] = 6.0
    counter.reject("/robot_1/keyframes", "keyframe 200 of robot 1: stamp 3 s is bad")
    assert len(lines) == 4
    assert lines[3].startswith("server: 100 more rejected on /robot_1/keyframes for the same")
    assert "(101 in all), latest: keyframe 200 of robot 1: stamp 3 s is bad" in lines[3]
    counter.reject("/robot_1/keyframes", "keyframe 201 of robot 1: stamp 4 s is bad")
    assert len(lines) == 4  # within the period: counted, not logged
    counter.flush(force=True)  # e.g. at shutdown
    assert len(lines) == 5 and "1 more rejected" in lines[4]
    assert counter.total == 104 and counter.counts["/robot_2/keyframes"] == 1


def test_reasons_tracked_are_bounded():
    lines = []
    counter = RejectCounter("client", log=lambda f, *a: lines.append(f % a), clock=lambda: 0.0)
    for i in range(3 * MAX_REASONS):
        counter.reject("/correction", f"reason {chr(65 + i % 26) * (1 + i // 26)}")
    assert len(counter.reason_counts) == MAX_REASONS + 1  # the last: all further reasons
    assert len(lines) == MAX_REASONS + 1 and counter.total == 3 * MAX_REASONS


def _store_checksum(path: str) -> str:
    """Digest of everything a map file holds (every table, every row)."""
    import sqlite3

    db = sqlite3.connect(path)
    h = hashlib.sha256()
    for (table,) in db.execute("SELECT name FROM sqlite_master WHERE type='table' ORDER BY name"):
        for row in db.execute(f"SELECT * FROM {table} ORDER BY rowid"):
            h.update(repr(row).encode())
    db.close()
    return h.hexdigest()


@pytest.mark.slow
def test_bad_keyframes_leave_the_map_file_unchanged(team, tmp_path):
    """Through the durable server: a rejected message writes nothing to the map file, and the
    file after the barrage rebuilds the team map of a server that never saw it."""
    from coop_slam.team.durable import DurableServer, poses_equal

    valid, vocab = team
    path = str(tmp_path / "map.db")
    durable = DurableServer(ServerConfig(robots=[1, 2]), lambda c: TeamServer(c, vocab), path)
    rng = np.random.default_rng(SEED + 1)
    for kf in valid:
        before = _store_checksum(path)
        for _ in range(8):
            bad, what = bad_keyframe(valid, rng, sorted(durable.server.store.keys()))
            try:
                out = durable.add_keyframe(bad)
            except (KeyframeError, ServerError, CoopSlamError):
                pass
            else:
                assert out.rejected, f"accepted: {what}"
            assert _store_checksum(path) == before, f"rejected message changed the file: {what}"
        durable.add_keyframe(copy.deepcopy(kf))
    durable.close()
    resumed = DurableServer(
        ServerConfig(robots=[1, 2]), lambda c: TeamServer(c, vocab), path, resume=True
    )
    reference = _server(vocab)
    for kf in valid:
        reference.add_keyframe(copy.deepcopy(kf))
    assert resumed.rebuilt.max_pose_diff_m < 1e-9 and poses_equal(resumed.server, reference)
