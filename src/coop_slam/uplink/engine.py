"""A client's radio side: its odometry's keyframe events in, numbered keyframe messages out.

:class:`ClientUplink` turns events into records in the robot's map frame (:mod:`.records`),
holds and plans them (:mod:`.holdback`, :mod:`.planner`), encodes each as the message of its kind
(:mod:`coop_slam.wire.codec`) and numbers it in the client's session, keeping it until the
server acknowledges it (:class:`coop_slam.wire.delivery.Outbox`). It answers the server's requests
for whole keyframes and its acknowledgements, and continues above the keyframe ids and map
segments the server holds when the client restarts. The client node and the server bench drive
this same object; it is thread-safe (the node calls it from its tracking, acknowledgement and
resend threads).

Nothing that cannot travel is numbered: a record is checked as the server checks it and its
message serialized as it will be published (an injected :class:`Serializer`: the ROS node's is
genpy's) before it takes a sequence number; one that fails is said and left out (the planner
forgets it: its next update goes whole), so the server's in-order stream has no gap and the
publisher's stream is never corrupted.

With a :class:`coop_slam.uplink.spool.Spool`, every message numbered is on the robot's disk
before it is published, until the server acknowledges it. A restarted client sends what the
spool kept first, once it has heard from the server (:meth:`ClientUplink.server_found`): in the
kept session when the server's acknowledgement names it (the server takes each message once, so
those it took before the kill are not applied twice), else numbered anew in a session of its
own (the server saw none of them), or not at all when they were made for another team map.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Callable, NamedTuple, Protocol

import numpy as np

from ..camera import CameraModel
from ..errors import CoopSlamError
from ..vo.map import MapKeyframe
from ..vo.types import EVENT_NEW_SEGMENT, EVENT_WARNING, KEYFRAME_ACTIONS
from ..wire.codec import Outgoing, encode
from ..wire.delivery import DeliveryConfig, Outbox, new_session
from ..wire.messages import (
    KIND_KEYFRAME,
    KIND_SIGNATURE,
    KeyframeAck,
    KeyframeMessage,
    KeyframeRequest,
)
from ..wire.record import ACTION_NEW, KeyframeRecord
from .config import UplinkConfig
from .planner import Planner
from .records import event_record, keyframe_record, signature_of
from .spool import Spool, SpooledMessage, SpoolError, SpoolState

log = logging.getLogger(__name__)


class Note(NamedTuple):
    """What the odometry said, in order: ``warning`` (text), ``segment`` (a new map segment:
    its number as sent, and why), ``keyframe`` (a record made, with the ids as sent)."""

    kind: str
    text: str = ""
    segment: int = 0
    record: KeyframeRecord | None = None


class Serializer(Protocol):
    """A keyframe message as the bytes that travel, and back. ``dumps`` raises a CoopSlamError
    naming the field when the message cannot be serialized; ``format_id`` names the format (a
    spool of another format is not read)."""

    format_id: str

    def dumps(self, msg: KeyframeMessage) -> bytes: ...

    def loads(self, data: bytes) -> KeyframeMessage: ...


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
        serializer: Serializer | None = None,
        spool: Spool | None = None,
    ):
        """``vocabulary``: the server's (place signatures name its words), needed in pull mode.
        ``serializer``: what is published (None: not checked, as the server bench does);
        ``spool``: where messages are kept until acknowledged (None: in memory only). A spool
        that kept messages holds back everything until :meth:`server_found`."""
        self.robot_id = robot_id
        self.frame_id = f"robot_{robot_id}/map"
        self.T_base_cam = np.eye(4) if T_base_cam is None else T_base_cam
        self.planner = Planner(config)
        config = config or UplinkConfig()
        self._sends_depth = config.sends_depth_images()
        if config.mode == "pull" and config.depth_images and not self._sends_depth:
            log.info(
                "robot %d: low-bandwidth mode sends no depth images, so the team's dense map and "
                "occupancy grid get nothing from it (uplink.pull_depth_images: true sends them)",
                robot_id,
            )
        self.outbox = Outbox(**vars(delivery or DeliveryConfig()))
        self._vocabulary = None
        self.vocabulary = vocabulary
        self.camera: CameraModel | None = None  # the odometry's, set by the client
        # A restarted client continues above the keyframe ids and map segments the server
        # stored; after a camera change the next odometry's continue above this one's.
        self.kf_id_base, self.segment_base = 0, 0
        # New keyframes sent whole (not those a spool kept from before), and those sent as place
        # signatures only (pull mode, or a radio budget's; until the server asks for them)
        self._whole: set[int] = set()
        self._signature_only: set[int] = set()
        # New keyframes whose message found no room or could not travel, until one of theirs goes
        self._dropped_new: set[int] = set()
        self.refused_full = 0  # messages refused: the outbox or the spool was full
        self.resent_from_spool = 0  # messages a spool kept from before, sent by this run
        self._full_since = -1  # refused_full when it became full (-1: not full)
        self._request_seen = 0
        self._lock = threading.RLock()
        self.serializer, self.spool = serializer, spool
        if spool is not None and serializer is None:
            raise SpoolError("a spool keeps serialized messages: give the uplink a serializer")
        self.started = False  # heard from the server (server_found)
        self._made = 0  # records made by this run
        self._kept, self._kept_gone = SpoolState(), 0  # kept messages; those not to go
        if spool is not None:
            self._kept = self._restore(spool)
        # Messages a spool kept: the server must say which session it knows before any goes.
        self.waiting_for_server = bool(self._kept.messages)

    @property
    def vocabulary(self):
        """The server's vocabulary: place signatures name its words (pull mode, and the keyframes
        a radio budget holds back in full mode; without it, those are not sent at all)."""
        return self._vocabulary

    @vocabulary.setter
    def vocabulary(self, vocabulary) -> None:
        self._vocabulary = vocabulary
        # (full mode: what the budget holds back goes as its signature; in pull mode every new
        # keyframe is one, and the budget says which go)
        self.planner.gate.sign = vocabulary is not None and not self.pull

    @property
    def signatures(self) -> bool:
        """Whether this uplink may send place signatures (and answer the server's requests)."""
        return self.pull or self.planner.gate.budget.limited

    @property
    def pull(self) -> bool:
        return self.planner.pull

    @property
    def keyframes_sent(self) -> int:
        """New keyframes sent whole by this run."""
        return len(self._whole)

    @property
    def keyframes_held_back(self) -> int:
        """New keyframes not sent whole: as place signatures only, or (a radio budget's) not at
        all."""
        return len(self._signature_only) + self.planner.gate.held_back + len(self._dropped_new)

    @property
    def held(self) -> int:
        """Records held back, not sent yet."""
        return len(self.planner.holdback) + self.planner.gate.waiting

    @property
    def unacked(self) -> int:
        return self.outbox.unacked

    def continue_after(self, last_keyframe_id: int, last_map_segment: int) -> None:
        """This robot sent keyframes up to these ids before (a restarted client): the next go
        above them, in a new map segment."""
        if last_keyframe_id > 0:
            self.kf_id_base = int(last_keyframe_id)
            self.segment_base = int(last_map_segment) + 1

    # --- a restarted client -----------------------------------------------------------------------
    def _restore(self, spool: Spool) -> SpoolState:
        """What the spool kept, in the outbox as numbered then (tentatively: the server decides,
        :meth:`server_found`); new keyframes go above the kept ones."""
        try:
            kept = spool.load()
            messages = [(m.sequence, self._loaded(m)) for m in kept.messages]
        except CoopSlamError as exc:
            spool.set_aside(f"its messages do not decode ({exc})")
            return spool.load()
        if messages:
            self.outbox.restore(kept.session, kept.last_sequence, messages)
            self.continue_after(kept.max_keyframe_id, kept.max_map_segment)
        return kept

    def _loaded(self, m: SpooledMessage) -> KeyframeMessage:
        msg = self.serializer.loads(m.payload)
        msg.session, msg.sequence = m.session, m.sequence
        return msg

    def server_found(self, ack: KeyframeAck | None, map_id: str = "") -> list[KeyframeMessage]:
        """The server's first acknowledgement (None: none came; then call again with the first
        that comes) and its team map's id (``""``: unknown). Decides what becomes of the
        messages a spool kept and where new keyframe ids start; returns what goes now (what was
        kept first). Later calls: as :meth:`acknowledged`."""
        with self._lock:
            if ack is None:
                return []
            if self.started:
                self.acknowledged(ack)
                return []
            self.started = True
            own = self._settle_spool(ack, map_id)
            server = (ack.last_keyframe_id, ack.last_map_segment) if ack.last_keyframe_id else None
            floors = [f for f in (server, own) if f is not None]
            if self._made == 0:  # (the spool's floor was tentative)
                self.kf_id_base, self.segment_base = 0, 0
                if floors:
                    self.continue_after(max(f[0] for f in floors), max(f[1] for f in floors))
            elif floors and max(f[0] for f in floors) > self.kf_id_base:
                log.warning(
                    "robot %d: the server holds keyframes up to %d from before, but this client "
                    "made keyframes from %d on before it heard from the server: their ids may "
                    "collide (start the server first, or raise server_wait_s)",
                    self.robot_id,
                    max(f[0] for f in floors),
                    self.kf_id_base + 1,
                )
            self.waiting_for_server = False
            self.acknowledged(ack)
            going = self.outbox.pending()
            self.resent_from_spool += len(self._kept.messages) - self._kept_gone
            return going

    def _settle_spool(self, ack: KeyframeAck, map_id: str) -> tuple[int, int] | None:
        """What becomes of what the spool kept (see the module); returns the highest keyframe id
        and segment the spool says this robot sent into the server's map (None: nothing)."""
        spool, kept = self.spool, self._kept
        self._kept_gone = 0
        if spool is None:
            return None
        meta = spool.load()
        if meta.map_id and map_id and meta.map_id != map_id:
            why = f"made for team map {meta.map_id}, the server's is {map_id}"
            if kept.messages:
                self._set_aside(why)
            spool.new_map(map_id)
            if kept.messages:
                self._renumber_new()
            return None
        spool.set_map_id(map_id)
        if kept.messages and ack.session == kept.session:
            log.warning(
                "robot %d: %d keyframe messages kept on disk from before the restart: the server "
                "has session %d up to %d, sending the rest first",
                self.robot_id,
                len(kept.messages),
                ack.session,
                ack.sequence,
            )
            self._kept_gone = sum(m.sequence <= ack.sequence for m in kept.messages)
        elif kept.messages:  # newer than any the server knows, whatever the clock did
            session = max(new_session(), kept.session + 1, ack.session + 1)
            log.warning(
                "robot %d: %d keyframe messages kept on disk from before the restart: the server "
                "saw none of them, sending them first in session %d",
                self.robot_id,
                len(kept.messages),
                session,
            )
            self._renumber(session)
        if meta.max_keyframe_id <= 0:
            return None
        return meta.max_keyframe_id, meta.max_map_segment

    def _renumber(self, session: int) -> None:
        """Everything kept numbered anew in ``session``, on disk and in the outbox alike."""
        if self.spool is not None:
            self.spool.renumber(session)
        for q, msg in self.outbox.renumber(session):
            msg.session, msg.sequence = session, q

    def _set_aside(self, why: str) -> None:
        """The spool's messages are for another map: none goes."""
        kept = self._kept
        aside = self.spool.set_aside(why)
        log.warning(
            "robot %d: %d keyframe messages kept on disk from before were %s: not sent, set aside "
            "as %s",
            self.robot_id,
            len(kept.messages),
            why,
            aside,
        )
        self.outbox.ack(kept.session, kept.last_sequence)
        self._kept_gone = len(kept.messages)

    def _renumber_new(self) -> None:
        """What this run numbered while it waited for the server goes in a new session, kept in
        the new spool file."""
        session = max(new_session(), self.outbox.session + 1)
        renumbered = self.outbox.renumber(session)
        for q, msg in renumbered:
            msg.session, msg.sequence = session, q
            self.spool.append(self._spooled(msg, self._payload(msg)))

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
                    self._made += 1
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
        """The server asks for whole keyframes (low-bandwidth mode, or those a radio budget sent
        as signatures): each goes as new, in full; keyframes the odometry no longer has
        (``keyframe(odometry id)`` None) are not sent (the server gives up on them), nor those
        that went whole already (the budget let one through while the request was on its way:
        it arrives as it is). A latched request already answered: nothing."""
        with self._lock:
            if request.request and request.request <= self._request_seen:
                return []
            self._request_seen = request.request
            going = []
            for kid in request.keyframe_ids:
                if self.planner.holds(kid):
                    continue
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
        """A record with this client run's keyframe ids and map segments (without its depth
        image where the mode leaves it out)."""
        if not self._sends_depth:
            rec.depth_image = np.zeros(0, np.uint8)
        rec.keyframe_id += self.kf_id_base
        rec.covisible_ids = rec.covisible_ids + np.uint32(self.kf_id_base)
        rec.map_segment += self.segment_base
        return rec

    def _send(self, going: list[tuple[KeyframeRecord, Outgoing]]) -> list[KeyframeMessage]:
        """The messages of records as the planner prepared them, numbered (none while waiting
        for the server: they go with what the spool kept). A record whose
        message cannot travel, or that finds no room, is left out and forgotten by the planner
        (its next update goes whole); no sequence number is used, so the server sees no gap."""
        out = []
        for rec, how in going:
            if how.skip:
                continue
            try:
                msg, payload = self._encoded(rec, how)
            except CoopSlamError as exc:  # one record that cannot go must not stop the rest
                log.error("keyframe %d not sent: %s", rec.keyframe_id, exc)
                self._dropped(rec)
                continue
            if not self._room(len(payload)):
                self._dropped(rec)
                continue
            try:
                msg.session, msg.sequence = self.outbox.session, self.outbox.sequence + 1
                if self.spool is not None:  # on disk before it is published
                    self.spool.append(self._spooled(msg, payload))
            except SpoolError as exc:
                log.error("keyframe %d not sent: %s", rec.keyframe_id, exc)
                self._dropped(rec)
                continue
            self.outbox.add(msg, nbytes=len(payload))
            self.planner.gate.sent(rec.keyframe_id, self.planner.kind_of(how), len(payload))
            # (a keyframe whose first message was dropped: its update goes whole, and the
            # server takes it as new)
            if rec.action == ACTION_NEW or rec.keyframe_id in self._dropped_new:
                self._dropped_new.discard(rec.keyframe_id)
                if how.signature:
                    self._signature_only.add(rec.keyframe_id)
                else:
                    self._signature_only.discard(rec.keyframe_id)
                    self._whole.add(rec.keyframe_id)
            if not self.waiting_for_server:
                out.append(msg)
        return out

    def _dropped(self, rec: KeyframeRecord) -> None:
        """``rec``'s message did not go: the planner forgets it (its next update goes whole); a
        new keyframe's counts as held back until something of it goes."""
        self.planner.forget([rec.keyframe_id])
        if rec.action == ACTION_NEW:
            self._dropped_new.add(rec.keyframe_id)

    def _encoded(self, rec: KeyframeRecord, how: Outgoing) -> tuple[KeyframeMessage, bytes]:
        """``rec``'s message, checked as the server checks it, and its bytes as published
        (unnumbered: the numbers are the outbox's)."""
        rec.validate({self.robot_id})
        if how.signature:
            msg = encode(signature_of(rec, self.vocabulary), how, self.frame_id)
        else:
            msg = encode(rec, how, self.frame_id)
        return msg, self._payload(msg)

    def _payload(self, msg: KeyframeMessage) -> bytes:
        if self.serializer is None:
            return b""
        return self.serializer.dumps(dataclasses.replace(msg, session=0, sequence=0))

    def _spooled(self, msg: KeyframeMessage, payload: bytes) -> SpooledMessage:
        new = msg.kind == KIND_SIGNATURE or (
            msg.kind == KIND_KEYFRAME and not msg.keyframe[0].replaces
        )
        return SpooledMessage(
            msg.session, msg.sequence, msg.keyframe_id, msg.map_segment, new, payload
        )

    def _room(self, payload_bytes: int) -> bool:
        """Room for one more message; said once when there is none (the newest are refused: the
        oldest is what the server waits for)."""
        full = self.outbox.full or (self.spool is not None and not self.spool.fits(payload_bytes))
        if not full:
            if self._full_since >= 0:
                log.warning(
                    "robot %d: the server acknowledged again: %d keyframe messages were not sent "
                    "meanwhile",
                    self.robot_id,
                    self.refused_full - self._full_since,
                )
                self._full_since = -1
            return True
        if self._full_since < 0:
            self._full_since = self.refused_full
            where = self.spool.path if self.spool is not None else "memory"
            log.warning(
                "robot %d: %d keyframe messages (%.1f MB) not acknowledged by the server are "
                "kept in %s (max_unacked / spool_max_mb reached): keyframes made from now on are "
                "not sent until the server acknowledges (is it running? see "
                "/robot_%d/keyframe_ack)",
                self.robot_id,
                self.outbox.unacked,
                (self.spool.bytes if self.spool is not None else 0) / 1e6,
                where,
                self.robot_id,
            )
        self.refused_full += 1
        return False

    # --- the server's answers ---------------------------------------------------------------------
    def acknowledged(self, ack: KeyframeAck) -> None:
        """The server's acknowledgement (or receipt) of this robot's messages. While waiting for
        the server (:meth:`server_found` not called yet): nothing."""
        with self._lock:
            if self.waiting_for_server:
                return
            self.outbox.server_is(ack.server_session)
            if self.outbox.ack(ack.session, ack.sequence) and self.spool is not None:
                try:
                    self.spool.ack(ack.session, ack.sequence)
                except SpoolError as exc:  # kept on disk: sent again after a restart, no harm
                    log.error("robot %d: %s", self.robot_id, exc)
            self.outbox.received(ack.received_session, ack.received_sequence)
        # Keyframes the server refused: later messages must not count on it holding them.
        self.planner.forget(ack.refused_keyframe_ids)

    def due_again(self, now: float | None = None) -> list[KeyframeMessage]:
        """Unacknowledged messages to send again now (oldest first)."""
        with self._lock:
            if self.waiting_for_server:
                return []
            return self.outbox.due(time.monotonic() if now is None else now)

    def close(self) -> None:
        if self.spool is not None:
            self.spool.close()
