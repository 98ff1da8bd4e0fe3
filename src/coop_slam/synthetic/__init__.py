"""Deterministic synthetic multi-robot RGB-D world: the project's embedded default dataset.

``world`` builds textured indoor buildings and ``bodies`` robot bodies with ArUco markers,
``render`` draws colour and exact depth through a pinhole camera (with optional sensor noise),
``scenarios`` gives the robots' ground-truth routes (``hand_held`` those of cameras carried by
hand), ``overlap`` derives when robots could first be merged, and ``generate`` writes everything as
TUM RGB-D folders (``coop_slam.synthetic.generate.generate``, read back with
``coop_slam.datasets.read_synthetic``).
"""

from .bodies import body_model
from .render import DEFAULT_CAMERA, DynamicObject, NoiseConfig, Renderer
from .scenarios import DEFAULT_SCENARIO, SCENARIOS, Scenario, make_scenario
from .world import DEFAULT_T_BASE_CAM, build_world

__all__ = [
    "DEFAULT_CAMERA",
    "DEFAULT_SCENARIO",
    "DEFAULT_T_BASE_CAM",
    "SCENARIOS",
    "DynamicObject",
    "NoiseConfig",
    "Renderer",
    "Scenario",
    "body_model",
    "build_world",
    "make_scenario",
]
