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
"""

from __future__ import annotations

import threading
from concurrent.futures import Future
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import CameraModel
from .config import VoConfig
from .shared_work import SharedJob, shared_worker

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
    h, w = gray.shape
    levels = [gray]
    for s in scales32[1:]:
        f = np.float32(1) / np.float32(s)
        size = (max(1, int(np.rint(np.float32(w) * f))), max(1, int(np.rint(np.float32(h) * f))))
        levels.append(cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR_EXACT))
    return levels


def _keypoint_table(kps, *names: str) -> np.ndarray:
    """(N, 2 + len(names)): each cv2.KeyPoint's u, v, then the named attributes. One attribute
    per comprehension: reading k.pt builds a tuple per keypoint (3.5x slower)."""
    table = np.empty((len(kps), 2 + len(names)))
    table[:, :2] = cv2.KeyPoint_convert(kps)
    for col, name in enumerate(names, start=2):
        table[:, col] = [getattr(k, name) for k in kps]
    return table


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


class OrbExtractor:
    """Grid-bucketed ORB extraction (see module docstring). Each pyramid level is detected and
    described by its own one-level OpenCV ORB, the levels shared between the caller and a worker
    thread (largest first, each to whichever is free; the worker starts on level 0 while the
    caller builds the rest of the pyramid): the same keypoints and descriptors as one OpenCV ORB
    over the whole pyramid (without the first FAST pass). ``split_levels=False``: all levels in
    the caller's thread.
    """

    def __init__(self, config: VoConfig, camera: CameraModel, split_levels: bool = True):
        self.config = config
        self.camera = camera
        feats = config.features
        per_level = _orb_level_split(feats.n_detect, feats.scale_factor, feats.n_levels)
        self._scales32 = orb_level_scales32(feats.scale_factor, feats.n_levels)
        self._orbs = [self._orb(n, feats.fast_threshold) for n in per_level]
        first = feats.fast_threshold_first
        self._orbs_first = (
            [self._orb(n, first) for n in per_level] if first > feats.fast_threshold else None
        )
        self._wanted = per_level
        self._scales = level_scales(config)
        self._split_levels = split_levels
        self._job: SharedJob | None = None  # the levels being worked on, for helpers
        self._helpers = threading.Condition()

    def _orb(self, n: int, threshold: int):
        feats = self.config.features
        return cv2.ORB_create(
            nfeatures=max(n, 1),
            scaleFactor=feats.scale_factor,
            nlevels=1,
            edgeThreshold=feats.edge_threshold_px,
            patchSize=_PATCH_PX,
            fastThreshold=threshold,
        )

    def extract(self, gray: np.ndarray) -> OrbKeypoints:
        return self.extract_with_levels(gray)[0]

    def extract_with_levels(self, gray: np.ndarray) -> tuple[OrbKeypoints, list[np.ndarray]]:
        """The image's keypoints and its pyramid (level images, as :func:`level_images`)."""
        levels = [gray]
        pyramid = threading.Event()

        def build_pyramid() -> None:
            try:
                levels.extend(level_images(gray, self._scales32)[1:])
            finally:
                pyramid.set()  # also when it failed: a worker waiting for it must not hang

        def detect(lv: int):
            if lv:
                pyramid.wait()
            if lv >= len(levels) or not self._wanted[lv]:
                return ()
            return self._detect_level(levels[lv], lv)

        found = self._on_levels(detect, build_pyramid)
        tables = [self._level_table(found[lv], lv, "response") for lv in range(len(levels))]
        table = np.vstack(tables)
        if len(table) == 0:
            return self._empty(), levels
        keep = self._bucket(table)
        first = np.cumsum([0] + [len(t) for t in tables])
        chosen = {
            lv: [
                found[lv][i] for i in keep[(keep >= first[lv]) & (keep < first[lv + 1])] - first[lv]
            ]
            for lv in range(len(levels))
        }
        described = self._on_levels(lambda lv: self._describe(levels[lv], lv, chosen[lv]))
        kept = [(lv, *described[lv]) for lv in range(len(levels)) if described[lv][0]]
        if not kept:
            return self._empty(), levels
        attrs = np.vstack([self._level_table(kps, lv, "angle") for lv, kps, _ in kept])
        octaves = attrs[:, 3]
        attrs[:, :2] = orb_level0_uv(attrs[:, :2], octaves, self.config.features.scale_factor)
        keypoints = OrbKeypoints(
            uv_px=attrs[:, :2],
            size_px=np.float32(_PATCH_PX) * self._scales32[octaves.astype(int)],
            angle_deg=attrs[:, 2].astype(np.float32),
            octaves=octaves.astype(np.uint8),
            descriptors=np.ascontiguousarray(np.vstack([d for _, _, d in kept]), dtype=np.uint8),
        )
        return keypoints, levels

    def _on_levels(self, work, prepare=None) -> dict:
        """{level: work(level)} for every level, largest first, each taken by the caller or a
        helper -- the worker thread (``split_levels``), a thread in :meth:`help_until` --
        whichever is free first: when the other core is busy (local mapping, the other image of
        a stereo pair) the caller does them all rather than wait. ``prepare()`` runs in the
        caller first, while a helper may already take level 0."""
        job = SharedJob(work, len(self._wanted))
        with self._helpers:
            self._job = job
            self._helpers.notify_all()
        try:
            if self._split_levels:
                shared_worker().submit(job.drain)
            if prepare is not None:
                prepare()
            return job.join()
        finally:
            with self._helpers:
                self._job = None

    def help_until(self, extraction: Future):
        """Work on this extractor's levels from another thread until ``extraction`` (running
        :meth:`extract_with_levels` elsewhere) is done; its result. A stereo pair's left image
        is extracted in the caller while the right is in a thread: the caller, done first,
        takes the right's levels rather than wait."""

        def wake(_) -> None:
            with self._helpers:
                self._helpers.notify_all()

        extraction.add_done_callback(wake)
        while True:
            with self._helpers:
                self._helpers.wait_for(
                    lambda: extraction.done() or (self._job is not None and not self._job.exhausted)
                )
                job = None if extraction.done() else self._job
            if job is None:
                return extraction.result()
            job.drain()

    def _detect_level(self, image: np.ndarray, level: int):
        """The level's keypoints: at the first threshold when it finds as many as the level wants,
        else at the low one (module docstring)."""
        if self._orbs_first is not None:
            kps = self._orbs_first[level].detect(image, None)
            if len(kps) >= self._wanted[level]:
                return kps
        return self._orbs[level].detect(image, None)

    def _describe(self, image: np.ndarray, level: int, chosen: list):
        """The chosen keypoints of one level and their descriptors (((), None): none)."""
        if not chosen:
            return (), None
        kps, desc = self._orbs[level].compute(image, chosen)
        return (kps, desc) if desc is not None and kps else ((), None)

    def _level_table(self, kps, level: int, name: str) -> np.ndarray:
        """(N, 4): u, v (level 0, as OpenCV's ORB reports them), the named attribute, level."""
        table = np.empty((len(kps), 4))
        if len(kps):
            table[:, :3] = _keypoint_table(kps, name)
            table[:, :2] = np.float32(table[:, :2]) * self._scales32[level]
        table[:, 3] = level
        return table

    def _bucket(self, attrs: np.ndarray) -> np.ndarray:
        """Indices of up to n_features keypoints: best per (level, cell) first, then
        second best, ... (:func:`_round_robin`)."""
        feats = self.config.features
        if len(attrs) <= feats.n_features:
            return np.arange(len(attrs))
        octave = np.clip(attrs[:, 3].astype(np.int64), 0, feats.n_levels - 1)
        cell_px = feats.grid_cell_px * self._scales
        return _round_robin(
            attrs[:, 0], attrs[:, 1], attrs[:, 2], octave, cell_px, feats.n_features
        )

    @staticmethod
    def _empty() -> OrbKeypoints:
        return OrbKeypoints(
            uv_px=np.zeros((0, 2)),
            size_px=np.zeros(0, np.float32),
            angle_deg=np.zeros(0, np.float32),
            octaves=np.zeros(0, np.uint8),
            descriptors=np.zeros((0, 32), np.uint8),
        )


def _round_robin(u, v, response, octave, cell_px, n_keep):
    """Sorted indices of the first n_keep keypoints in the order: rank within their (level, cell)
    by response (0 = the cell's best), then response, then index. Cells are ``cell_px[level]``
    squares of level-0 pixels."""
    n = len(u)
    n_keep = min(n_keep, n)
    if n_keep <= 0:
        return np.zeros(0, np.int64)
    octave = np.asarray(octave, np.int64)
    size = cell_px[octave]
    cell = (octave * 4096 + np.floor(v / size).astype(np.int64)) * 4096
    cell += np.floor(u / size).astype(np.int64)
    # Each keypoint's place in the order by response (ties: by index) makes every key below
    # unique, so unstable sorts give the lexicographic order.
    place = np.empty(n, np.int64)
    place[np.argsort(-response, kind="stable")] = np.arange(n)
    by_cell = np.argsort(cell * n + place)
    cell_sorted = cell[by_cell]
    first = np.r_[0, np.flatnonzero(cell_sorted[1:] != cell_sorted[:-1]) + 1]
    rank = np.empty(n, np.int64)
    rank[by_cell] = np.arange(n) - np.repeat(first, np.diff(np.r_[first, n]))
    return np.sort(np.argpartition(rank * n + place, n_keep - 1)[:n_keep])
