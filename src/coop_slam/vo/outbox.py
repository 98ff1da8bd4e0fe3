"""What a client sends the server: its odometry's keyframe events as :class:`KeyframeRecord` s,
expressed in the robot's map frame.

The odometry's own map frame is its first camera frame. The robot's ``robot_k/map`` is the robot
body at start (z up, REP-103), so poses and points are moved by ``T_base_cam`` on the way out.
"""

from __future__ import annotations

import dataclasses
import heapq
import threading
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..bow.signature import word_counts
from ..config import require
from ..datasets.base import CameraModel
from ..descriptors import DESCRIPTOR_BYTES, hamming_rows
from ..geometry import transform_points
from ..keyframe_record import (
    ACTION_NEW,
    ACTION_REMOVE,
    ACTION_UPDATE,
    MAX_REF_KEYFRAMES,
    KeyframeRecord,
    PlaceSignature,
    apply_moves,
    apply_observation_patch,
    observation_index,
    observation_patch,
    split_moves,
)
from .map import MapKeyframe
from .types import KEYFRAME_ACTIONS, VoEvent

UPLINK_MODES = ("full", "pull")


def keyframe_record(
    kf: MapKeyframe,
    robot_id: int,
    camera: CameraModel,
    T_base_cam: np.ndarray | None = None,
    action: int = ACTION_NEW,
) -> KeyframeRecord:
    """The record of one keyframe snapshot (NEW or UPDATE), in the robot's map frame."""
    T_base_cam = np.eye(4) if T_base_cam is None else T_base_cam
    pts = (
        transform_points(T_base_cam, kf.map_points_xyz)
        if len(kf.map_points_xyz)
        else np.zeros((0, 3))
    )
    return KeyframeRecord(
        robot_id=robot_id,
        keyframe_id=int(kf.keyframe_id),
        stamp_s=float(kf.stamp_s),
        camera=camera,
        T_map_cam=T_base_cam @ kf.T_map_cam,
        keypoints=kf.keypoints_flat().reshape(-1, 4),
        octaves=kf.octaves,
        descriptors=kf.descriptors,
        depths_m=kf.depths_m,
        map_point_ids=kf.map_point_ids,
        map_points=pts.astype(np.float32),
        covisible_ids=kf.covisible_ids,
        covisible_weights=kf.covisible_weights,
        map_segment=int(kf.map_segment),
        action=action,
    )


def event_record(
    ev: VoEvent, robot_id: int, camera: CameraModel, T_base_cam: np.ndarray | None = None
) -> KeyframeRecord:
    """The record of a keyframe event (NEW, UPDATE or REMOVE); see :data:`KEYFRAME_ACTIONS`."""
    action = KEYFRAME_ACTIONS[ev.kind]
    if action == ACTION_REMOVE:
        return KeyframeRecord(
            robot_id=robot_id,
            keyframe_id=ev.keyframe_id,
            stamp_s=0.0,
            camera=camera,
            T_map_cam=np.eye(4),
            map_segment=ev.map_segment,
            action=action,
        )
    return keyframe_record(ev.keyframe, robot_id, camera, T_base_cam, action)


@dataclass
class UplinkConfig:
    """What a client's keyframe messages carry (``config/client.yaml`` section ``uplink``)."""

    # Updates leave out what the keyframe saw when the server has it, and carry only the
    # observations that changed (false: every update in full, as a new keyframe).
    delta_updates: bool = True
    # A map point that moved less than this since it last went to the server is not sent
    # again with an update [m]; 0 = every point that moved at all.
    point_move_m: float = 0.002
    # full: every keyframe goes whole. pull (low-bandwidth mode, the server's pull.enabled): a
    # new keyframe goes as its place signature; whole when the server asks for it, and only
    # then its updates.
    mode: str = "full"
    # Full mode: a new keyframe waits this long before it goes [s of data time], and goes with
    # what local BA made of it meanwhile; one the client culls within it (most culled keyframes
    # are) never travels. 0 = at once.
    hold_new_s: float = 1.0
    # Full mode: the updates of a keyframe the server has go at most once per this long, the
    # latest of them [s of data time] (local BA moves every keyframe of its window after each new
    # keyframe). 0 = each as it comes.
    coalesce_updates_s: float = 1.0
    # Full mode: a keyframe leaves out the descriptors of keypoints observing a map point the
    # server has in another keyframe (it takes them there): a map point's descriptor travels
    # once. false: every keyframe carries all its descriptors.
    share_descriptors: bool = True
    # ... when the descriptor there differs from the keypoint's own in at most this many bits
    # (of 256): a map point's descriptor changes with the view (median 33 bits between keyframes
    # of our worlds), and matching across robots, which the server does with them, needs them
    # close to what the camera saw. 256: always.
    share_max_bits: int = 32
    # How many of the keyframes the server holds are searched for a new keyframe's map points:
    # its covisible ones first, then the newest.
    ref_keyframes: int = 32
    # Wall-clock seconds without a camera frame after which whatever is held goes (the camera
    # stopped, or the run ended).
    idle_flush_s: float = 2.0

    def validate(self) -> None:
        require(self.point_move_m >= 0, "uplink.point_move_m must be >= 0 [m]")
        require(self.mode in UPLINK_MODES, f"uplink.mode must be one of {UPLINK_MODES}")
        require(self.hold_new_s >= 0, "uplink.hold_new_s must be >= 0 [s]")
        require(self.coalesce_updates_s >= 0, "uplink.coalesce_updates_s must be >= 0 [s]")
        require(self.idle_flush_s > 0, "uplink.idle_flush_s must be > 0 [s]")
        require(
            0 <= self.share_max_bits <= 8 * DESCRIPTOR_BYTES,
            f"uplink.share_max_bits must be in [0, {8 * DESCRIPTOR_BYTES}]",
        )
        require(
            1 <= self.ref_keyframes <= MAX_REF_KEYFRAMES,
            f"uplink.ref_keyframes must be in [1, {MAX_REF_KEYFRAMES}]",
        )


def signature_of(rec: KeyframeRecord, vocabulary) -> PlaceSignature:
    """The place signature of a new keyframe (low-bandwidth mode): its record without what it saw
    and its BoW vector in ``vocabulary`` (the server's)."""
    bow, _ = vocabulary.transform(rec.descriptors)
    counts = word_counts(bow, vocabulary.word_weights)
    bare = dataclasses.replace(
        rec,
        keypoints=np.zeros((0, 4), np.float32),
        octaves=np.zeros(0, np.uint8),
        descriptors=np.zeros((0, 32), np.uint8),
        depths_m=np.zeros(0, np.float32),
        map_point_ids=np.zeros(0, np.uint32),
        map_points=np.zeros((0, 3), np.float32),
    )
    return PlaceSignature(bare, bow, counts)


class Outgoing(NamedTuple):
    """How a keyframe record goes: ``delta`` without what the keyframe saw (``KeyFrame.delta``);
    ``patched`` (delta updates only) the keypoints whose observations go, None for all;
    ``signature`` as its place signature only; ``skip`` not at all; ``refs`` (a full message) the
    keyframes whose descriptors it refers to and, per keypoint, which (``KeyFrame``
    ``ref_keyframes``, ``descriptor_refs``; None: every descriptor goes); ``moves`` (a delta
    update) keypoints whose map point only moved and their (k, 3) moves [m] in steps of
    ``MOVE_STEP_M`` (``KeyFrame`` ``moved``, ``moves_q``; their observations are not in the
    patch)."""

    delta: bool
    patched: np.ndarray | None = None
    signature: bool = False
    skip: bool = False
    refs: tuple[np.ndarray, np.ndarray] | None = None
    moves: tuple[np.ndarray, np.ndarray] | None = None


class _Held(NamedTuple):
    """What the server holds of a keyframe: the digest of what it saw (as sent), its
    observations (map point ids, per-keypoint points, NaN where none), its map segment and its
    descriptors."""

    digest: bytes
    ids: np.ndarray
    points: np.ndarray
    segment: int
    descriptors: np.ndarray  # (N, 32) as the server holds them


class Holdback:
    """When each keyframe record goes: a new keyframe after ``hold_new_s`` (its record then the
    latest snapshot, still as new; nothing at all when it was removed meanwhile), the updates of a
    keyframe already sent at most once per ``coalesce_s`` (the latest, ``coalesce_s`` after the
    first of them was held), removals of sent keyframes at once. Times are data time (frame
    stamps), so a lock-step run sends the same messages however fast the machine is. Records of
    one keyframe go in the order they were made; the server handles keyframes in any order."""

    def __init__(self, hold_new_s: float = 0.0, coalesce_s: float = 0.0):
        self.hold_new_s, self.coalesce_s = float(hold_new_s), float(coalesce_s)
        # keyframe id -> (data time held since, latest record); insertion order = creation order
        self._new: dict[int, tuple[float, KeyframeRecord]] = {}
        self._updates: dict[int, tuple[float, KeyframeRecord]] = {}

    def __len__(self) -> int:
        return len(self._new) + len(self._updates)

    def offer(self, rec: KeyframeRecord, now_s: float) -> list[KeyframeRecord]:
        """Hold ``rec`` (made at data time ``now_s``); returns what goes at once."""
        k = rec.keyframe_id
        if rec.action == ACTION_NEW:
            if self.hold_new_s <= 0:
                return [rec]
            self._new[k] = (now_s, rec)
        elif rec.action == ACTION_UPDATE:
            if k in self._new:  # not sent yet: it goes as new, as it is now
                self._new[k] = (self._new[k][0], dataclasses.replace(rec, action=ACTION_NEW))
            elif self.coalesce_s <= 0:
                return [rec]
            else:
                self._updates[k] = (self._updates.get(k, (now_s,))[0], rec)
        else:
            self._updates.pop(k, None)
            if self._new.pop(k, None) is None:  # the server has it
                return [rec]
        return []

    def due(self, now_s: float) -> list[KeyframeRecord]:
        """What has waited long enough at data time ``now_s``: new keyframes first, oldest
        first. Held later than ``now_s`` (data time went back: a looped bag, a reset clock) is
        due too, or it would wait until data time caught up."""
        out = []
        for held, wait in ((self._new, self.hold_new_s), (self._updates, self.coalesce_s)):
            for k in [k for k, (t, _) in held.items() if now_s - t >= wait or now_s < t]:
                out.append(held.pop(k)[1])
        return out

    def flush(self) -> list[KeyframeRecord]:
        """Everything held, new keyframes first."""
        return self.due(float("inf"))


class Uplink:
    """What each keyframe message carries. An update goes without what the keyframe saw
    (``KeyFrame.delta``) when its keypoints, octaves, descriptors and depths are the ones sent with
    the keyframe as new (the server has them), and then with only the observations that changed
    since they last went:
    keypoints that observe another map point (or none), or whose map point moved more than
    ``point_move_m`` (local BA moves most points of a keyframe a little, and an update that
    sent them all was most of a client's traffic); a point that only moved goes as its move in
    int16 steps of ``MOVE_STEP_M`` (when ``point_move_m`` is at least a step). ``delta_updates``
    False: every update goes in full.

    In pull mode a new keyframe goes as its place signature, and whole only when the server asks
    (:meth:`answer`); updates of keyframes the server holds move their pose only (no points),
    those of the others are not sent; removals are.

    A full message leaves out the descriptors of keypoints observing a map point that a
    keyframe the server holds observes too (``share_descriptors``): the server takes them there.

    It keeps, per keyframe, the observations as the server holds them (the messages reach the
    server in order, and every one does: :class:`coop_slam.delivery.Outbox`); a keyframe the
    server refused (:meth:`forget`, from its acknowledgement) is no longer counted on.

    When records go is :class:`Holdback`'s (full mode; in pull mode each goes as it comes):
    :meth:`offer` a record as the odometry makes it, send what it and :meth:`due` return."""

    def __init__(self, config: UplinkConfig | None = None):
        config = config or UplinkConfig()
        config.validate()
        self.enabled, self.min_point_move_m = config.delta_updates, config.point_move_m
        self.pull = config.mode == "pull"
        self.idle_flush_s = config.idle_flush_s
        self.share = config.share_descriptors and not self.pull
        self.max_refs, self.max_bits = config.ref_keyframes, config.share_max_bits
        self.holdback = (
            Holdback() if self.pull else Holdback(config.hold_new_s, config.coalesce_updates_s)
        )
        self._held: dict[int, _Held] = {}  # keyframe id -> what the server holds of it
        # Keyframes the server refused, to forget before the next message is prepared (said by
        # the acknowledgement's thread)
        self._refused: set[int] = set()
        self._refused_lock = threading.Lock()

    def offer(self, rec: KeyframeRecord, now_s: float) -> list[tuple[KeyframeRecord, Outgoing]]:
        """A record the odometry made at data time ``now_s``: what goes now, and how."""
        return [(r, self.prepare(r)) for r in self.holdback.offer(rec, now_s)]

    def due(self, now_s: float) -> list[tuple[KeyframeRecord, Outgoing]]:
        """The held records that go at data time ``now_s``, and how."""
        return [(r, self.prepare(r)) for r in self.holdback.due(now_s)]

    def flush(self) -> list[tuple[KeyframeRecord, Outgoing]]:
        """Every held record, and how it goes."""
        return [(r, self.prepare(r)) for r in self.holdback.flush()]

    def forget(self, keyframe_ids) -> None:
        """The server refused these keyframes' last messages: it does not hold them as this
        uplink thinks, so no message refers to them and their next update goes whole (any
        thread)."""
        with self._refused_lock:
            self._refused.update(int(k) for k in keyframe_ids)

    def prepare(self, rec: KeyframeRecord) -> Outgoing:
        """How ``rec`` (about to be sent) goes; remembers what the server will hold after it."""
        with self._refused_lock:
            refused, self._refused = self._refused, set()
        for k in refused:
            self._held.pop(k, None)
        if rec.action == ACTION_NEW:
            if self.pull:
                return Outgoing(False, signature=True)
            refs, descriptors = self._refs(rec)
            self._hold(rec.keyframe_id, rec.static_digest(), rec, descriptors)
            return Outgoing(False, refs=refs)
        held = self._held.get(rec.keyframe_id)
        if self.pull and rec.action == ACTION_UPDATE and held is None:
            return Outgoing(False, skip=True)
        if rec.action != ACTION_UPDATE or not self.enabled or held is None:
            self._held.pop(rec.keyframe_id, None)
            return Outgoing(False)
        digest = rec.static_digest()
        if held.digest != digest:  # what the keyframe saw changed: it goes in full
            refs, descriptors = self._refs(rec)
            self._hold(rec.keyframe_id, digest, rec, descriptors)
            return Outgoing(False, refs=refs)
        if self.pull:  # the radio's budget goes to whole keyframes: updates move the pose
            return Outgoing(True, np.zeros(0, np.uint32))
        per_keypoint = rec.map_points_per_keypoint()
        patched = observation_patch(
            held.ids, held.points, rec.map_point_ids, per_keypoint, self.min_point_move_m
        )
        patched, moved, moves = split_moves(
            held.ids, held.points, patched, rec.map_point_ids, per_keypoint, self.min_point_move_m
        )
        ids = rec.map_point_ids[patched]
        held_ids, held_points = apply_observation_patch(
            held.ids, held.points, patched, ids, per_keypoint[patched][ids != 0]
        )
        held_points = apply_moves(held_ids, held_points, moved, moves)
        self._held[rec.keyframe_id] = held._replace(ids=held_ids, points=held_points)
        return Outgoing(True, patched, moves=(moved, moves) if len(moved) else None)

    def answer(self, rec: KeyframeRecord) -> Outgoing:
        """A keyframe the server asked for (pull mode): it goes whole, as new, and its updates
        from now on."""
        self._hold(rec.keyframe_id, rec.static_digest(), rec)
        return Outgoing(False)

    def _hold(
        self,
        keyframe_id: int,
        digest: bytes,
        rec: KeyframeRecord,
        descriptors: np.ndarray | None = None,
    ) -> None:
        """Remember what the server holds of ``rec`` once it got it: its descriptors are
        ``descriptors`` (those it took from other keyframes) or the record's."""
        self._held[keyframe_id] = _Held(
            digest,
            np.array(rec.map_point_ids, np.uint32),
            rec.map_points_per_keypoint(),
            int(rec.map_segment),
            np.array(rec.descriptors if descriptors is None else descriptors, np.uint8),
        )

    def _refs(self, rec: KeyframeRecord) -> tuple[tuple[np.ndarray, np.ndarray] | None, np.ndarray]:
        """Which of ``rec``'s descriptors the server can take from keyframes it holds: a
        keypoint's map point's descriptor there within ``share_max_bits`` of its own. Returns
        the keyframes (``rec``'s covisible ones first, then the newest, at most
        ``ref_keyframes``, of its map segment) and per keypoint the one to take it from (0: it
        travels) -- None when every descriptor travels -- and the descriptors the server then
        holds."""
        own = np.asarray(rec.descriptors, np.uint8)
        if not self.share:
            return None, own
        server = own.copy()
        ids = np.asarray(rec.map_point_ids, np.uint32)
        same = {k for k, h in self._held.items() if h.segment == rec.map_segment}
        same.discard(rec.keyframe_id)
        by_weight = np.argsort(-np.asarray(rec.covisible_weights, np.int64), kind="stable")
        covisible = [k for k in (int(rec.covisible_ids[i]) for i in by_weight) if k in same]
        newest = heapq.nlargest(self.max_refs, same)
        order = list(dict.fromkeys(covisible + newest))[: self.max_refs]
        refs = np.zeros(len(ids), np.uint8)
        used: list[int] = []
        for kf_id in order:
            open_ = np.flatnonzero((refs == 0) & (ids != 0))
            if not len(open_):
                break
            held = self._held[kf_id]
            at = observation_index(held.ids, ids[open_])
            open_, at = open_[at >= 0], at[at >= 0]
            close = hamming_rows(own[open_], held.descriptors[at]) <= self.max_bits
            if np.any(close):
                used.append(kf_id)
                refs[open_[close]] = len(used)
                server[open_[close]] = held.descriptors[at[close]]
        if not used:
            return None, own
        return (np.asarray(used, np.uint32), refs), server
