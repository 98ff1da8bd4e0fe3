"""Relative-pose estimation between two keyframes (place recognition and rendezvous).

Pure core: numpy arrays in, numpy arrays out (OpenCV for PnP; bundle adjustment in numpy).
Transforms follow ``T_a_b`` = maps points from frame b into frame a; ``T_a_b`` of two keyframes is
``T_camA_camB``.
"""

from .ba import BaResult, two_view_ba
from .camera import RegistrationError, backproject
from .icp import IcpResult, icp_descriptor
from .keyframe_view import KeyframeView, point_sigma_m, sample_depth
from .matching import match_descriptors
from .pnp import PnpResult, pnp_ransac
from .ransac import RansacResult, ransac_rigid
from .relative_pose import (
    RegistrationConfig,
    RelativePoseResult,
    estimate_3d3d,
    estimate_pnp,
    estimate_similarity,
)
from .umeyama import umeyama, umeyama_batch

__all__ = [
    "BaResult",
    "IcpResult",
    "KeyframeView",
    "PnpResult",
    "RansacResult",
    "RegistrationConfig",
    "RegistrationError",
    "RelativePoseResult",
    "backproject",
    "estimate_3d3d",
    "estimate_pnp",
    "estimate_similarity",
    "icp_descriptor",
    "match_descriptors",
    "pnp_ransac",
    "point_sigma_m",
    "ransac_rigid",
    "sample_depth",
    "two_view_ba",
    "umeyama",
    "umeyama_batch",
]
