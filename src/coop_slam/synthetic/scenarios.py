"""Multi-robot scenarios: timestamped ``T_world_base`` trajectories through the synthetic world.

Robots drive like small ground robots: planar, 0.35-0.45 m/s with limited acceleration, corners
rounded to arcs so the yaw rate stays under ~35 deg/s, and smooth in-place turns. Each scenario has
one clear purpose for evaluating map merging:

- ``rendezvous``: two robots meet, see each other's marker and then look at the same scene together.
- ``revisit``: robot 2 drives through places robot 1 saw earlier, never at the same time.
- ``disjoint``: two robots in two different buildings: nothing to merge, ever.
- ``aliasing``: two buildings with identical posters at the same spots; one robot in each.
- ``team`` (the demo default, 2-4 robots): a revisit first, then rendezvous.
- ``multi`` (2-8 robots): a lap or more of the corridor ring each, on two lanes; revisits, own
  loops and a rendezvous.
- ``kitchen`` (2-3 cameras, 30 Hz): not robots but people carrying a Kinect-like RGB-D camera by
  hand round a small cluttered kitchen, in 6-DoF, with the sensor's imperfections (motion blur,
  depth holes and quantisation, registration error): as hard as real hand-held data. Their walk
  is :mod:`.hand_held`'s.

Building coordinates (building 0 at the world origin): outer walls x in [0, 12], y in [0, 8];
corridor centre lines y = 1 (south), y = 7 (north), x = 1 (west), x = 11 (east); room A door at
(4, 2), room B door at (8, 6), door between the rooms at (6, 4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import CoopSlamError
from ..geometry import exp_so3
from .bodies import DEFAULT_MARKER_SIZE_M
from .hand_held import kitchen_walk
from .render import NoiseConfig, kinect_noise
from .world import BUILDING_SPACING_M, DEFAULT_T_BASE_CAM, HAND_HELD_T_BASE_CAM

START_STAMP_S = 1.0  # ROS time 0 means "unset", so the first frame is at 1 s
MAX_SPEED_MPS = 0.45
MAX_YAW_RATE_DPS = 35.0
ACCEL_MPS2 = 0.4
YAW_ACCEL_DPS2 = 60.0
CORNER_RADIUS_M = 0.8
LANE_OFFSET_M = 0.45


class ScenarioError(CoopSlamError):
    """Unknown scenario or unsupported parameters (robot count, duration, rate)."""


@dataclass
class Trajectory:
    """Ground-truth ``T_world_base`` (N, 4, 4) of one robot at shared timestamps.

    ``motion`` is the continuous motion the poses were sampled from (``motion.sample(times since
    START_STAMP_S)`` -> (N, 4, 4)), for poses between frames (motion blur, sensor delays).
    """

    robot_id: int
    stamps_s: np.ndarray
    poses_se3: np.ndarray
    motion: object | None = None

    @property
    def name(self) -> str:
        return f"robot_{self.robot_id}"

    def poses_at(self, stamps_s) -> np.ndarray:
        """(N, 4, 4) ``T_world_base`` at any stamps (not only the frames')."""
        if self.motion is None:
            raise ScenarioError(f"{self.name}: no continuous motion to sample between frames")
        return self.motion.sample(np.atleast_1d(np.asarray(stamps_s, float)) - START_STAMP_S)


@dataclass
class Scenario:
    name: str
    seed: int
    layout: str  # world layout for coop_slam.synthetic.world.build_world
    rate_hz: float
    duration_s: float
    trajectories: list[Trajectory]
    description: str
    T_base_cam: np.ndarray = field(default_factory=lambda: DEFAULT_T_BASE_CAM.copy())
    marker_size_m: float = DEFAULT_MARKER_SIZE_M
    meta: dict = field(default_factory=dict)
    # Cameras carried by hand (6-DoF, base_link = the camera carrier): no robot bodies, no markers,
    # and the camera does not stay level (no planar-motion prior).
    hand_held: bool = False
    noise: NoiseConfig = field(default_factory=NoiseConfig)  # the sensor's noise profile
    # Robots whose camera is mounted otherwise than T_base_cam: robot id -> their T_base_cam
    mounts: dict = field(default_factory=dict)

    @property
    def robot_ids(self) -> list[int]:
        return [t.robot_id for t in self.trajectories]

    def mount(self, robot_id: int) -> np.ndarray:
        """Robot ``robot_id``'s camera optical frame in its base_link."""
        return self.mounts.get(robot_id, self.T_base_cam)


# --- route building ------------------------------------------------------------------------------
def _unwrap_to(yaw_from: float, yaw_to: float) -> float:
    """``yaw_to`` shifted by multiples of 2 pi to be within pi of ``yaw_from``."""
    return yaw_from + (yaw_to - yaw_from + math.pi) % (2 * math.pi) - math.pi


class Route:
    """Builds one robot's motion as a list of densely sampled (t, x, y, yaw) pieces."""

    def __init__(self, x: float, y: float, yaw_deg: float, speed_mps: float, origin_xy=(0.0, 0.0)):
        self.origin = np.asarray(origin_xy, float)
        self.t = [0.0]
        self.x = [x + self.origin[0]]
        self.y = [y + self.origin[1]]
        self.yaw = [math.radians(yaw_deg)]
        self.speed = min(speed_mps, MAX_SPEED_MPS)

    @property
    def time_s(self) -> float:
        return self.t[-1]

    def _append(self, t, x, y, yaw):
        t0 = self.t[-1]
        self.t.extend((t0 + np.asarray(t)).tolist())
        self.x.extend(np.asarray(x).tolist())
        self.y.extend(np.asarray(y).tolist())
        self.yaw.extend(np.asarray(yaw).tolist())

    def wait(self, seconds: float) -> Route:
        if seconds > 0:
            self._append([seconds], [self.x[-1]], [self.y[-1]], [self.yaw[-1]])
        return self

    def wait_until(self, time_s: float) -> Route:
        return self.wait(time_s - self.time_s)

    def turn_to(self, yaw_deg: float) -> Route:
        """Turn in place along the shorter way, with a trapezoidal yaw-rate profile."""
        y0 = self.yaw[-1]
        y1 = _unwrap_to(y0, math.radians(yaw_deg))
        angle = abs(y1 - y0)
        if angle < 1e-6:
            return self
        w_max = math.radians(MAX_YAW_RATE_DPS) * 0.85
        acc = math.radians(YAW_ACCEL_DPS2)
        profile = _trapezoid(angle, w_max, acc)
        self._append(
            profile[0],
            np.full(len(profile[0]), self.x[-1]),
            np.full(len(profile[0]), self.y[-1]),
            y0 + np.sign(y1 - y0) * profile[1],
        )
        return self

    def drive(self, *waypoints_xy) -> Route:
        """Drive from the current position through ``waypoints_xy`` (building coordinates), with
        rounded corners, starting and ending at rest. Turns in place first if the first leg does
        not start along the current heading."""
        pts = [np.array([self.x[-1], self.y[-1]])] + [
            np.asarray(p, float) + self.origin for p in waypoints_xy
        ]
        first = pts[1] - pts[0]
        heading = math.atan2(first[1], first[0])
        if abs(_unwrap_to(self.yaw[-1], heading) - self.yaw[-1]) > math.radians(2):
            self.turn_to(math.degrees(heading))
        xy, yaw, curvature = _fillet_path(pts, CORNER_RADIUS_M)
        ds = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        v_lim = np.minimum(
            self.speed, math.radians(MAX_YAW_RATE_DPS) / np.maximum(np.abs(curvature), 1e-9)
        )
        v = _velocity_profile(ds, v_lim, ACCEL_MPS2)
        dt = 2.0 * ds / np.maximum(v[:-1] + v[1:], 1e-9)
        t = np.concatenate([[0.0], np.cumsum(dt)])
        yaw = _unwrap_to(self.yaw[-1], yaw[0]) + np.unwrap(yaw - yaw[0])
        self._append(t[1:], xy[1:, 0], xy[1:, 1], yaw[1:])
        return self

    def sample(self, stamps_rel_s: np.ndarray) -> np.ndarray:
        """(N, 4, 4) T_world_base at times relative to the route start (holds the last pose)."""
        t = np.asarray(self.t)
        # Remove duplicate times (zero-length pieces) so interpolation is well defined.
        keep = np.concatenate([[True], np.diff(t) > 1e-9])
        t = t[keep]
        x = np.interp(stamps_rel_s, t, np.asarray(self.x)[keep])
        y = np.interp(stamps_rel_s, t, np.asarray(self.y)[keep])
        yaw = np.interp(stamps_rel_s, t, np.unwrap(np.asarray(self.yaw)[keep]))
        poses = np.repeat(np.eye(4)[None], len(stamps_rel_s), axis=0)
        c, s = np.cos(yaw), np.sin(yaw)
        poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
        poses[:, 0, 3], poses[:, 1, 3] = x, y
        return poses


def _trapezoid(distance: float, v_max: float, acc: float, dt: float = 0.01):
    """(times, positions) of a rest-to-rest move over ``distance`` with bounded speed and accel."""
    t_acc = v_max / acc
    if acc * t_acc**2 > distance:  # triangular profile: never reaches v_max
        t_acc = math.sqrt(distance / acc)
        v_max = acc * t_acc
    t_cruise = (distance - acc * t_acc**2) / v_max
    total = 2 * t_acc + t_cruise
    t = np.linspace(0.0, total, max(2, math.ceil(total / dt) + 1))
    s = np.where(
        t < t_acc,
        0.5 * acc * t**2,
        np.where(
            t < t_acc + t_cruise,
            0.5 * acc * t_acc**2 + v_max * (t - t_acc),
            distance - 0.5 * acc * np.maximum(total - t, 0.0) ** 2,
        ),
    )
    return t[1:], s[1:]


def _velocity_profile(ds: np.ndarray, v_lim: np.ndarray, acc: float) -> np.ndarray:
    """Fastest speeds along the path with a speed limit and |accel| <= acc, at rest at both ends."""
    v = v_lim.copy()
    v[0] = v[-1] = 0.0
    for i in range(1, len(v)):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * acc * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * acc * ds[i]))
    return v


def _fillet_path(points: list[np.ndarray], radius: float, step: float = 0.01):
    """Dense (xy (M, 2), yaw (M,), curvature (M,)) of a polyline with arcs at the corners."""
    pts = [p for i, p in enumerate(points) if i == 0 or np.linalg.norm(p - points[i - 1]) > 1e-6]
    if len(pts) < 2:
        raise ScenarioError("a drive needs at least one waypoint away from the current position")
    pieces = []  # ('line', a, b) or ('arc', centre, r, a0, a1)
    cur = pts[0]
    for i in range(1, len(pts) - 1):
        d0 = pts[i] - pts[i - 1]
        d1 = pts[i + 1] - pts[i]
        l0, l1 = np.linalg.norm(d0), np.linalg.norm(d1)
        d0, d1 = d0 / l0, d1 / l1
        turn = math.atan2(d0[0] * d1[1] - d0[1] * d1[0], float(d0 @ d1))
        if abs(turn) < 1e-6:
            continue
        tangent = min(radius * math.tan(abs(turn) / 2), 0.45 * l0, 0.45 * l1)
        r = tangent / math.tan(abs(turn) / 2)
        a = pts[i] - d0 * tangent
        b = pts[i] + d1 * tangent
        left = np.array([-d0[1], d0[0]]) * math.copysign(1.0, turn)
        centre = a + left * r
        a0 = math.atan2(a[1] - centre[1], a[0] - centre[0])
        pieces.append(("line", cur, a))
        pieces.append(("arc", centre, r, a0, turn))
        cur = b
    pieces.append(("line", cur, pts[-1]))
    xy, yaw, curv = [], [], []
    for piece in pieces:
        if piece[0] == "line":
            _, a, b = piece
            length = float(np.linalg.norm(b - a))
            if length < 1e-9:
                continue
            n = max(1, math.ceil(length / step))
            s = np.linspace(0.0, 1.0, n + 1)[:-1]
            xy.append(a + s[:, None] * (b - a))
            yaw.append(np.full(n, math.atan2(b[1] - a[1], b[0] - a[0])))
            curv.append(np.zeros(n))
        else:
            _, centre, r, a0, turn = piece
            n = max(2, math.ceil(abs(turn) * r / step))
            ang = a0 + np.linspace(0.0, turn, n + 1)[:-1]
            xy.append(centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1))
            yaw.append(ang + math.copysign(math.pi / 2, turn))
            curv.append(np.full(n, 1.0 / r))
    last = pieces[-1]
    end_yaw = math.atan2(last[2][1] - last[1][1], last[2][0] - last[1][0])
    xy.append(pts[-1][None])
    yaw.append(np.array([end_yaw]))
    curv.append(np.zeros(1))
    return np.concatenate(xy), np.concatenate(yaw), np.concatenate(curv)


# --- scenarios ---------------------------------------------------------------------------------
def _stamps(duration_s: float, rate_hz: float) -> np.ndarray:
    n = round(duration_s * rate_hz)
    return START_STAMP_S + np.arange(n) / rate_hz


def _scenario(name, seed, layout, rate_hz, duration_s, routes, description, **meta) -> Scenario:
    stamps = _stamps(duration_s, rate_hz)
    trajs = [
        # Robot ids start at 1 (robot 1 is the master; 0 means "no robot" on the wire).
        Trajectory(k + 1, stamps.copy(), r.sample(stamps - START_STAMP_S), r)
        for k, r in enumerate(routes)
    ]
    return Scenario(
        name, int(seed), layout, float(rate_hz), float(duration_s), trajs, description, meta=meta
    )


def _speeds(rng: np.random.Generator, n: int, base: float = 0.4) -> list[float]:
    return [float(base + rng.uniform(-0.03, 0.03)) for _ in range(n)]


def _jitter(rng: np.random.Generator, amount: float = 0.08) -> float:
    return float(rng.uniform(-amount, amount))


def _meeting_pair(rng: np.random.Generator) -> tuple[Route, Route, float]:
    """Two robots approach head-on in the south corridor (seeing each other's marker), stop; the
    second turns around and both drive east together looking at the same scene. Returns the
    routes and when they set off together [s from the start]."""
    v = _speeds(rng, 1)[0]  # same speed for both: robot 1 follows robot 2 at a constant gap
    a = Route(2.0 + _jitter(rng), 1.0, 0.0, v).drive((5.2, 1.0))
    b = Route(10.0 + _jitter(rng), 1.0, 180.0, v).drive((7.0, 1.0)).wait(1.0).turn_to(0.0)
    start = max(a.time_s, b.time_s) + 0.5
    a.wait_until(start).drive((9.4, 1.0))
    b.wait_until(start).drive((11.0, 1.0), (11.0, 3.2))
    return a, b, start


def rendezvous(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """Robots 0 and 1 approach head-on in the south corridor (seeing each other's marker), stop,
    robot 2 turns around and both drive east together looking at the same scene."""
    a, b, start = _meeting_pair(np.random.default_rng(seed))
    return _scenario(
        "rendezvous",
        seed,
        "ring",
        rate_hz,
        duration_s,
        [a, b],
        rendezvous.__doc__,
        meet_time_s=START_STAMP_S + start,
    )


def revisit(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """Robot 1 drives the south and east corridors; robot 2 starts in the north corridor, goes
    round through the west corridor and then drives the south corridor after robot 1 has left it."""
    rng = np.random.default_rng(seed)
    va, vb = _speeds(rng, 2)
    a = Route(2.5 + _jitter(rng), 1.0, 0.0, va).drive((11.0, 1.0), (11.0, 7.0), (8.5, 7.0))
    b = Route(4.5 + _jitter(rng), 7.0, 180.0, vb).drive((1.0, 7.0), (1.0, 1.0), (9.0, 1.0))
    return _scenario("revisit", seed, "ring", rate_hz, duration_s, [a, b], revisit.__doc__)


def disjoint(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """Robot 1 in building 0, robot 2 in building 1 (different textures): no shared view, ever."""
    rng = np.random.default_rng(seed)
    va, vb = _speeds(rng, 2)
    a = Route(2.5 + _jitter(rng), 1.0, 0.0, va).drive((11.0, 1.0), (11.0, 6.0))
    b = Route(9.5 + _jitter(rng), 7.0, 180.0, vb, origin_xy=(BUILDING_SPACING_M, 0.0))
    b.drive((1.0, 7.0), (1.0, 3.0))
    return _scenario(
        "disjoint", seed, "two_buildings", rate_hz, duration_s, [a, b], disjoint.__doc__
    )


def aliasing(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """One robot per building; both drive towards the same (identical) posters at the corridor
    ends, at different places: a place recognizer sees strong but false matches."""
    rng = np.random.default_rng(seed)
    va, vb = _speeds(rng, 2)
    a = Route(3.0 + _jitter(rng), 1.0, 0.0, va).drive((11.0, 1.0), (11.0, 5.0))
    b = Route(3.5 + _jitter(rng), 1.0, 0.0, vb, origin_xy=(BUILDING_SPACING_M, 0.0))
    b.drive((11.0, 1.0), (11.0, 5.0))
    return _scenario(
        "aliasing", seed, "two_buildings_aliased", rate_hz, duration_s, [a, b], aliasing.__doc__
    )


def team(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """Demo default. Robot 1 drives the south corridor and waits in the east corridor; robot 2
    starts in the north corridor, revisits the south corridor later and joins robot 1 from behind
    (rendezvous). Robot 3 crosses the rooms and revisits robot 2's start; robot 4 starts at the
    north end of the east corridor, where robot 1 arrives and waits later (a revisit), and drives
    the north corridor west ahead of robot 3, which follows its view (and robot 2's first one),
    into the west corridor. (Its first route stopped after 2.6 m, sharing 20-28 descriptor
    matches with any other robot's keyframes: too little to merge.)"""
    rng = np.random.default_rng(seed)
    speeds = _speeds(rng, robots, base=0.42)
    routes = [
        Route(2.5 + _jitter(rng), 1.0, 0.0, speeds[0]).drive((11.0, 1.0), (11.0, 4.6)),
        Route(4.5 + _jitter(rng), 7.0, 180.0, speeds[1]).drive(
            (1.0, 7.0), (1.0, 1.0), (11.0, 1.0), (11.0, 3.0)
        ),
    ]
    if robots >= 3:
        routes.append(
            Route(4.0, 3.0 + _jitter(rng), 90.0, speeds[2]).drive(
                (4.0, 4.0), (7.5, 4.0), (8.0, 4.6), (8.0, 7.0), (2.5, 7.0)
            )
        )
    if robots >= 4:
        routes.append(
            Route(11.0, 5.6 + _jitter(rng), 90.0, speeds[3]).drive(
                (11.0, 7.0), (1.0, 7.0), (1.0, 4.0)
            )
        )
    return _scenario("team", seed, "ring", rate_hz, duration_s, routes, team.__doc__)


MOUNTS_HEIGHT_M = (0.3, 0.8, 0.5)  # robots 1, 2, 3
MOUNTS_PITCH_DOWN_DEG = (0.0, 20.0, 10.0)


def camera_mount(height_m: float, pitch_down_deg: float, forward_m: float = 0.1) -> np.ndarray:
    """A forward-looking camera's ``T_base_cam`` at ``height_m`` above the floor, pitched down."""
    T = DEFAULT_T_BASE_CAM.copy()
    # About base y: +x (forward) turns towards -z (the floor).
    T[:3, :3] = exp_so3(np.array([0.0, math.radians(pitch_down_deg), 0.0])) @ T[:3, :3]
    T[:3, 3] = [forward_m, 0.0, height_m]
    return T


def mounts(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """Three robots, each with its own camera mount: at 0.3, 0.8 and 0.5 m, pitched down by 0,
    20 and 10 degrees. Robots 1 and 2 meet as in ``rendezvous`` (the server must place each
    one's marker sightings with its own mount); robot 3 comes round from the north corridor
    through the west one into the south corridor, where robot 1 started (a revisit)."""
    rng = np.random.default_rng(seed)
    a, b, start = _meeting_pair(rng)
    c = Route(4.5 + _jitter(rng), 7.0, 180.0, _speeds(rng, 1, base=0.45)[0])
    c.drive((1.0, 7.0), (1.0, 1.0), (6.0, 1.0))
    sc = _scenario(
        "mounts",
        seed,
        "ring",
        rate_hz,
        duration_s,
        [a, b, c],
        mounts.__doc__,
        meet_time_s=START_STAMP_S + start,
    )
    sc.mounts = {
        t.robot_id: camera_mount(h, p)
        for t, h, p in zip(sc.trajectories, MOUNTS_HEIGHT_M, MOUNTS_PITCH_DOWN_DEG)
    }
    sc.T_base_cam = sc.mounts[1]
    return sc


def kidnap(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """Robot 1 drives the south and east corridors; robot 2 follows it along the south corridor
    (they merge), then its camera goes dark (covered, no image, no depth) while it drives round the
    corner into the east corridor, which only robot 1 has mapped: robot 2's own map cannot place
    it there, the team map can (server-assisted relocalization)."""
    rng = np.random.default_rng(seed)
    va, vb = _speeds(rng, 2)
    a = Route(2.5 + _jitter(rng), 1.0, 0.0, va).drive((11.0, 1.0), (11.0, 7.0))
    b = Route(1.2 + _jitter(rng), 1.0, 0.0, vb).wait(3.0).drive((9.6, 1.0))
    dark_from = b.time_s
    b.drive((11.0, 1.0), (11.0, 2.4))
    dark_until = b.time_s
    b.drive((11.0, 5.0))
    return _scenario(
        "kidnap",
        seed,
        "ring",
        rate_hz,
        duration_s,
        [a, b],
        kidnap.__doc__,
        # robot id -> [from, until] stamps [s] of frames with a dark camera
        dark={"2": [START_STAMP_S + dark_from, START_STAMP_S + dark_until]},
    )


def _ring_loop(lane: float, clockwise: bool) -> list[np.ndarray]:
    """Corners of the corridor loop offset by ``lane`` metres towards the outer walls."""
    lo, hi_x, hi_y = 1.0 - lane, 11.0 + lane, 7.0 + lane
    ccw = [np.array(p) for p in ((lo, lo), (hi_x, lo), (hi_x, hi_y), (lo, hi_y))]
    return ccw[::-1] if clockwise else ccw


def _perimeter(corners: list[np.ndarray]) -> float:
    return float(
        sum(np.linalg.norm(corners[(i + 1) % len(corners)] - c) for i, c in enumerate(corners))
    )


def _loop_route(
    start_s: float, corners: list[np.ndarray], speed: float, wait_s: float, duration_s: float
) -> Route:
    """A route starting ``start_s`` metres along the closed polyline ``corners``, going round."""
    closed = corners + [corners[0]]
    seg = [np.linalg.norm(closed[i + 1] - closed[i]) for i in range(len(corners))]
    perimeter = float(sum(seg))
    s = start_s % perimeter
    i = 0
    while s > seg[i]:
        s -= seg[i]
        i += 1
    d = (closed[i + 1] - closed[i]) / seg[i]
    p = closed[i] + d * s
    route = Route(p[0], p[1], math.degrees(math.atan2(d[1], d[0])), speed)
    route.wait(wait_s)
    laps = math.ceil(duration_s * speed / perimeter) + 1
    waypoints = [closed[(i + 1 + k) % len(corners)] for k in range(laps * len(corners))]
    # Keep the robot moving through every corner: one long drive, not one drive per corner.
    return route.drive(*[tuple(w) for w in waypoints])


def multi(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """N robots drive the corridor ring counter-clockwise, even ids on the outer lane, odd ids on
    the inner lane, evenly spaced; robot 2 instead starts 7 m ahead of robot 1 on the outer lane and
    waits, so robot 1 catches up with it (rendezvous). Each robot drives a lap or more: it closes
    its own loop and drives through what the robots ahead of it mapped (revisits). (Robots driving
    the ring in opposite directions never see one scene from the same side: nothing to merge.)"""
    rng = np.random.default_rng(seed)
    v = 0.4 + float(rng.uniform(-0.02, 0.02))  # one speed: robots keep their gaps
    outer_ids = [k for k in range(robots) if k % 2 == 0 or k == 1]
    inner_ids = [k for k in range(robots) if k % 2 == 1 and k != 1]
    outer = _ring_loop(LANE_OFFSET_M, clockwise=False)
    inner = _ring_loop(-LANE_OFFSET_M, clockwise=False)
    perimeter_outer, perimeter_inner = _perimeter(outer), _perimeter(inner)
    routes: dict[int, Route] = {}
    routes[0] = _loop_route(0.5, outer, v, 0.0, duration_s)
    if robots > 1:
        routes[1] = _loop_route(7.5, outer, v, 8.0, duration_s)
    others = [k for k in outer_ids if k > 1]
    for j, k in enumerate(others):
        # Spread over the part of the loop after robot 2, leaving room for robot 1 to catch up.
        s = 7.5 + 5.0 + (perimeter_outer - 7.5 - 9.0) * j / max(1, len(others))
        routes[k] = _loop_route(s, outer, v, 0.0, duration_s)
    for j, k in enumerate(inner_ids):
        s = perimeter_inner * (j + 0.5) / len(inner_ids)
        routes[k] = _loop_route(s, inner, v, 0.0, duration_s)
    return _scenario(
        "multi",
        seed,
        "ring",
        rate_hz,
        duration_s,
        [routes[k] for k in range(robots)],
        multi.__doc__,
    )


KITCHEN_RATE_HZ = 30.0  # a Kinect's frame rate


def kitchen(seed: int, robots: int, duration_s: float, rate_hz: float) -> Scenario:
    """People with a hand-held Kinect walk round the table of a 4 m x 3.5 m kitchen, one after
    the other on the same loop (evenly spaced, never closer than ~1 m), each looking at the
    counters, shelves and furniture around them and across the room. Each camera sees what the
    one ahead saw a lap fraction earlier (revisits) and closes its own loop after a lap (~17 s);
    30 Hz, 6-DoF with hand shake, Kinect-like sensor noise (``render.kinect_noise``)."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(0, 2 * np.pi)
    motions = [kitchen_walk(rng, start + 2 * np.pi * k / robots) for k in range(robots)]
    stamps = _stamps(duration_s, rate_hz)
    trajs = [
        Trajectory(k + 1, stamps.copy(), m.sample(stamps - START_STAMP_S), m)
        for k, m in enumerate(motions)
    ]
    return Scenario(
        "kitchen",
        int(seed),
        "kitchen",
        float(rate_hz),
        float(duration_s),
        trajs,
        kitchen.__doc__,
        T_base_cam=HAND_HELD_T_BASE_CAM.copy(),
        hand_held=True,
        noise=kinect_noise(),
    )


@dataclass(frozen=True)
class ScenarioSpec:
    fn: object
    default_robots: int
    min_robots: int
    max_robots: int
    default_duration_s: float
    default_rate_hz: float = 15.0
    hand_held: bool = False  # people carry the cameras (6-DoF, no planar-motion prior, no bodies)


SCENARIOS = {
    "rendezvous": ScenarioSpec(rendezvous, 2, 2, 2, 34.0),
    "revisit": ScenarioSpec(revisit, 2, 2, 2, 46.0),
    "disjoint": ScenarioSpec(disjoint, 2, 2, 2, 30.0),
    "aliasing": ScenarioSpec(aliasing, 2, 2, 2, 32.0),
    "team": ScenarioSpec(team, 2, 2, 4, 56.0),
    "kidnap": ScenarioSpec(kidnap, 2, 2, 2, 40.0),
    "multi": ScenarioSpec(multi, 4, 2, 8, 90.0),
    "kitchen": ScenarioSpec(kitchen, 2, 2, 3, 28.0, KITCHEN_RATE_HZ, hand_held=True),
    "mounts": ScenarioSpec(mounts, 3, 3, 3, 40.0),
}
DEFAULT_SCENARIO = "team"


def make_scenario(
    name: str = DEFAULT_SCENARIO,
    seed: int = 0,
    robots: int | None = None,
    duration_s: float | None = None,
    rate_hz: float | None = None,
) -> Scenario:
    """Build scenario ``name``; ``robots``/``duration_s``/``rate_hz`` None take the scenario's
    defaults (15 Hz for the ground robots, 30 Hz for hand-held cameras)."""
    spec = SCENARIOS.get(name)
    if spec is None:
        raise ScenarioError(f"unknown scenario '{name}'; use one of {', '.join(SCENARIOS)}")
    robots = spec.default_robots if robots is None else int(robots)
    if not spec.min_robots <= robots <= spec.max_robots:
        raise ScenarioError(
            f"scenario '{name}' supports {spec.min_robots}-{spec.max_robots} robots, got {robots}"
        )
    duration_s = spec.default_duration_s if duration_s is None else float(duration_s)
    rate_hz = spec.default_rate_hz if rate_hz is None else float(rate_hz)
    if not (duration_s > 0 and rate_hz > 0) or duration_s * rate_hz < 1:
        raise ScenarioError(f"duration {duration_s} s at {rate_hz} Hz gives no frame")
    return spec.fn(int(seed), robots, duration_s, float(rate_hz))
