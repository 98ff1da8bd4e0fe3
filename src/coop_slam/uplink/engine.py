"""A client's radio side: its odometry's keyframe events in, numbered keyframe messages out.

:class:`ClientUplink` turns events into records in the robot's map frame (:mod:`.records`),
holds and plans them (:mod:`.holdback`, :mod:`.planner`), encodes each as the message of its kind
(:mod:`coop_slam.wire.codec`) and numbers it in the client's session, keeping it until the
server acknowledges it (:class:`coop_slam.wire.delivery.Outbox`). It answers the server's requests
for whole keyframes and its acknowledgements, and continues above the keyframe ids and map
segments the server holds when the client restarts. The client node and the server bench drive
this same object; it is thread-safe (the node calls it from its tracking, acknowledgement and
resend threads).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable, NamedTuple

import numpy as np

from ..camera import CameraModel
from ..errors import CoopSlamError
from ..vo.map import MapKeyframe
from ..vo.types import EVENT_NEW_SEGMENT, EVENT_WARNING, KEYFRAME_ACTIONS
from ..wire.codec import Outgoing, encode
from ..wire.delivery import DeliveryConfig, Outbox
from ..wire.messages import KeyframeAck, KeyframeMessage, KeyframeRequest
from ..wire.record import ACTION_NEW, KeyframeRecord
from .config import UplinkConfig
from .planner import Planner
from .records import event_record, keyframe_record, signature_of

log = logging.getLogger(__name__)


class Note(NamedTuple):
    """What the odometry said, in order: ``warning`` (text), ``segment`` (a new map segment:
    its number as sent, and why), ``keyframe`` (a record made, with the ids as sent)."""

    kind: str
    text: str = ""
    segment: int = 0
    record: KeyframeRecord | None = None


class Step(NamedTuple):
    messages: list[KeyframeMessage]  # to send now, numbered
    notes: list[Note]


class ClientUplink:
    def __init__(
        self,
        robot_id: int,
        config: UplinkConfig | None = None,
        delivery: DeliveryConfig | None = None,
        T_base_cam: np.ndarray | None = None,
        vocabulary=None,
    ):
        """``vocabulary``: the server's (place signatures name its words), needed in pull mode."""
        self.robot_id = robot_id
        self.frame_id = f"robot_{robot_id}/map"
        self.T_base_cam = np.eye(4) if T_base_cam is None else T_base_cam
        self.planner = Planner(config)
        self.outbox = Outbox(**vars(delivery or DeliveryConfig()))
        self.vocabulary = vocabulary
        self.camera: CameraModel | None = None  # the odometry's, set by the client
        # A restarted client continues above the keyframe ids and map segments the server
        # stored; after a camera change the next odometry's continue above this one's.
        self.kf_id_base, self.segment_base = 0, 0
        self.keyframes_sent = 0  # new keyframes sent
        self.overflowed = False  # the outbox gave up a message (said once)
        self._request_seen = 0
        self._lock = threading.RLock()

    @property
    def pull(self) -> bool:
        return self.planner.pull

    @property
    def held(self) -> int:
        """Records held back, not sent yet."""
        return len(self.planner.holdback)

    @property
    def unacked(self) -> int:
        return self.outbox.unacked

    def continue_after(self, last_keyframe_id: int, last_map_segment: int) -> None:
        """The server holds keyframes of this robot up to these ids (a restarted client): the
        next go above them, in a new map segment."""
        if last_keyframe_id > 0:
            self.kf_id_base = int(last_keyframe_id)
            self.segment_base = int(last_map_segment) + 1

    def odometry_replaced(self, keyframes_made: int, map_segment: int) -> None:
        """A new odometry starts (the camera changed): it numbers its keyframes from 1 and its
        segments from 0 again, so the messages go on after the old one's."""
        with self._lock:
            self.kf_id_base += keyframes_made
            self.segment_base += map_segment

    # --- records out ------------------------------------------------------------------------------
    def events(self, events, now_s: float | None) -> Step:
        """The odometry's events at data time ``now_s``: the messages that go now (None: the
        odometry is closing, everything held goes) and what the events said."""
        made_s = 0.0 if now_s is None else now_s
        notes, going = [], []
        with self._lock:
            for ev in events:
                if ev.kind == EVENT_WARNING:
                    notes.append(Note("warning", ev.message))
                elif ev.kind == EVENT_NEW_SEGMENT:
                    segment = ev.map_segment + self.segment_base
                    notes.append(Note("segment", ev.message, segment))
                    going += self.planner.flush()  # the old map's keyframes go first
                elif ev.kind in KEYFRAME_ACTIONS:
                    rec = self._as_sent(
                        event_record(ev, self.robot_id, self.camera, self.T_base_cam)
                    )
                    notes.append(Note("keyframe", record=rec))
                    going += self.planner.offer(rec, made_s)
            going += self.planner.flush() if now_s is None else self.planner.due(now_s)
            return Step(self._send(going), notes)

    def flush(self) -> list[KeyframeMessage]:
        """Every held record's message."""
        with self._lock:
            return self._send(self.planner.flush())

    def answer(
        self, request: KeyframeRequest, keyframe: Callable[[int], MapKeyframe | None]
    ) -> list[KeyframeMessage]:
        """The server asks for whole keyframes (low-bandwidth mode): each goes as new, in full;
        keyframes the odometry no longer has (``keyframe(odometry id)`` None) are not sent (the
        server gives up on them). A latched request already answered: nothing."""
        with self._lock:
            if request.request and request.request <= self._request_seen:
                return []
            self._request_seen = request.request
            going = []
            for kid in request.keyframe_ids:
                kf = keyframe(int(kid) - self.kf_id_base)
                if kf is None:
                    log.info("the server asks for keyframe %d, gone", kid)
                    continue
                rec = self._as_sent(
                    keyframe_record(kf, self.robot_id, self.camera, self.T_base_cam)
                )
                rec.action = ACTION_NEW
                going.append((rec, self.planner.answer(rec)))
            return self._send(going)

    def _as_sent(self, rec: KeyframeRecord) -> KeyframeRecord:
        """A record with this client run's keyframe ids and map segments."""
        rec.keyframe_id += self.kf_id_base
        rec.covisible_ids = rec.covisible_ids + np.uint32(self.kf_id_base)
        rec.map_segment += self.segment_base
        return rec

    def _send(self, going: list[tuple[KeyframeRecord, Outgoing]]) -> list[KeyframeMessage]:
        """The messages of records as the planner prepared them, numbered."""
        out = []
        for rec, how in going:
            if how.skip:
                continue
            try:
                if how.signature:
                    msg = encode(signature_of(rec, self.vocabulary), how, self.frame_id)
                else:
                    msg = encode(rec, how, self.frame_id)
            except CoopSlamError as exc:  # one record the encoder refuses must not stop the rest
                log.error("keyframe %d not sent: %s", rec.keyframe_id, exc)
                continue
            self.keyframes_sent += rec.action == ACTION_NEW
            msg.session, msg.sequence, overflow = self.outbox.add(msg)
            if overflow and not self.overflowed:
                self.overflowed = True
                log.warning(
                    "%d keyframe messages not acknowledged by the server (is it running? see "
                    "/robot_%d/keyframe_ack): the oldest are given up from now on (max_unacked)",
                    self.outbox.max_unacked,
                    self.robot_id,
                )
            out.append(msg)
        return out

    # --- the server's answers ---------------------------------------------------------------------
    def acknowledged(self, ack: KeyframeAck) -> None:
        """The server's acknowledgement (or receipt) of this robot's messages."""
        with self._lock:
            self.outbox.server_is(ack.server_session)
            self.outbox.ack(ack.session, ack.sequence)
            self.outbox.received(ack.received_session, ack.received_sequence)
        # Keyframes the server refused: later messages must not count on it holding them.
        self.planner.forget(ack.refused_keyframe_ids)

    def due_again(self, now: float | None = None) -> list[KeyframeMessage]:
        """Unacknowledged messages to send again now (oldest first)."""
        with self._lock:
            return self.outbox.due(time.monotonic() if now is None else now)
