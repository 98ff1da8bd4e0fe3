"""Incremental pose-graph sharing back to the robots: which optimized keyframe poses a robot's
correction carries.

After each optimization the server could send a robot every keyframe pose it holds; over a radio
that is most of the downlink, and almost all of it unchanged. :class:`PoseFeedback` remembers what
it last sent for each keyframe (at first: the client's own pose, as the client sent it) and selects
only the keyframes whose optimized pose moved beyond a small threshold since, plus the robot's
newest keyframe (the client anchors its ``map -> odom`` transform on it). The client lays them
over its odometry (:mod:`coop_slam.vo.shared_poses`) and keeps sending its odometry's poses, so the
comparison is always against what was sent, never against what the client made of it.

Poses are in the robot's map frame, in the server's units for that map (metres, or a monocular
map's units times its scale).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import require


@dataclass
class PoseFeedbackConfig:
    """Which optimized keyframe poses a correction carries back to a robot."""

    min_trans_m: float = 0.001  # send a keyframe's pose when it moved this far since last sent [m]
    min_rot_deg: float = 0.05  # ... or turned this much [deg]

    def validate(self) -> None:
        require(self.min_trans_m >= 0, "server: pose_feedback.min_trans_m must be >= 0")
        require(self.min_rot_deg >= 0, "server: pose_feedback.min_rot_deg must be >= 0")


class PoseFeedback:
    """Per map (a robot's map segment id on the server): the poses last sent for its keyframes."""

    def __init__(self, config: PoseFeedbackConfig | None = None):
        self.config = config or PoseFeedbackConfig()
        self.config.validate()
        self._sent: dict[int, dict[int, np.ndarray]] = {}  # map id -> keyframe id -> T_map_cam

    def select(
        self,
        map_id: int,
        optimized: dict[int, np.ndarray],
        client: dict[int, np.ndarray],
    ) -> dict[int, np.ndarray]:
        """The keyframes to send now, id -> optimized T_map_cam: those that moved beyond the
        thresholds since last sent (at first: against ``client``, the client's own poses), and
        the newest. Marks them sent."""
        cfg = self.config
        sent = self._sent.setdefault(map_id, {})
        for k in set(sent) - set(optimized):  # culled keyframes
            del sent[k]
        ids = sorted(optimized)
        if not ids:
            return {}
        # Vectorized: this runs for every robot after every optimization of the team map.
        new = np.stack([optimized[k] for k in ids])
        before = np.stack([sent.get(k, client.get(k, _UNKNOWN)) for k in ids])
        trans_m = np.linalg.norm(new[:, :3, 3] - before[:, :3, 3], axis=1)
        R_rel = np.einsum("nji,njk->nik", before[:, :3, :3], new[:, :3, :3])
        cos = np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        rot_deg = np.degrees(np.arccos(cos))
        moved = ~(trans_m < cfg.min_trans_m) | ~(rot_deg < cfg.min_rot_deg)  # NaN: never sent
        moved[-1] = True  # the newest always goes
        out = {k: optimized[k] for k, m in zip(ids, moved) if m}
        sent.update({k: np.array(T) for k, T in out.items()})
        return out


_UNKNOWN = np.full((4, 4), np.nan)  # a keyframe neither sent nor known as the client has it
