"""The odometry's compiled kernels (numba: the pose optimization, the projection and its search,
the stereo matching, the local BA, a map point's distinctive descriptor and the vocabulary's
descent for place signatures), compiled before the first frame rather than on it; and the
compiled extraction's first call.

numba compiles a kernel on its first call (about 5 s for both here) and keeps the machine code in
its cache beside the sources, so later starts load it (a tenth of a second). ``scripts/setup``
fills the cache; :class:`coop_slam.vo.VisualOdometry` warms up when it is made, so no frame
waits for the compiler."""

from __future__ import annotations

import threading

import numpy as np

from ..bow import vocabulary
from ..descriptors import most_distinctive
from ..optim import schur_ba
from .config import VoConfig
from .features import FrameFeatures, OrbExtractor, OrbKeypoints, level_images, orb_level_scales32
from .matching import Projection, project_points, search_by_projection
from .pose_opt import optimize_pose
from .stereo_matching import match_stereo

# Once a process: an odometry made when the first frame has come (a client's) then takes ~5 ms,
# not the ~15-45 ms of calling every kernel again.
_WARM: list = []
_WARM_LOCK = threading.Lock()


def warm_up() -> None:
    """Call each kernel once on a tiny problem (compiles it, or loads it from the cache); once a
    process."""
    with _WARM_LOCK:
        if not _WARM:
            _call_each_kernel()
            _WARM.append(True)


def _call_each_kernel() -> None:
    vocabulary.warm_up()
    schur_ba.warm_up()  # the local BA's (its process warms up on its own; this fills the cache)
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    points = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0], [0.0, 0.5, 2.5], [0.5, 0.5, 3.0]])
    uv = points[:, :2] / points[:, 2:] * 500.0 + [320.0, 240.0]
    optimize_pose(np.eye(4), points, uv, uv[:, 0] - 20.0, np.ones(4), K, 40.0)
    n = len(uv)
    desc = np.zeros((n, 32), np.uint8)
    frame = FrameFeatures(
        uv, np.ones(n, np.float32), np.full(n, -1, np.float32), np.zeros(n, np.uint8), desc,
        np.ones(n, np.float32), points, uv[:, 0] - 20.0,
    )  # fmt: skip
    proj = Projection(np.arange(n), uv, uv[:, 0] - 20.0, points[:, 2], np.zeros(n, int))
    scales = 1.2 ** np.arange(8)
    project_points(np.eye(4), points, K, 40.0, (640, 480), scales, np.full(n, 5.0), -points)
    for chi2 in (None, 5.991):
        search_by_projection(proj, desc, frame, 4.0, scales, 50, 0.9, chi2_gate=chi2)
    image = np.zeros((64, 96), np.uint8)
    kps = OrbKeypoints(uv + [-300.0, -200.0], np.ones(n, np.float32), np.zeros(n, np.float32),
                       np.zeros(n, np.uint8), desc)  # fmt: skip
    levels = level_images(image, orb_level_scales32(1.2, 8))
    # The compiled extraction's first call sets up OpenCV's ORB, FAST and blur (~4 ms).
    texture = np.random.default_rng(0).integers(0, 256, (240, 320), dtype=np.uint8)
    OrbExtractor(VoConfig(), None).extract_images([texture, texture])
    match_stereo(kps, kps, levels, levels, scales, 500.0, VoConfig())
    most_distinctive(np.zeros((1, 8, 4), np.uint64), np.ones((1, 8), bool))  # local mapping's
