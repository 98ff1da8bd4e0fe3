"""Each robot describes its own camera and marker mounts; the server places a sighting of robot b
with b's description, never with one team-wide mount."""

import logging
from types import SimpleNamespace

import numpy as np
import pytest

from coop_slam.geometry import invert, se3, transform_error
from coop_slam.markers import MarkerConfig, MarkerDetector, body_hypotheses
from coop_slam.robot_description import (
    MarkerSeen,
    RobotDescription,
    RobotDescriptionError,
    describe,
)
from coop_slam.synthetic.scenarios import camera_mount
from coop_slam.synthetic.world import DEFAULT_T_BASE_CAM


def _yaw(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def test_a_sighting_with_another_marker_size_is_placed_by_the_observed_robots_own():
    """Robot 2 carries a 0.18 m marker; robot 1 assumes 0.25 m (its own). Taken as it is, the
    body would be 39 % too far; rescaled by robot 2's description it is where it is."""
    from coop_slam.camera import CameraModel
    from coop_slam.synthetic.bodies import body_model
    from coop_slam.synthetic.render import DynamicObject, NoiseConfig, Renderer
    from coop_slam.synthetic.world import build_world

    camera = CameraModel(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
    renderer = Renderer(build_world("ring", 0), camera, NoiseConfig(enabled=False))
    T_world_base2 = se3(_yaw(180.0), [1.5, 0.05, 0.0])
    bgr, _ = renderer.render(
        DEFAULT_T_BASE_CAM, [DynamicObject(T_world_base2, body_model(2, 0.18))]
    )
    observer = MarkerDetector(MarkerConfig(marker_size_m=0.25))
    (s,) = [s for s in observer.detect(bgr, camera.K) if s.marker_id == 2][:1]
    truth = invert(DEFAULT_T_BASE_CAM) @ T_world_base2
    robot_2 = describe(2, "rgbd", camera_mount(0.8, 20.0), MarkerConfig(marker_size_m=0.18))
    placed = robot_2.T_cam_body(MarkerSeen(s.T_cam_marker, 0.25))
    err_t, err_r = min(transform_error(T, truth) for T in body_hypotheses(placed))
    assert err_t < 0.05 and err_r < 3.0
    naive_t = np.linalg.norm(s.T_cam_body[:3, 3] - truth[:3, 3])  # the observer's own marker
    assert naive_t > 0.3


def test_descriptions_are_validated_with_the_robot_and_field_named():
    good = describe(3, "stereo", camera_mount(0.5, 10.0), MarkerConfig())
    good.validate()
    bad = [
        (dict(sensor="lidar"), "sensor"),
        (dict(marker_size_m=0.0), "marker_size_m"),
        (dict(T_base_cam=np.full((4, 4), np.nan)), "T_base_cam"),
        (dict(T_base_marker=np.diag([2.0, 1.0, 1.0, 1.0])), "T_base_marker"),
        (dict(body_size_m=(0.4, 0.4)), "body_size_m"),
    ]
    for change, field in bad:
        with pytest.raises(RobotDescriptionError, match=f"robot 3.*{field}"):
            RobotDescription(**{**good.__dict__, **change})


def test_camera_mount_height_and_pitch():
    T = camera_mount(0.8, 20.0)
    assert T[2, 3] == pytest.approx(0.8)
    optical_axis_base = T[:3, :3] @ [0.0, 0.0, 1.0]
    assert np.degrees(np.arcsin(-optical_axis_base[2])) == pytest.approx(20.0)
    assert optical_axis_base[0] > 0.9  # still looking forward
    np.testing.assert_allclose(camera_mount(0.5, 0.0)[:3, :3], DEFAULT_T_BASE_CAM[:3, :3])


class _Durable:
    """What the worker hands the durable server for a sighting."""

    def __init__(self):
        self.calls = []
        self.server = SimpleNamespace(known_robots={1, 2})
        self.pull = None

    def sighting(self, a, b, stamp_s, T_camA_bodyB, T_bodyB_camB):
        self.calls.append((a, b, T_camA_bodyB, T_bodyB_camB))
        return None


def test_the_worker_places_sightings_with_the_sighted_robots_description(caplog):
    from coop_slam.team.config import ServerConfig
    from coop_slam.team.jobs import RendezvousJob
    from coop_slam.team.worker import ServerWorker

    durable = _Durable()
    worker = ServerWorker(ServerConfig(robots=[1, 2]), lambda resume, load: durable)
    T_cam_marker = se3(_yaw(30.0), [0.2, 0.1, 2.0])
    job = RendezvousJob(1, 2, 5.0, MarkerSeen(T_cam_marker, 0.25), sighting=True)
    with caplog.at_level(logging.WARNING):
        worker.handle(job)
        worker.handle(job)
    assert durable.calls[-1][2:] == (None, None)  # robot 2 said nothing: when, not where
    assert sum("robot 2 has not described itself" in r.message for r in caplog.records) == 1

    mount_1, mount_2 = camera_mount(0.3, 0.0), camera_mount(0.8, 20.0)
    worker.sightings.describe(describe(1, "rgbd", mount_1, MarkerConfig()))
    worker.sightings.describe(describe(2, "rgbd", mount_2, MarkerConfig(marker_size_m=0.125)))
    worker.handle(job)
    _, _, T_camA_bodyB, T_bodyB_camB = durable.calls[-1]
    np.testing.assert_allclose(T_bodyB_camB, mount_2)  # robot 2's camera, not robot 1's
    expected = T_cam_marker.copy()
    expected[:3, 3] *= 0.5
    np.testing.assert_allclose(
        T_camA_bodyB, expected @ invert(MarkerConfig().base_marker()), atol=1e-12
    )
