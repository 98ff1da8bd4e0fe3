"""What a client tells the team besides its keyframes: the other robots it sees (their markers,
``/robot_sightings``, a rendezvous cue; their bodies are masked for the odometry, a robot being a
moving object, with the size and marker mount each sighted robot describes on
``/robot_k/description``, its own until that came), and, when it is lost and its own map cannot
place the camera, its view, asking the server for the team's local map there
(``/server/relocalize``)."""

from __future__ import annotations

import dataclasses
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np
import rospy

from ..errors import CoopSlamError
from ..geometry import invert, transform_points
from ..markers import MarkerDetector, body_box_cam
from ..robot_description import MarkerSeen
from ..wire.bow_signature import encode_signature
from .convert import MessageError, description_from_msg, pose_to_msg

ASK_EVERY_S = 1.0  # at most one relocalization question a second, one at a time


class TeamCues:
    """``vocabulary()`` gives the server's vocabulary (fetched on first use);
    ``segment_base()`` the map segment the odometry's segment 0 is sent as."""

    def __init__(
        self,
        robot_id: int,
        T_base_cam: np.ndarray,
        markers: MarkerDetector,
        marker_every: int,
        vocabulary: Callable[[], object],
        segment_base: Callable[[], int],
        cam_frame: str = "",
        detect_beside: bool = True,
    ):
        from coop_slam.msg import RobotSighting

        self.robot_id, self.T_base_cam = robot_id, T_base_cam
        self.name = f"robot_{robot_id}"
        self.cam_frame = cam_frame or f"{self.name}/camera_optical"
        self.markers, self.marker_every = markers, marker_every
        self.vocabulary, self.segment_base = vocabulary, segment_base
        self.pub_sighting = rospy.Publisher("/robot_sightings", RobotSighting, queue_size=10)
        self._RobotSighting = RobotSighting
        self._described: dict = {}  # robot id -> its RobotDescription (subscribed when sighted)
        self._description_subs: dict = {}
        self._busy, self._last_s = False, 0.0
        # Marker detection (5-13 ms a VGA image) runs beside tracking, without Python's lock; its
        # sightings go out with the next frame: (detection, stamp, the frame's result, segment).
        # Not ``detect_beside`` (lock-step playback): in the frame, as the results must not
        # depend on the machine's load.
        self._detecting = None
        self._detector = None
        if detect_beside:
            self._detector = ThreadPoolExecutor(max_workers=1, thread_name_prefix="markers")

    # --- markers ----------------------------------------------------------------------------------
    def sightings(self, frames: int, stamp, image, res, vo, K: np.ndarray) -> None:
        """Every ``marker_every`` frames: other robots' markers in the image, looked for in a
        worker thread (a frame that comes while it is busy is not looked at); what it saw is
        said on the first frame after it finished."""
        if self._detecting is not None and self._detecting[0].done():
            self.finish(vo)
        if not self.marker_every or frames % self.marker_every or self._detecting is not None:
            return
        tracked_in = (vo, None if vo is None else vo.map_segment)
        if self._detector is None:
            self._say(self.markers.detect(image, K), stamp, res, vo, tracked_in)
            return
        detection = self._detector.submit(self.markers.detect, image, K)
        self._detecting = (detection, stamp, res, tracked_in)

    def finish(self, vo) -> None:
        """Say what the detection under way saw, once it is done (the camera stopped: nothing
        would say it)."""
        if self._detecting is None:
            return
        (detection, stamp, res, tracked_in), self._detecting = self._detecting, None
        self._say(detection.result(), stamp, res, vo, tracked_in)

    def _say(self, seen, stamp, res, vo, tracked_in) -> None:
        """Publish the sightings of one frame; mask the sighted bodies in the odometry's map when
        it is still the map that frame was tracked in (``tracked_in``: odometry, map segment)."""
        cfg = self.markers.config
        same_map = vo is not None and tracked_in == (vo, vo.map_segment)
        masking = res.ok and cfg.mask_s > 0 and same_map
        for s in seen:
            if s.marker_id == self.robot_id or s.marker_id < 1:
                continue  # our own body, or not a robot id
            if masking:  # a robot is a moving object, not a landmark
                box_cfg, T_cam_body = self._body_of(s, cfg)
                corners_map = transform_points(res.T_map_cam, body_box_cam(box_cfg, T_cam_body))
                vo.ignore_region(corners_map, stamp.to_sec() + cfg.mask_s)
            msg = self._RobotSighting(
                observer_id=self.robot_id,
                observed_id=s.marker_id,
                marker_id=s.marker_id,
                T_cam_marker=pose_to_msg(s.T_cam_marker),
                marker_size_m=cfg.marker_size_m,
                reprojection_error_px=s.reprojection_error_px,
            )
            msg.header.stamp, msg.header.frame_id = stamp, self.cam_frame
            self.pub_sighting.publish(msg)

    def _body_of(self, s, cfg):
        """(marker config with the sighted robot's body size, its body in the camera frame):
        from its own description once it came, else as this robot's configuration assumes."""
        rid = s.marker_id
        if rid not in self._description_subs:
            from coop_slam.msg import RobotDescription

            self._description_subs[rid] = rospy.Subscriber(
                f"/robot_{rid}/description",
                RobotDescription,
                lambda msg, r=rid: self._on_description(r, msg),
                queue_size=1,
            )
        d = self._described.get(rid)
        if d is None:
            return cfg, s.T_cam_body
        box = dataclasses.replace(cfg, body_size_m=list(d.body_size_m))
        return box, d.T_cam_body(MarkerSeen(s.T_cam_marker, cfg.marker_size_m))

    def _on_description(self, robot_id: int, msg) -> None:
        try:
            self._described[robot_id] = description_from_msg(msg)
        except MessageError as exc:
            rospy.logwarn_throttle(
                30.0, f"client {self.name}: robot_{robot_id}'s description is unusable: {exc}"
            )

    # --- a lost robot -----------------------------------------------------------------------------
    def maybe_ask(self, vo) -> None:
        """Lost, and the own map does not place the camera: ask the server (in a thread)."""
        view = vo.lost_view()
        if view is None or self._busy or time.monotonic() - self._last_s < ASK_EVERY_S:
            return
        self._busy, self._last_s = True, time.monotonic()
        vo.expect_local_map()
        threading.Thread(target=self._ask, args=(vo, view, vo.map_segment), daemon=True).start()

    def _ask(self, vo, descriptors: np.ndarray, segment: int) -> None:
        from coop_slam.srv import Relocalize

        points, desc, pending = None, None, False
        try:
            bow, _ = self.vocabulary().transform(descriptors)
            gaps, weights, weight_max = encode_signature(bow)
            ask = rospy.ServiceProxy("/server/relocalize", Relocalize)
            ask.wait_for_service(timeout=2.0)
            rep = ask(
                robot_id=self.robot_id,
                map_segment=segment + self.segment_base(),
                bow_word_gaps=gaps,
                bow_weights=weights,
                bow_weight_max=weight_max,
            )
            pending = bool(getattr(rep, "pending", False))
            answer = (
                "sends the team's local map"
                if rep.found
                else ("fetches it" if pending else "cannot place it")
            )
            rospy.loginfo("client %s: lost; the server %s: %s", self.name, answer, rep.message)
            if rep.found and vo.map_segment == segment:
                pts = np.asarray(rep.points, float).reshape(-1, 3)
                # Sent in robot_k/map; the odometry's map frame is its first camera frame.
                points = transform_points(invert(self.T_base_cam), pts)
                desc = np.frombuffer(rep.descriptors, np.uint8).reshape(-1, 32)
        except (rospy.ROSException, rospy.ServiceException, CoopSlamError, ValueError) as exc:
            rospy.logwarn("client %s: lost; asking the server failed: %s", self.name, exc)
        finally:
            if pending:  # keep waiting, and ask again soon
                self._last_s = time.monotonic() - 0.7
            else:
                vo.offer_local_map(points, desc)
            self._busy = False
