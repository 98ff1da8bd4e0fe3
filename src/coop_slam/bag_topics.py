"""Which robots' cameras a rosbag holds, whatever driver recorded them: the player's own topics
(``/robot_k/camera/...``, as ``scripts/export_bag`` writes them) and the topics of the common ROS
camera drivers, each under any namespace.

A robot's namespace ``/robot_k`` gives it id k; other namespaces (``""`` for a bag of one camera,
``/alpha``, ``/beta``...) are numbered from 1 in name order, skipping ids taken. Each camera is
mapped onto the player's topics (:func:`coop_slam.playback.camera_topics`), which is what the
clients subscribe to: a bag from a real robot replays through the same system as the demo's.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from .errors import CoopSlamError
from .playback import camera_topics


class BagTopicsError(CoopSlamError):
    """A bag whose camera topics cannot be told apart or assigned to robots."""


@dataclass(frozen=True)
class Driver:
    """A camera driver's topic names, relative to its namespace."""

    name: str
    sensor: str  # rgbd, stereo or mono
    image: str  # colour (left of a pair)
    second: str | None  # depth or right image (None: monocular)
    infos: dict = field(default_factory=dict)  # the player's info role -> topic
    # Recognised only with its camera infos (a bare ``image_raw`` is too common a name to
    # take alone); the others' infos are mapped when present (a client waits for them).
    needs_info: bool = False


DRIVERS = (
    # The TUM RGB-D benchmark's bags (openni / freenect of their time): depth in metres.
    Driver(
        "tum",
        "rgbd",
        "camera/rgb/image_color",
        "camera/depth/image",
        {"color": "camera/rgb/camera_info"},
    ),
    Driver(
        "openni2",
        "rgbd",
        "camera/rgb/image_raw",
        "camera/depth_registered/image_raw",
        {"color": "camera/rgb/camera_info"},
    ),
    Driver(
        "realsense2",
        "rgbd",
        "camera/color/image_raw",
        "camera/aligned_depth_to_color/image_raw",
        {"color": "camera/color/camera_info"},
    ),
    Driver(  # the player's own (and scripts/export_bag's)
        "coop_slam",
        "rgbd",
        "camera/color/image_raw",
        "camera/depth/image_raw",
        {"color": "camera/color/camera_info"},
    ),
    Driver(
        "stereo",
        "stereo",
        "camera/left/image_rect",
        "camera/right/image_rect",
        {"left": "camera/left/camera_info", "right": "camera/right/camera_info"},
    ),
    Driver(  # stereo_image_proc under the camera's own namespace
        "stereo_image_proc",
        "stereo",
        "left/image_rect",
        "right/image_rect",
        {"left": "left/camera_info", "right": "right/camera_info"},
    ),
    Driver("mono", "mono", "camera/color/image_raw", None, {"color": "camera/color/camera_info"}),
    Driver("mono_rgb", "mono", "camera/rgb/image_raw", None, {"color": "camera/rgb/camera_info"}),
    Driver("mono_raw", "mono", "image_raw", None, {"color": "camera_info"}, needs_info=True),
)
ROBOT_NAMESPACE = re.compile(r"^/robot_(\d+)$")


@dataclass
class BagCamera:
    robot_id: int
    namespace: str  # "" for topics at the root
    driver: Driver
    remap: dict  # bag topic -> the player's topic

    @property
    def sensor(self) -> str:
        return self.driver.sensor

    @property
    def image_topic(self) -> str:
        return _join(self.namespace, self.driver.image)


def _join(namespace: str, name: str) -> str:
    return f"{namespace}/{name}"


def _inside(ns: str, camera_ns: str, driver: Driver) -> bool:
    """Whether namespace ``ns`` lies in the topic tree of a camera found at ``camera_ns`` (its
    driver's first name components: ``camera``, or ``left`` and ``right``)."""
    heads = {name.split("/")[0] for name in (driver.image, driver.second or "") if name}
    return any(ns == _join(camera_ns, h) or ns.startswith(_join(camera_ns, h) + "/") for h in heads)


def bag_cameras(topics) -> list[BagCamera]:
    """The cameras among a bag's topic names (an iterable of ``/...`` names), by robot id; raises
    :class:`BagTopicsError` when one bag topic would feed two robots' cameras."""
    topics = set(topics)
    found: dict[str, Driver] = {}  # namespace -> its driver (first that fits, most complete)
    claimed: set[str] = set()
    for driver in DRIVERS:
        suffix = "/" + driver.image
        for topic in sorted(topics):
            if not topic.endswith(suffix):
                continue
            ns = topic[: -len(suffix)]
            needed = [driver.second] if driver.second else []
            needed += list(driver.infos.values()) if driver.needs_info else []
            if ns in found or topic in claimed or not all(_join(ns, n) in topics for n in needed):
                continue
            if driver.second is None and any(
                _join(ns, d.second) in topics
                for d in DRIVERS
                if d.image == driver.image and d.second
            ):
                continue  # a depth image beside it: not a monocular camera
            if driver.second is None and any(_inside(ns, n, found[n]) for n in found):
                continue  # a stream of a camera already found (its depth, IR or raw images)
            found[ns] = driver
            claimed.update(_join(ns, n) for n in [driver.image, *needed])
    taken = {int(m.group(1)) for ns in found if (m := ROBOT_NAMESPACE.match(ns))}
    free = (k for k in range(1, 10**6) if k not in taken)
    cameras = []
    for ns in sorted(found, key=lambda n: (ROBOT_NAMESPACE.match(n) is None, n)):
        m = ROBOT_NAMESPACE.match(ns)
        rid = int(m.group(1)) if m else next(free)
        d = found[ns]
        own = camera_topics(rid, d.sensor)
        remap = {_join(ns, d.image): own["image"]}
        if d.second:
            remap[_join(ns, d.second)] = own["second"]
        for role, name in d.infos.items():
            if _join(ns, name) in topics:
                remap[_join(ns, name)] = own["infos"][role]
        cameras.append(BagCamera(rid, ns, d, remap))
    mapped = [t for c in cameras for t in c.remap]
    twice = sorted({t for t in mapped if mapped.count(t) > 1})
    if twice:
        raise BagTopicsError(f"bag topics {twice} would feed two robots' cameras")
    return sorted(cameras, key=lambda c: c.robot_id)


def describe_drivers() -> str:
    """The topic sets recognised, for an error message."""
    return "; ".join(
        f"{d.name}: <ns>/{d.image}" + (f" + <ns>/{d.second}" if d.second else "") for d in DRIVERS
    )
