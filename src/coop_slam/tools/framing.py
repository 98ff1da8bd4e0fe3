"""Frame the recorded RViz view on the map a run will build (``scripts/demo``'s per-run RViz
config): numpy only, no ROS.

Frames: RViz shows ``world``, the frame of the world group, whose root is the team's smallest robot
id; that robot's ``robot_k/map`` is its body at its first frame (z up, REP-103: the client moves
its odometry's first-camera frame by ``T_base_cam``). So a ground-truth camera pose ``G`` (dataset
frame) sits at ``T_base_cam @ inv(G_root_0) @ G`` in ``world``, for every robot of the world group.
Groups not merged with it are drawn ``unmerged_offset_m`` along x (server) and are deliberately
left out: the view frames the world group, i.e. the team map once the robots are merged.

What is framed: the ground-truth camera positions plus what the cameras see -- points of a few
depth images per robot back-projected with their ground-truth poses (RGB-D), or, without depth
images (stereo, bags), the centre and corners of each camera's view ``LOOK_AHEAD_M`` ahead. The
view is RViz's orbit view (the config's pitch; its yaw or a quarter turn to it, whichever shows
the map larger) centred on those points, at the distance that makes them span ``FILL`` of the
16:9 picture.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# RViz's orbit view: "Field of View" is the vertical FOV (Ogre setFOVy), default pi/4.
DEFAULT_FOV_RAD = math.pi / 4
DEFAULT_PITCH_RAD = 1.15  # rviz/coop_slam.rviz: top-down-ish
DEFAULT_YAW_RAD = 1.5 * math.pi  # rviz/coop_slam.rviz: looking along +y, x to the right
LOOK_AHEAD_M = 2.0  # without depth images: the cameras see surfaces ~1-3 m ahead [m]
DEPTH_RANGE_M = (0.3, 6.0)  # depths the clients use (client.yaml vo.min_depth_m / max_depth_m)
DEPTH_FRAMES = 24  # depth images read per robot, evenly spread over its frames
DEPTH_STEP_PX = 16  # every 16th pixel of a row and column
TRIM_PERCENT = 1.0  # seen points outside the [1 %, 99 %] range of an axis are ignored (strays)
HALF_TAN = (0.6, 0.45)  # a camera's half field of view (tangents x, y) when unknown (~62 x 48 deg)
FILL = 0.9  # the points span this share of the picture on its limiting side
MAX_POSES = 2000  # per robot; longer trajectories are subsampled evenly


class FramingError(ValueError):
    """Nothing to frame (no ground truth of the world robot, no points, bad input)."""


@dataclass(frozen=True)
class OrbitView:
    """An RViz ``rviz/Orbit`` view: its config keys Focal Point, Distance, Pitch, Yaw, Field of
    View."""

    focal: tuple[float, float, float]
    distance: float
    pitch: float
    yaw: float
    fov: float = DEFAULT_FOV_RAD

    def eye(self) -> np.ndarray:
        """The camera position, as RViz's OrbitViewController::updateCamera places it."""
        return np.asarray(self.focal, float) - self.distance * _camera_axes(self.pitch, self.yaw)[0]

    def config(self) -> dict:
        """The keys of the config's ``Visualization Manager / Views / Current`` to replace."""
        x, y, z = (round(float(v), 4) for v in self.focal)
        return {
            "Distance": round(float(self.distance), 4),
            "Focal Point": {"X": x, "Y": y, "Z": z},
            "Pitch": round(float(self.pitch), 6),
            "Yaw": round(float(self.yaw), 6),
            "Field of View": round(float(self.fov), 6),
        }


def _camera_axes(pitch: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(forward, right, up) unit vectors of an orbit camera (RViz: fixed yaw axis +z)."""
    cp, sp = math.cos(pitch), math.sin(pitch)
    forward = -np.array([math.cos(yaw) * cp, math.sin(yaw) * cp, sp])
    right = np.array([-math.sin(yaw), math.cos(yaw), 0.0])  # forward x z, normalised
    return forward, right, np.cross(right, forward)


def project(view: OrbitView, points: np.ndarray, aspect: float = 16.0 / 9.0) -> np.ndarray:
    """Points (N, 3) -> picture coordinates (N, 2), x right and y up, in [-1, 1] when inside."""
    forward, right, up = _camera_axes(view.pitch, view.yaw)
    d = np.asarray(points, float).reshape(-1, 3) - view.eye()
    depth = d @ forward
    tv = math.tan(view.fov / 2.0)
    return np.column_stack([(d @ right) / (depth * tv * aspect), (d @ up) / (depth * tv)])


def _distance(d: np.ndarray, axes, th: float, tv: float, min_distance: float) -> float:
    """Smallest orbit distance at which points ``d`` (relative to the focal point) project
    within [-th, th] x [-tv, tv] (tangents of the half FOVs)."""
    forward, right, up = axes
    along = d @ forward
    need = np.maximum(np.abs(d @ right) / th, np.abs(d @ up) / tv) - along
    return max(float(need.max()), min_distance, 0.1 - float(along.min()))


def fit_orbit_view(
    points,
    pitch: float = DEFAULT_PITCH_RAD,
    yaws: tuple[float, ...] | None = None,
    fov: float = DEFAULT_FOV_RAD,
    aspect: float = 16.0 / 9.0,
    fill: float = FILL,
    min_distance: float = 1.0,
    iterations: int = 6,
) -> OrbitView:
    """The orbit view that shows ``points`` (N, 3) centred, spanning ``fill`` of the picture
    (vertical FOV ``fov``, width / height ``aspect``) on its limiting side.

    ``yaws``: candidates, the first preferred (default: the package's yaw, then a quarter turn
    to it); a later one wins only when it needs a distance over 5 % shorter. The focal point
    starts at the centre of the points' box and moves horizontally until the points' picture is
    centred (a few fixed iterations: deterministic)."""
    points = np.asarray(points, float).reshape(-1, 3)
    if len(points) == 0 or not np.all(np.isfinite(points)):
        raise FramingError("no points to frame, or non-finite ones")
    if not (0.0 < fov < math.pi and aspect > 0 and 0.0 < fill <= 1.0):
        raise FramingError("fov, aspect and fill must be positive (fov < pi, fill <= 1)")
    if not 0.0 < pitch < math.pi / 2:
        raise FramingError("pitch must be in (0, pi/2): the view looks down on the map")
    yaws = (DEFAULT_YAW_RAD, DEFAULT_YAW_RAD - math.pi / 2) if yaws is None else yaws
    tv = fill * math.tan(fov / 2.0)
    th = tv * aspect
    best = None
    for yaw in yaws:
        axes = _camera_axes(pitch, yaw)
        forward, right, up = axes
        ground = np.array([forward[0], forward[1], 0.0]) / math.cos(pitch)  # unit, horizontal
        focal = (points.min(axis=0) + points.max(axis=0)) / 2.0
        for _ in range(iterations):
            d = points - focal
            distance = _distance(d, axes, th, tv, min_distance)
            depth = distance + d @ forward
            x, y = (d @ right) / depth, (d @ up) / depth
            # the picture moves opposite to the focal point: by s on screen for s * distance
            # along `right`, and for s * distance / sin(pitch) along the ground
            mid_x, mid_y = (x.max() + x.min()) / 2.0, (y.max() + y.min()) / 2.0
            focal = focal + distance * (mid_x * right + mid_y / math.sin(pitch) * ground)
        distance = _distance(points - focal, axes, th, tv, min_distance)
        if best is None or distance < 0.95 * best[0]:
            best = (distance, yaw, focal)
    distance, yaw, focal = best
    return OrbitView(tuple(float(v) for v in focal), distance, pitch, yaw % (2.0 * math.pi), fov)


def T_world_gt(gts: dict, T_base_cam: np.ndarray | None = None, world_robot: int | None = None):
    """The dataset's ground-truth frame in RViz's ``world``: ``T_base_cam @ inv(G_0)``, ``G_0``
    the first ground-truth pose of ``world_robot`` (default: the smallest id). ``gts``: robot id
    -> (stamps, (N, 4, 4) T_gt_cam), as ``RunInput.gts``; ``T_base_cam``: the clients' camera
    optical frame in base_link (identity when None)."""
    if not gts:
        raise FramingError("no robots")
    world_robot = min(gts) if world_robot is None else world_robot
    poses = np.asarray(gts.get(world_robot, ((), ()))[1], float).reshape(-1, 4, 4)
    poses = poses[np.all(np.isfinite(poses), axis=(1, 2))]
    if len(poses) == 0:
        raise FramingError(f"no ground truth of robot {world_robot} (the origin of world)")
    T_base_cam = np.eye(4) if T_base_cam is None else np.asarray(T_base_cam, float)
    return T_base_cam @ np.linalg.inv(poses[0])


def dense_truth_of(inputs, T_base_cam: np.ndarray | None = None):
    """The synthetic world a run (:class:`coop_slam.evaluation.run_data.RunInput`) played, in
    ``world``, to score its dense map against; None when the run played no synthetic world."""
    from ..evaluation.map_results import dense_truth

    if not inputs.world:
        return None
    return dense_truth(inputs.world, T_world_gt(inputs.gts, T_base_cam))


def world_camera_poses(gts: dict, T_world_gt: np.ndarray) -> np.ndarray:
    """All robots' finite ground-truth camera poses (M, 4, 4) in ``world``; at most
    ``MAX_POSES`` per robot (evenly subsampled)."""
    out = [np.zeros((0, 4, 4))]
    for robot in sorted(gts):
        poses = np.asarray(gts[robot][1], float).reshape(-1, 4, 4)
        poses = poses[np.all(np.isfinite(poses), axis=(1, 2))]
        if len(poses) > MAX_POSES:
            poses = poses[np.linspace(0, len(poses) - 1, MAX_POSES).round().astype(int)]
        out.append(T_world_gt @ poses)
    return np.concatenate(out)


def backproject(
    depth_m: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    step: int = DEPTH_STEP_PX,
    depth_range: tuple[float, float] = DEPTH_RANGE_M,
) -> np.ndarray:
    """Every ``step``-th pixel of a depth image [m] with a depth in ``depth_range``, as points
    (N, 3) in the frame of ``T_world_cam`` (camera optical frame, intrinsics ``K``)."""
    h, w = depth_m.shape[:2]
    v, u = np.mgrid[step // 2 : h : step, step // 2 : w : step]
    z = np.asarray(depth_m, float)[v, u]
    ok = np.isfinite(z) & (z >= depth_range[0]) & (z <= depth_range[1])
    u, v, z = u[ok], v[ok], z[ok]
    cam = np.column_stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
    return cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def look_ahead_points(
    poses: np.ndarray, look_ahead_m: float = LOOK_AHEAD_M, half_tan=HALF_TAN
) -> np.ndarray:
    """The centre and corners of the cameras' view ``look_ahead_m`` ahead: (5 M, 3) points of
    camera poses (M, 4, 4) (optical frames: z forward), ``half_tan`` the tangents of the half
    fields of view (x, y)."""
    poses = np.asarray(poses, float).reshape(-1, 4, 4)
    tx, ty = half_tan
    rays = look_ahead_m * np.array(
        [[0, 0, 1], [-tx, -ty, 1], [tx, -ty, 1], [-tx, ty, 1], [tx, ty, 1]]
    )
    return (poses[:, None, :3, :3] @ rays[None, :, :, None])[..., 0].reshape(-1, 3) + np.repeat(
        poses[:, :3, 3], len(rays), axis=0
    )


def half_tangents(camera) -> tuple[float, float]:
    """Tangents of a camera model's half fields of view (x, y)."""
    return camera.width / 2.0 / camera.fx, camera.height / 2.0 / camera.fy


def trimmed(points: np.ndarray, percent: float = TRIM_PERCENT) -> np.ndarray:
    """The points inside the [percent, 100 - percent] percentiles of every axis."""
    points = np.asarray(points, float).reshape(-1, 3)
    if len(points) == 0 or percent <= 0:
        return points
    lo, hi = np.percentile(points, [percent, 100.0 - percent], axis=0)
    return points[np.all((points >= lo) & (points <= hi), axis=1)]


def seen_depth_points(streams, T_world_gt: np.ndarray, frames: int = DEPTH_FRAMES):
    """(points (N, 3) in ``world``, depth images used): a few depth images per robot stream
    (``playback.RobotStream``; those with ground truth and a depth image), back-projected with
    their ground-truth poses. Reads the images; unreadable ones are skipped."""
    chunks, used = [np.zeros((0, 3))], 0
    for stream in streams:
        seq = stream.sequence
        poses = seq.frame_poses()
        ok = [i for i, f in enumerate(seq.frames) if f.depth_path and np.all(np.isfinite(poses[i]))]
        if not ok:
            continue
        for i in sorted({ok[j] for j in np.linspace(0, len(ok) - 1, frames).round().astype(int)}):
            try:
                depth = seq.load_depth_m(seq.frames[i])
            except Exception:  # noqa: BLE001 - a missing or broken image: frame with the others
                continue
            chunks.append(backproject(depth, seq.camera.K, T_world_gt @ poses[i]))
            used += 1
    return np.concatenate(chunks), used


def framing_points(
    poses: np.ndarray, seen: np.ndarray | None = None, half_tan=HALF_TAN
) -> np.ndarray:
    """What the view must show: the camera positions and the seen points (strays trimmed); the
    look-ahead points (:func:`look_ahead_points`) instead when there are no seen points."""
    poses = np.asarray(poses, float).reshape(-1, 4, 4)
    if seen is None or len(seen) == 0:
        seen = look_ahead_points(poses, half_tan=half_tan)
    else:
        seen = trimmed(seen)
    return np.vstack([poses[:, :3, 3], seen])


def _current_view(cfg: dict, template) -> dict:
    try:
        current = cfg["Visualization Manager"]["Views"]["Current"]
    except (KeyError, TypeError):
        raise FramingError(f"{template}: no 'Visualization Manager / Views / Current'") from None
    if not isinstance(current, dict) or current.get("Class") != "rviz/Orbit":
        raise FramingError(f"{template}: the current view is not an rviz/Orbit view")
    return current


def template_view(template: str | Path) -> OrbitView:
    """The current orbit view of an RViz config (defaults for keys it leaves out)."""
    import yaml

    with open(template, encoding="utf-8") as fh:
        current = _current_view(yaml.safe_load(fh), template)
    focal = current.get("Focal Point") or {}
    return OrbitView(
        tuple(float(focal.get(k, 0.0)) for k in ("X", "Y", "Z")),
        float(current.get("Distance", 10.0)),
        float(current.get("Pitch", DEFAULT_PITCH_RAD)),
        float(current.get("Yaw", DEFAULT_YAW_RAD)),
        float(current.get("Field of View", DEFAULT_FOV_RAD)),
    )


# Sizes in metres of displays drawn at the robots (axes), scaled with the view
_SCALED_KEYS = {
    "rviz/TF": ("Marker Scale",),
    "rviz/Pose": (
        "Axes Length",
        "Axes Radius",
        "Head Length",
        "Head Radius",
        "Shaft Length",
        "Shaft Radius",
    ),
}


def _scale_displays(displays, scale: float) -> None:
    for display in displays or ():
        if not isinstance(display, dict):
            continue
        for key in _SCALED_KEYS.get(display.get("Class"), ()):
            if isinstance(display.get(key), (int, float)):
                display[key] = round(float(display[key]) * scale, 4)
        _scale_displays(display.get("Displays"), scale)  # groups


def _disable_topics(displays, prefix: str) -> None:
    for display in displays or ():
        if isinstance(display, dict):
            if str(display.get("Topic", "")).startswith(prefix):
                display["Enabled"] = False  # a disabled display does not subscribe
            _disable_topics(display.get("Displays"), prefix)


def framed_config(
    template: str | Path,
    out: str | Path,
    view: OrbitView,
    note: str = "",
    axes_scale: float = 1.0,
    station_only: bool = False,
) -> Path:
    """Write a copy of the RViz config ``template`` whose current view (an ``rviz/Orbit`` one)
    takes ``view``'s focal point, distance, pitch, yaw and field of view, and whose TF and pose
    axes are ``axes_scale`` times as large (so a closer view does not blow them up); everything
    else kept. ``station_only``: the robots' own topics (``/robot_k/...``: local maps, poses,
    paths) are not shown, so a viewer on the station does not pull them across the radio."""
    import yaml

    with open(template, encoding="utf-8") as fh:
        cfg = yaml.safe_load(fh)
    _current_view(cfg, template).update(view.config())
    if station_only:
        _disable_topics(cfg["Visualization Manager"].get("Displays"), "/robot_")
    if axes_scale != 1.0:
        _scale_displays(cfg["Visualization Manager"].get("Displays"), axes_scale)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    header = f"# {Path(template).name}, its view framed on this run's map. {note}".rstrip()
    with open(out, "w", encoding="utf-8") as fh:
        fh.write(header + "\n")
        yaml.safe_dump(cfg, fh, sort_keys=False)
    return out
