"""Reader for folders written by the synthetic world generator (``coop_slam.synthetic.generate``).

A synthetic world is ``world.yaml`` (scenario, robots, ``T_base_cam``, overlap events) plus one TUM
RGB-D folder per robot; ground truth of every robot is in the same world frame.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import yaml

from ..errors import GeometryError
from ..geometry import check_se3
from .base import DatasetError, Sequence
from .tum import read_tum

WORLD_FILE = "world.yaml"
COMPLETE_MARKER = ".complete"


@dataclass
class SyntheticWorld:
    """A generated multi-robot dataset; ``sequences`` are keyed by robot id."""

    folder: str
    meta: dict
    sequences: dict[int, Sequence]
    T_base_cam: np.ndarray  # the robots' camera mount (robot 1's where they differ)
    overlap: dict = field(
        default_factory=dict
    )  # rendezvous, revisit, marker_sightings, first_overlap
    mounts: dict = field(default_factory=dict)  # robot id -> its own T_base_cam, where given

    @property
    def robot_ids(self) -> list[int]:
        return sorted(self.sequences)

    def mount(self, robot_id: int) -> np.ndarray:
        """Robot ``robot_id``'s camera optical frame in its base_link."""
        return self.mounts.get(robot_id, self.T_base_cam)

    @property
    def scenario(self) -> str:
        return str(self.meta.get("scenario", ""))

    def first_overlap_s(self, a: int, b: int) -> float | None:
        """Stamp [s] of the first moment robots a and b could be merged (None: never)."""
        times = [
            e["stamp_s"]
            for e in self.overlap.get("first_overlap", [])
            if sorted(e["robots"]) == sorted([a, b])
        ]
        return min(times) if times else None


def read_synthetic(folder: str) -> SyntheticWorld:
    """Read a generated world folder; DatasetError names what is missing or malformed."""
    if not os.path.isdir(folder):
        raise DatasetError(f"synthetic world folder not found: {folder}")
    world_file = os.path.join(folder, WORLD_FILE)
    if not os.path.isfile(world_file):
        raise DatasetError(f"{folder} is not a synthetic world: {WORLD_FILE} is missing")
    if not os.path.isfile(os.path.join(folder, COMPLETE_MARKER)):
        raise DatasetError(
            f"synthetic world {folder} is incomplete (no {COMPLETE_MARKER}): its generation was "
            "interrupted; delete the folder and generate it again"
        )
    try:
        with open(world_file, encoding="utf-8") as fh:
            meta = yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        raise DatasetError(f"{world_file} is not valid YAML: {exc}") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{world_file}: expected a mapping at the top level")
    robots = meta.get("robots")
    if not isinstance(robots, list) or not robots:
        raise DatasetError(f"{world_file}: 'robots' must be a non-empty list")
    try:
        T_base_cam = check_se3(np.array(meta.get("T_base_cam"), dtype=float), "T_base_cam")
    except (GeometryError, ValueError, TypeError) as exc:
        raise DatasetError(f"{world_file}: invalid T_base_cam: {exc}") from None
    sequences: dict[int, Sequence] = {}
    mounts: dict[int, np.ndarray] = {}
    for k, robot in enumerate(robots):
        if (
            not isinstance(robot, dict)
            or not isinstance(robot.get("id"), int)
            or "name" not in robot
        ):
            raise DatasetError(f"{world_file}: robots[{k}] needs an integer 'id' and a 'name'")
        if robot["id"] in sequences:
            raise DatasetError(f"{world_file}: robot id {robot['id']} appears twice")
        sub = os.path.join(folder, str(robot.get("folder", robot["name"])))
        if not os.path.isdir(sub):
            raise DatasetError(
                f"synthetic world {folder}: folder of {robot['name']} missing ({sub})"
            )
        sequences[robot["id"]] = read_tum(sub, name=str(robot["name"]))
        if "T_base_cam" in robot:
            try:
                mounts[robot["id"]] = check_se3(np.array(robot["T_base_cam"], dtype=float), "")
            except (GeometryError, ValueError, TypeError) as exc:
                raise DatasetError(
                    f"{world_file}: robots[{k}] has an invalid T_base_cam: {exc}"
                ) from None
    overlap = meta.get("overlap") or {}
    if not isinstance(overlap, dict):
        raise DatasetError(f"{world_file}: 'overlap' must be a mapping")
    return SyntheticWorld(
        folder=os.path.abspath(folder),
        meta=meta,
        sequences=sequences,
        T_base_cam=T_base_cam,
        overlap=overlap,
        mounts=mounts,
    )
