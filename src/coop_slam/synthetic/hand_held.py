"""Hand-held cameras' motion in closed form (smooth, at any time): people walking round the
kitchen table with a camera in hand (:func:`kitchen_walk`), the ``kitchen`` scenario's routes
(:mod:`.scenarios`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Sines:
    """A smooth random signal: sum_i amp_i sin(2 pi freq_i t + phase_i)."""

    amp: np.ndarray
    freq_hz: np.ndarray
    phase: np.ndarray

    @classmethod
    def random(cls, rng: np.random.Generator, amp, freq_hz, count: int = 1) -> Sines:
        """``count`` components, amplitudes and frequencies uniform in the (lo, hi) ranges."""
        return cls(
            rng.uniform(*amp, count), rng.uniform(*freq_hz, count), rng.uniform(0, 2 * np.pi, count)
        )

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * np.asarray(t_s, float)[:, None] * self.freq_hz + self.phase
        return (self.amp * np.sin(arg)).sum(axis=1)

    @property
    def peak(self) -> float:
        return float(np.abs(self.amp).sum())


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((len(a), 3, 3))
    R[:, 0, 0] = 1.0
    R[:, 1, 1], R[:, 1, 2], R[:, 2, 1], R[:, 2, 2] = c, -s, s, c
    return R


def _rot_y(a):
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((len(a), 3, 3))
    R[:, 1, 1] = 1.0
    R[:, 0, 0], R[:, 0, 2], R[:, 2, 0], R[:, 2, 2] = c, s, -s, c
    return R


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((len(a), 3, 3))
    R[:, 2, 2] = 1.0
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, -s, s, c
    return R


def _small_rotations(rotvec: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of (N, 3) rotation vectors (Rodrigues)."""
    angle = np.linalg.norm(rotvec, axis=1)
    axis = rotvec / np.maximum(angle, 1e-12)[:, None]
    K = np.zeros((len(rotvec), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - K.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3)[None] + s * K + (1 - c) * K @ K


@dataclass
class HandHeldMotion:
    """A person walking round a loop with a camera in hand, in closed form (smooth, any time).

    The carrier walks an ellipse (``loop_centre_xy``, ``loop_axes_m``) at a mean angular rate
    with a varying pace, wandering a little off it, the camera's height rising and falling and
    bobbing with the steps. It looks ahead and a little across the room (``yaw_bias_rad`` from the
    ellipse's outward normal) at the counters, shelves and furniture 1-3 m away, sweeping slowly
    to either side by ``yaw_offset``; it looks down by ``pitch`` (negative), rolls a little, and
    hand shake adds small fast rotations and shifts.
    ``sample`` gives ``T_world_base`` with base_link = the camera carrier (x forward, y left,
    z up; ``HAND_HELD_T_BASE_CAM`` turns it into the optical frame).
    """

    loop_centre_xy: np.ndarray
    loop_axes_m: np.ndarray
    phase0_rad: float
    rate_rad_s: float
    pace: Sines  # phase added to rate * t [rad]: the walking speed varies
    wander_x: Sines  # [m]
    wander_y: Sines
    height_m: float
    height: Sines  # [m], slow changes and step bob
    yaw_bias_rad: float  # from the loop's outward normal (+: towards the walking direction)
    yaw_offset: Sines  # [rad] about that
    pitch_rad: float
    pitch: Sines  # [rad] about pitch_rad
    roll: Sines  # [rad]
    shake_rot: list[Sines]  # [rad] about the base's x, y, z
    shake_xyz: list[Sines]  # [m] in the world

    def _phase(self, t_s: np.ndarray) -> np.ndarray:
        return self.phase0_rad + self.rate_rad_s * t_s + self.pace(t_s)

    def positions(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 3) camera positions in the world (without hand shake)."""
        phase = self._phase(t_s)
        a, b = self.loop_axes_m
        x = self.loop_centre_xy[0] + a * np.cos(phase) + self.wander_x(t_s)
        y = self.loop_centre_xy[1] + b * np.sin(phase) + self.wander_y(t_s)
        return np.column_stack([x, y, self.height_m + self.height(t_s)])

    def sample(self, t_s) -> np.ndarray:
        t_s = np.atleast_1d(np.asarray(t_s, float))
        phase = self._phase(t_s)
        a, b = self.loop_axes_m
        normal = np.arctan2(np.sin(phase) / b, np.cos(phase) / a)
        yaw = normal + self.yaw_bias_rad + self.yaw_offset(t_s)
        pitch = self.pitch_rad + self.pitch(t_s)
        # base_link: yaw about z, then nose down (looking down = positive rotation about y).
        R = _rot_z(yaw) @ _rot_y(-pitch) @ _rot_x(self.roll(t_s))
        R = R @ _small_rotations(np.column_stack([s(t_s) for s in self.shake_rot]))
        poses = np.repeat(np.eye(4)[None], len(t_s), axis=0)
        poses[:, :3, :3] = R
        poses[:, :3, 3] = self.positions(t_s) + np.column_stack([s(t_s) for s in self.shake_xyz])
        return poses


# The kitchen (world.KITCHEN_SIZE_M, corner at the origin): people walk round the table on this
# ellipse, 0.4-0.5 m from the table and the furniture by the walls.
KITCHEN_LOOP_CENTRE_XY = (2.3, 1.85)
KITCHEN_LOOP_AXES_M = (0.95, 0.72)
KITCHEN_LAP_S = 19.0  # ~0.28 m/s on average
# Walking counter-clockwise, the walking direction is at +90 deg from the outward normal: people
# look ahead and a little across the room, so most of what they see is 1.4-2.4 m away (median
# depth per frame; RedKitchen: 1.45-2.4 m). Looking outwards (0 deg) they would mostly see the
# counter beside them at ~1 m.
YAW_BIAS_DEG = 110.0


def kitchen_walk(rng: np.random.Generator, phase0_rad: float) -> HandHeldMotion:
    """One person's walk round the kitchen table, starting at loop angle ``phase0_rad``."""
    deg = math.radians
    rate = 2 * np.pi / KITCHEN_LAP_S
    # Pace: +-30 % about the mean speed from one slow component (its derivative is amp 2 pi f):
    # people slow down to look, then walk on. Everybody has the same mean rate, so people that
    # start apart stay apart.
    pace_f = rng.uniform(1 / 11, 1 / 8)
    pace = Sines(
        np.array([0.3 * rate / (2 * np.pi * pace_f)]),
        np.array([pace_f]),
        rng.uniform(0, 2 * np.pi, 1),
    )
    return HandHeldMotion(
        loop_centre_xy=np.array(KITCHEN_LOOP_CENTRE_XY),
        loop_axes_m=np.array(KITCHEN_LOOP_AXES_M),
        phase0_rad=float(phase0_rad),
        rate_rad_s=rate,
        pace=pace,
        wander_x=Sines.random(rng, (0.015, 0.03), (0.05, 0.2), 2),
        wander_y=Sines.random(rng, (0.015, 0.03), (0.05, 0.2), 2),
        height_m=1.45,
        # Slow changes (up to +-0.2 m over 4-14 s) and the step bob (~1 cm at ~1.8 Hz).
        height=Sines(
            np.array([rng.uniform(0.1, 0.13), rng.uniform(0.04, 0.06), rng.uniform(0.006, 0.01)]),
            np.array(
                [rng.uniform(1 / 14, 1 / 9), rng.uniform(1 / 6, 1 / 4), rng.uniform(1.6, 2.0)]
            ),
            rng.uniform(0, 2 * np.pi, 3),
        ),
        # Looking ahead and a little across the room, sweeping slowly (+-40 deg) from the counters
        # beside the walker to across the table, with glances.
        yaw_bias_rad=deg(YAW_BIAS_DEG),
        yaw_offset=Sines(
            np.array([deg(rng.uniform(28, 34)), deg(rng.uniform(6, 9))]),
            np.array([rng.uniform(1 / 16, 1 / 12), rng.uniform(1 / 6, 1 / 4)]),
            rng.uniform(0, 2 * np.pi, 2),
        ),
        # Looking down at the counters and the table: -22 +- 12 deg.
        pitch_rad=deg(-22.0),
        pitch=Sines(
            np.array([deg(rng.uniform(8, 9)), deg(rng.uniform(2.5, 3))]),
            np.array([rng.uniform(1 / 12, 1 / 8), rng.uniform(1 / 5, 1 / 3)]),
            rng.uniform(0, 2 * np.pi, 2),
        ),
        roll=Sines(
            np.array([deg(rng.uniform(2.5, 3.2)), deg(rng.uniform(1.0, 1.4))]),
            np.array([rng.uniform(1 / 8, 1 / 5), rng.uniform(0.4, 0.6)]),
            rng.uniform(0, 2 * np.pi, 2),
        ),
        # Hand shake: up to ~0.5 deg and ~2 mm per axis at 1.5-4 Hz (smooth, so velocity stays
        # continuous; fast enough to blur and to upset a constant-velocity motion model).
        shake_rot=[Sines.random(rng, (deg(0.1), deg(0.17)), (1.5, 4.0), 3) for _ in range(3)],
        shake_xyz=[Sines.random(rng, (0.0004, 0.0008), (1.5, 4.0), 3) for _ in range(3)],
    )
