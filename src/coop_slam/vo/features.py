"""ORB features of one frame, spread over the image and the scale pyramid; and the frame's
features as tracking uses them (:class:`FrameFeatures`: keypoints with what the sensor measured
about each, see :mod:`.sensor`).

OpenCV's ORB keeps the keypoints with the best Harris score, which clusters them on strongly
textured regions. As ORB-SLAM does with its quadtree, we detect more candidates than needed and keep
the best of each grid cell of each pyramid level first (round robin over cells: every cell's best,
then every cell's second best, ...). A low FAST threshold gives texture-poor cells candidates where
a level has few strong corners; in textured cells the Harris ranking still prefers the strong
corners, which gives the effect of ORB-SLAM's two-threshold FAST fallback per level (a second
masked ORB pass, for texture-poor cells only, costs a full detection: measured 6 ms). Descriptors
are computed for the kept keypoints only.

FAST at the low threshold costs about twice as much as at ORB-SLAM's first threshold (20: far more
pixels pass its first test). OpenCV's ORB keeps a level's 2n best FAST scores, then the n best
Harris responses of those; so when a level has 2n corners of score 20 or more, detecting it at 20
finds the same keypoints as the low threshold (as a set: in another order; OpenCV >= 3 keeps the
ties at the cut). Each level can therefore be detected at the first threshold (stereo cameras),
and again at the low one only when that finds fewer keypoints than the level wants (a level with
between n and 2n strong corners keeps those, not weaker ones that would win on Harris response).

The extraction runs compiled (orb_native.cpp, through OpenCV's C++ API): made in Python, a
cv2.KeyPoint object per candidate and the tables read back from them cost ~2 ms of a KITTI image's
~14, and held Python's lock while the other image's extraction wanted it. It detects as ORB does,
but orients only the keypoints the grid keeps (ORB orients every one it finds) with the same
angles; a KITTI pair's extraction 12.2 -> 11.2 ms.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import CameraModel
from .config import VoConfig
from .types import VoError

_PATCH_PX = 31  # ORB's descriptor patch


@dataclass
class OrbKeypoints:
    """ORB keypoints of one image (level-0 pixel coordinates) and their descriptors."""

    uv_px: np.ndarray  # (N, 2) float64
    size_px: np.ndarray  # (N,) float32
    angle_deg: np.ndarray  # (N,) float32, -1 = none
    octaves: np.ndarray  # (N,) uint8 pyramid level
    descriptors: np.ndarray  # (N, 32) uint8

    def __len__(self) -> int:
        return len(self.uv_px)


@dataclass
class FrameFeatures:
    """Keypoints of one frame (level-0 pixel coordinates) with depth and back-projected 3D."""

    uv_px: np.ndarray  # (N, 2) float64
    size_px: np.ndarray  # (N,) float32
    angle_deg: np.ndarray  # (N,) float32, -1 = none
    octaves: np.ndarray  # (N,) uint8 pyramid level
    descriptors: np.ndarray  # (N, 32) uint8
    depths_m: np.ndarray  # (N,) float32, 0 = none
    points_cam: np.ndarray  # (N, 3) float64, NaN where there is no depth
    u_right_px: np.ndarray  # (N,) float64, virtual right-image u; NaN where there is no depth
    _tree: object = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.uv_px)

    @property
    def has_depth(self) -> np.ndarray:
        return self.depths_m > 0

    def subset(self, keep: np.ndarray) -> "FrameFeatures":
        """The keypoints selected by ``keep`` (boolean mask or indices)."""
        return FrameFeatures(
            self.uv_px[keep],
            self.size_px[keep],
            self.angle_deg[keep],
            self.octaves[keep],
            self.descriptors[keep],
            self.depths_m[keep],
            self.points_cam[keep],
            self.u_right_px[keep],
        )

    def tree(self):
        """KD-tree over uv_px (built on first use, shared by all searches on this frame)."""
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.uv_px if len(self.uv_px) else np.zeros((0, 2)))
        return self._tree


def level_scales(config: VoConfig) -> np.ndarray:
    """Scale of each pyramid level relative to level 0 (1, 1.2, 1.44, ...)."""
    return config.features.scale_factor ** np.arange(config.features.n_levels, dtype=float)


def orb_level0_uv(pt_px: np.ndarray, octaves: np.ndarray, scale_factor: float) -> np.ndarray:
    """Level-0 pixel position (N, 2) of OpenCV ORB keypoints from their reported ``pt``.

    OpenCV finds a keypoint at pixel x_l of pyramid level l (scale s = scale_factor**l) and
    reports x_l * s. With pixel centres, as cv2.resize samples, that pixel sits at
    (x_l + 0.5) * s - 0.5 of level 0. The reported position was up to 1.3 px (level 7) to the
    top-left of that. Measured offline on 12 synthetic robot sequences: camera height bias
    -0.79 -> -0.38 cm, mean ATE 0.63 -> 0.49 cm. OpenCV's level images are round(W / s) wide, so
    the exact sample position is (x_l + 0.5) * W / W_l - 0.5. Using that scaled those
    trajectories by 0.25-0.3 % on 2 of the 12 sequences (mean ATE 0.75 cm); why is not
    understood, so the ideal pyramid's mapping is used.
    """
    s = float(scale_factor) ** np.asarray(octaves, dtype=float).reshape(-1, 1)
    return np.asarray(pt_px, dtype=float).reshape(-1, 2) + 0.5 * (s - 1.0)


def inv_sigma2(config: VoConfig, octaves: np.ndarray) -> np.ndarray:
    """Measurement information per keypoint: 1 / (1 px * scale**octave)**2, as in ORB-SLAM."""
    return 1.0 / level_scales(config)[np.asarray(octaves, dtype=int)] ** 2


def orb_level_scales32(scale_factor: float, n_levels: int) -> np.ndarray:
    """Each pyramid level's scale as OpenCV's ORB has it (float32, from its float32 scale factor):
    it reports positions and sizes its levels with these."""
    return np.float32(float(np.float32(scale_factor)) ** np.arange(n_levels))


def level_images(gray: np.ndarray, scales32: np.ndarray) -> list[np.ndarray]:
    """The image at each pyramid level (level 0 = gray), sized (in float32: at .5 the rounding
    differs from double's, e.g. 540 / 1.2**3) and resized as OpenCV's ORB does; ``scales32``:
    :func:`orb_level_scales32`."""
    return _native().pyramid(gray, [float(s) for s in scales32])


def _orb_level_split(n_detect: int, scale_factor: float, n_levels: int) -> list[int]:
    """OpenCV's ORB: keypoints wanted per level (a geometric series, in float as OpenCV computes
    it)."""
    factor = np.float32(1.0 / scale_factor)
    wanted = np.float32(n_detect) * (np.float32(1) - factor)
    wanted /= np.float32(1) - np.float32(float(factor) ** n_levels)
    per_level = []
    for _ in range(n_levels - 1):
        per_level.append(int(np.rint(wanted)))
        wanted = np.float32(wanted * factor)
    per_level.append(max(n_detect - sum(per_level), 0))
    return per_level


def _native():
    """The compiled extraction (orb_native.cpp), built by scripts/setup."""
    try:
        from . import _orb_native
    except ImportError as exc:
        raise VoError(
            "coop_slam's compiled ORB extraction (coop_slam/vo/_orb_native) is not built or does "
            f"not load ({exc}): run scripts/setup, which builds it with catkin_make"
        ) from exc
    return _orb_native


class OrbExtractor:
    """Grid-bucketed ORB extraction (see module docstring), compiled (orb_native.cpp): each
    pyramid level detected and described as by its own one-level OpenCV ORB, the levels of all the
    images of a frame shared by ``vo.features.threads`` threads (largest first, each to whichever
    is free; one builds an image's pyramid while another detects its level 0): the same keypoints
    and descriptors as one OpenCV ORB over the whole pyramid (without the first FAST pass).
    """

    def __init__(self, config: VoConfig, camera: CameraModel, threads: int | None = None):
        self.config = config
        self.camera = camera
        feats = config.features
        self._scales32 = orb_level_scales32(feats.scale_factor, feats.n_levels)
        self._native = _native().OrbFrameExtractor(
            wanted=_orb_level_split(feats.n_detect, feats.scale_factor, feats.n_levels),
            scales32=[float(s) for s in self._scales32],
            cell_px=[float(c) for c in feats.grid_cell_px * level_scales(config)],
            scale_factor=feats.scale_factor,
            edge_threshold_px=feats.edge_threshold_px,
            patch_px=_PATCH_PX,
            fast_threshold=feats.fast_threshold,
            # at most the low threshold: one pass
            fast_threshold_first=max(feats.fast_threshold_first, 0),
            n_features=feats.n_features,
            threads=feats.threads if threads is None else threads,
        )

    def extract(self, gray: np.ndarray) -> OrbKeypoints:
        return self.extract_with_levels(gray)[0]

    def extract_with_levels(self, gray: np.ndarray) -> tuple[OrbKeypoints, list[np.ndarray]]:
        """The image's keypoints and its pyramid (level images, as :func:`level_images`)."""
        return self.extract_images([gray])[0]

    def extract_images(self, grays: list) -> list[tuple[OrbKeypoints, list[np.ndarray]]]:
        """Each image's keypoints and pyramid; the images' levels extracted together (a stereo
        pair's two images on two threads finish together)."""
        try:
            extracted = self._native.extract(list(grays))
        except ValueError as exc:
            raise VoError(f"ORB extraction: {exc}") from exc
        return [(self._keypoints(*out[:4]), out[4]) for out in extracted]

    def _keypoints(self, pt_px, angle_deg, octaves, descriptors) -> OrbKeypoints:
        return OrbKeypoints(
            uv_px=orb_level0_uv(pt_px, octaves, self.config.features.scale_factor),
            size_px=np.float32(_PATCH_PX) * self._scales32[octaves],
            angle_deg=angle_deg,
            octaves=octaves,
            descriptors=descriptors,
        )


def round_robin(u, v, response, octave, cell_px, n_keep) -> np.ndarray:
    """Sorted indices of the first n_keep keypoints in the order: rank within their (level, cell)
    by response (0 = the cell's best), then response, then index. Cells are ``cell_px[level]``
    squares of level-0 pixels. (The extraction's bucketing, compiled.)"""
    return _native().round_robin(u, v, response, octave, [float(c) for c in cell_px], n_keep)
