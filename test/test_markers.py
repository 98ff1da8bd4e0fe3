"""Marker sighting: a robot body rendered by the synthetic world is found at its true pose."""

import numpy as np
import pytest

from coop_slam.errors import ConfigError
from coop_slam.geometry import invert, se3, transform_error
from coop_slam.markers import MarkerConfig, MarkerDetector, MarkerError, body_hypotheses
from coop_slam.synthetic.bodies import body_model
from coop_slam.synthetic.render import Renderer
from coop_slam.synthetic.world import DEFAULT_T_BASE_CAM, build_world


@pytest.mark.parametrize("yaw_deg", [180.0, 150.0, 90.0])
def test_marker_pose_of_a_rendered_body(yaw_deg):
    from coop_slam.camera import CameraModel
    from coop_slam.synthetic.render import DynamicObject, NoiseConfig

    camera = CameraModel(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
    renderer = Renderer(build_world("ring", 0), camera, NoiseConfig(enabled=False))
    T_world_base1 = se3(t=[0.0, 0.0, 0.0])
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    T_world_base2 = se3(R, [1.8, 0.1, 0.0])  # robot 2 ahead of robot 1's camera
    T_world_cam = T_world_base1 @ DEFAULT_T_BASE_CAM
    bgr, _ = renderer.render(T_world_cam, [DynamicObject(T_world_base2, body_model(2))])
    sightings = MarkerDetector(MarkerConfig()).detect(bgr, camera.K)
    assert sightings and {s.marker_id for s in sightings} == {2}  # two faces may be visible
    truth = invert(T_world_cam) @ T_world_base2
    for s in sightings:
        assert s.reprojection_error_px < 1.0
        errs = [transform_error(T, truth) for T in body_hypotheses(s.T_cam_body)]
        best_t, best_r = min(errs, key=lambda e: e[1])
        assert best_t < 0.05 and best_r < 3.0
        # The body position does not depend on which face was seen.
        assert np.linalg.norm(s.T_cam_body[:3, 3] - truth[:3, 3]) < 0.05


def test_empty_image_and_bad_config():
    with pytest.raises(MarkerError, match="empty"):
        MarkerDetector().detect(np.zeros((0, 0), np.uint8), np.eye(3))
    with pytest.raises(ConfigError, match="dictionary"):
        MarkerDetector(MarkerConfig(dictionary="DICT_NOPE"))


def test_body_box_covers_the_rendered_body():
    """The box the odometry ignores after a sighting contains every pixel of the seen body."""
    from coop_slam.camera import CameraModel
    from coop_slam.markers import body_box_cam
    from coop_slam.synthetic.render import DynamicObject, NoiseConfig

    camera = CameraModel(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
    renderer = Renderer(build_world("ring", 0), camera, NoiseConfig(enabled=False))
    a = np.radians(160.0)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    T_world_cam = DEFAULT_T_BASE_CAM
    bgr, depth = renderer.render(
        T_world_cam, [DynamicObject(se3(R, [1.6, 0.2, 0.0]), body_model(3))]
    )
    _, depth_empty = renderer.render(T_world_cam, [])
    v, u = np.nonzero(np.abs(depth - depth_empty) > 0.01)  # the body's pixels
    assert len(u) > 1000
    config = MarkerConfig(mask_grow_m=0.03)  # the marker pose is good to a few centimetres
    (sighting,) = [s for s in MarkerDetector(config).detect(bgr, camera.K)][:1]
    corners = body_box_cam(config, sighting.T_cam_body)
    assert corners.shape == (32, 3) and np.all(corners[:, 2] > 0)
    uv = corners[:, :2] / corners[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
    assert np.all((u >= u0) & (u <= u1) & (v >= v0) & (v <= v1))
    # ... and not much more than the body: the four heading hypotheses of a square body agree.
    assert (u1 - u0) * (v1 - v0) < 2.0 * (np.ptp(u) + 1) * (np.ptp(v) + 1)
    with pytest.raises(ConfigError, match="body_size_m"):
        MarkerDetector(MarkerConfig(body_size_m=[0.4, 0.4]))


def test_client_yaml_markers_section_is_the_defaults():
    import os

    from coop_slam.config import load_yaml_config

    path = os.path.join(os.path.dirname(__file__), "..", "config", "client.yaml")
    assert load_yaml_config(MarkerConfig, path, section="markers") == MarkerConfig()
