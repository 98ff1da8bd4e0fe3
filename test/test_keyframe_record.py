"""KeyframeRecord.validate: malformed and physically absurd keyframes are rejected with a message
naming the field; well-formed ones (and the limits themselves) pass."""

import dataclasses

import numpy as np
import pytest

from coop_slam.wire.record import (
    ACTION_REMOVE,
    MAX_COVISIBLE,
    MAX_DEPTH_M,
    MAX_IMAGE_SIDE_PX,
    MAX_KEYPOINTS,
    MAX_POSITION_M,
    MAX_STAMP_S,
    KeyframeError,
    KeyframeRecord,
)
from helpers import camera, make_keyframe


def _camera(**changes):
    return dataclasses.replace(camera(), **changes)


def _set(name, value):
    return lambda kf: setattr(kf, name, value)


def _edit(name, fn):
    def mutate(kf):
        arr = getattr(kf, name).copy()
        fn(arr)
        setattr(kf, name, arr)

    return mutate


def _translate(t):
    def mutate(kf):
        kf.T_map_cam = kf.T_map_cam.copy()
        kf.T_map_cam[:3, 3] = t

    return mutate


@pytest.mark.parametrize(
    "mutate, match",
    [
        # What the fuzzer found accepted: finite yet absurd.
        (_set("camera", _camera(fx=1e-300)), r"fx = 1e-300 px is outside \[1, 64000\]"),
        (_set("camera", _camera(fy=1e9)), "fy = 1e.09 px is outside"),
        (_set("camera", _camera(cx=1e6)), "principal point"),
        (_set("camera", _camera(cy=-500.0)), "principal point"),
        (_set("camera", _camera(width=20000, cx=100.0)), "exceeds 16384 px per side"),
        (_translate([1e300, 0, 0]), "pose position 1e.300 m from the map origin"),
        (_translate([0, 0, -2 * MAX_POSITION_M]), "beyond the 100000 m"),
        (_edit("map_points", lambda a: a.__setitem__((3, 1), 1e30)), "a map point lies 1e.30 m"),
        (_edit("depths_m", lambda a: a.__setitem__(2, 5000.0)), r"depths must be in \[0, 1000\]"),
        (_edit("depths_m", lambda a: a.__setitem__(2, -1.0)), "depths must be"),
        (_set("stamp_s", 1e300), "stamp 1e.300 s is not a valid time"),
        (_set("stamp_s", -0.5), "not a valid time"),
        (_set("stamp_s", float("nan")), "not a valid time"),
        (_edit("keypoints", lambda a: a.__setitem__((0, 2), -1.0)), r"sizes must be in \[0, 800\]"),
        (_edit("keypoints", lambda a: a.__setitem__((0, 2), 1e30)), "sizes must be in"),
        (
            _edit("keypoints", lambda a: a.__setitem__((4, 3), 720.0)),
            r"angles must be in \[-1, 360\]",
        ),
        (_edit("keypoints", lambda a: a.__setitem__((4, 3), -5.0)), "angles must be in"),
        (_edit("octaves", lambda a: a.__setitem__(0, 200)), "octave 200 is above"),
        # Malformed.
        (_set("robot_id", 0), "robot_id 0 is invalid"),
        (_set("robot_id", 1.5), "robot_id 1.5 is invalid"),
        (_set("keyframe_id", -3), "keyframe_id -3 of robot 1 is invalid"),
        (_set("keyframe_id", 1 << 40), "keyframe_id .* is invalid"),
        (_set("action", 7), "unknown action 7"),
        (_set("map_segment", -1), "map_segment -1"),
        (_set("T_map_cam", np.full((4, 4), np.nan)), "pose contains NaN or inf"),
        (_set("T_map_cam", np.eye(3)), r"pose has shape \(3, 3\)"),
        (_set("T_map_cam", "identity"), "pose must be a numeric array"),
        (_set("camera", "pinhole"), "camera must be a CameraModel"),
        (_set("keypoints", np.zeros((10, 3), np.float32)), r"keypoints has shape \(10, 3\)"),
        (_set("keypoints", np.zeros((10, 4), object)), "keypoints must be a numeric array"),
        (_set("descriptors", np.zeros((50, 32), np.int16)), "descriptors must be 50 x 32 bytes"),
        (_set("descriptors", np.zeros((49, 32), np.uint8)), "descriptors must be 50 x 32 bytes"),
        (_set("octaves", np.zeros(3, np.uint8)), "octaves has 3 entries, expected one per"),
        (_set("map_point_ids", np.full(50, -1, np.int64)), "map_point_ids holds a negative"),
        (_set("map_points", np.zeros((2, 3), np.float32)), "expected 3 x 25"),
        (_edit("keypoints", lambda a: a.__setitem__((1, 0), np.inf)), "keypoints contains NaN"),
        (_edit("keypoints", lambda a: a.__setitem__((1, 0), 5000.0)), "outside the 640x480"),
        (_set("covisible_weights", np.zeros(5, np.uint16)), "differ in length"),
        (
            _set("keypoints", np.zeros((MAX_KEYPOINTS + 1, 4), np.float32)),
            f"keypoints holds {MAX_KEYPOINTS + 1} entries, above the limit of {MAX_KEYPOINTS}",
        ),
        (
            _set("covisible_ids", np.zeros(MAX_COVISIBLE + 1, np.uint32)),
            "covisible_ids holds .* above the limit",
        ),
    ],
)
def test_bad_keyframes_are_rejected_naming_the_field(mutate, match):
    kf = make_keyframe(n=50)
    mutate(kf)
    with pytest.raises(KeyframeError, match=match):
        kf.validate({1, 2})


def test_keyframes_at_the_limits_pass():
    kf = make_keyframe(n=MAX_KEYPOINTS)
    kf.camera = _camera(width=MAX_IMAGE_SIDE_PX, height=480, fx=1.0, fy=100.0 * MAX_IMAGE_SIDE_PX)
    kf.T_map_cam = kf.T_map_cam.copy()
    kf.T_map_cam[:3, 3] = [MAX_POSITION_M, -MAX_POSITION_M, 0.0]
    kf.depths_m[:2] = [0.0, MAX_DEPTH_M]  # 0 = no depth
    kf.keypoints[:2, 3] = [-1.0, 360.0]  # -1 = no orientation
    kf.stamp_s = np.nextafter(MAX_STAMP_S, 0)
    kf.covisible_ids = np.arange(1, MAX_COVISIBLE + 1, dtype=np.uint32)
    kf.covisible_weights = np.ones(MAX_COVISIBLE, np.uint16)
    assert kf.validate({1}) is kf
    # A principal point off the image centre (a cropped sensor) is a camera still.
    kf = make_keyframe()
    kf.camera = _camera(cx=-600.0, cy=900.0)
    kf.validate()


def test_a_remove_is_bounded_but_its_contents_are_not_looked_at():
    kf = make_keyframe(n=20)
    kf.action = ACTION_REMOVE
    kf.depths_m = np.full(3, np.nan, np.float32)  # contents of a REMOVE are ignored ...
    assert kf.validate({1}) is kf
    for name, arr in [
        ("keypoints", np.zeros((200_000, 4), np.float32)),  # ... its sizes are not
        ("descriptors", np.zeros((200_000, 32), np.uint8)),
        ("map_points", np.zeros((MAX_KEYPOINTS + 1, 3), np.float32)),
        ("covisible_ids", np.zeros(MAX_COVISIBLE + 1, np.uint32)),
    ]:
        big = make_keyframe(n=20)
        big.action = ACTION_REMOVE
        setattr(big, name, arr)
        with pytest.raises(KeyframeError, match=f"{name} holds .* above the limit"):
            big.validate({1})
    bad = make_keyframe(n=20)
    bad.action = ACTION_REMOVE
    bad.T_map_cam = np.full((4, 4), 1e300)
    with pytest.raises(KeyframeError, match="pose"):
        bad.validate({1})


def test_the_clients_remove_record_passes():
    """What vo.outbox sends for a culled keyframe: identity pose, stamp 0, empty arrays."""
    rec = KeyframeRecord(2, 7, 0.0, camera(), np.eye(4), action=ACTION_REMOVE)
    assert rec.validate({1, 2}) is rec
