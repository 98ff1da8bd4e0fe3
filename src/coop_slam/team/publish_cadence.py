"""When the server publishes the stitched team map (cloud, paths, merge edges).

The stitched cloud fuses every robot's points; its cost grows with the team map, to a second or
more per build with eight robots (``scripts/bench --only server_scale``). It is built beside the
server's worker (:mod:`.map_builder`), but on the same cores. The map is shown after a merge and
every ``period_s`` of data time, but the builder never takes more than ``max_busy_share`` of the
wall time: after a cloud that took ``c`` seconds to build, the next waits at least
``c * (1 / max_busy_share - 1)`` seconds. When the server is idle (its queue drained) the final
state is always shown.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..config import require


@dataclass
class PublishCadenceConfig:
    period_s: float = 2.0  # data time between two team maps [s]
    max_busy_share: float = 0.2  # of the wall time spent building team clouds, at most

    def validate(self) -> None:
        require(self.period_s > 0, "server: cloud_period_s must be > 0")
        require(0 < self.max_busy_share <= 1, "server: cloud_max_busy_share must be in (0, 1]")


class PublishCadence:
    def __init__(self, config: PublishCadenceConfig | None = None):
        self.config = config or PublishCadenceConfig()
        self.config.validate()
        self._last_stamp_s = -1e18
        self._next_wall_s = -1e18  # the budget allows the next map from this wall time on

    def due(self, stamp_s: float, merged: bool, wall_s: float) -> bool:
        """Whether to publish the team map after a message of data time ``stamp_s`` (at wall time
        ``wall_s``; ``merged``: the message made a merge)."""
        if wall_s < self._next_wall_s:
            return False
        return merged or stamp_s - self._last_stamp_s >= self.config.period_s

    def published(self, stamp_s: float, started_wall_s: float, ended_wall_s: float) -> None:
        """A team map was published (its data time, wall times its building started and ended)."""
        cost = max(ended_wall_s - started_wall_s, 0.0)
        self._last_stamp_s = stamp_s
        self._next_wall_s = ended_wall_s + cost * (1.0 / self.config.max_busy_share - 1.0)
