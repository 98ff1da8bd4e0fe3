"""What the server's worker is asked to do: one dataclass per kind of job (see
:mod:`coop_slam.team.worker`), made by the node's callbacks, ``scripts/replay`` and the bench."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from ..robot_description import MarkerSeen
from ..wire.codec import Decoded


@dataclass
class KeyframeJob:
    item: Decoded
    stamp_s: float  # the message's header stamp
    session: int = 0  # delivery (see coop_slam.wire.delivery); 0 = unsequenced
    sequence: int = 0


@dataclass
class RendezvousJob:
    robot_a: int
    robot_b: int
    stamp_s: float | None  # None: now (the robots' latest keyframes)
    marker: MarkerSeen | None = None  # marker sighting: robot b's marker as robot a saw it
    sighting: bool = False  # a marker sighting (rate-limited) rather than an operator request
    reply: Future | None = None  # (merge or None, message)

    @property
    def pair(self) -> tuple[int, int]:
        return self.robot_a, self.robot_b


@dataclass
class GlobalBaJob:
    robot_id: int | None
    reply: Future  # (GlobalBaResult or None, message)


@dataclass
class RelocalizeJob:
    robot_id: int
    map_segment: int
    bow: Any  # BowVector of the lost robot's view
    reply: Future  # (LocalMap or None, message, pending)


@dataclass
class MapFileJob:
    path: str
    load: bool  # load (else save)
    reply: Future  # (success, message, path)
