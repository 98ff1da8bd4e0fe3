"""The team map on disk: a durable, versioned SQLite store the server writes as it accepts input,
and from which a restarted server (``resume``) or a later session (``load_map``) rebuilds the
whole team state.

The server core is deterministic: the same input in the same order gives the same keyframe
database, groups, merges, pose graph and optimized poses. So the store keeps the server's input
as an append-only log -- every accepted keyframe message (with its keypoints, descriptors, depths
and map points), marker sighting, rendezvous request and global-BA request -- and rebuilds the
state by feeding that log to a fresh :class:`~coop_slam.team.server.TeamServer`. Beside the log
it keeps the derived state as tables a user can query with ``sqlite3`` (keyframes, optimized
poses, merges, constraints, groups), and checks on rebuild that the rebuilt poses are the stored
ones. The log needs no vocabulary: BoW vectors are recomputed from the stored descriptors.

Schema (``SCHEMA_VERSION`` 1), one file:

- ``meta(key TEXT PRIMARY KEY, value TEXT)``: ``schema_version``, ``created_utc``, ``robots``
  (JSON list), ``vocabulary_sha256``, ``map_id`` (a random id of this team map, kept on resume: a
  client's spool made for another map is not sent into this one).
- ``inputs(seq INTEGER PRIMARY KEY, kind TEXT, robot_id INTEGER, keyframe_id INTEGER,
  action INTEGER, stamp_s REAL, payload BLOB)``: the log, in the order the server took it.
  ``kind`` is ``keyframe`` (payload: :func:`encode_record`), ``sighting``, ``rendezvous`` or
  ``global_ba`` (payload: JSON of the call's arguments).
- ``keyframes(robot_id, keyframe_id, map_segment, sensor, stamp_s, T_map_cam BLOB,
  T_group_cam BLOB, PRIMARY KEY(robot_id, keyframe_id))``: stored keyframes (removed ones
  deleted); poses as 16 little-endian float64, row-major; ``T_group_cam`` optimized, in the
  frame of the robot's group root map.
- ``merges(seq, type, robot_a, robot_b, keyframe_a, keyframe_b, stamp_s, T_mapA_mapB BLOB,
  inliers, residual_px)`` and ``constraints(seq, type, robot_a, keyframe_a, robot_b, keyframe_b,
  stamp_s, T_camA_camB BLOB, inliers, residual_px)``.
- ``groups(robot_id INTEGER PRIMARY KEY, root INTEGER, T_root_map BLOB)``: per map id (a robot's
  first map segment has its id, later segments ids above all robots', see
  :mod:`coop_slam.team.segments`), its group's root map and its map in the root's frame.
- ``acks(robot_id INTEGER PRIMARY KEY, session INTEGER, sequence INTEGER)``: per robot, the
  client session and the highest message sequence stored (what the server acknowledges).

Every input is one transaction (log row, derived rows, acknowledgement), committed before the
server acknowledges it. WAL journal with ``synchronous=NORMAL``: a committed input survives a
crash of the process (kill -9); a power cut may lose the last few.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import sqlite3
import time
import uuid
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from ..camera import CameraModel
from ..errors import CoopSlamError
from ..wire.record import ACTION_REMOVE, ACTION_UPDATE, ARRAY_FIELDS, STATIC_ARRAYS, KeyframeRecord
from .global_ba import GlobalBaError

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
KIND_KEYFRAME, KIND_SIGHTING, KIND_RENDEZVOUS, KIND_GLOBAL_BA = (
    "keyframe",
    "sighting",
    "rendezvous",
    "global_ba",
)
# Rebuilt poses further than this from the stored ones mean the rebuild did not reproduce the
# run (a different server version or configuration): said, not fatal.
_POSE_MISMATCH_M = 1e-6

_RECORD_MAGIC = b"CSKF1"


_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS inputs (
    seq INTEGER PRIMARY KEY, kind TEXT NOT NULL, robot_id INTEGER, keyframe_id INTEGER,
    action INTEGER, stamp_s REAL, payload BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    robot_id INTEGER, keyframe_id INTEGER, map_segment INTEGER, sensor TEXT, stamp_s REAL,
    T_map_cam BLOB, T_group_cam BLOB, PRIMARY KEY (robot_id, keyframe_id));
CREATE TABLE IF NOT EXISTS merges (
    seq INTEGER PRIMARY KEY, type TEXT, robot_a INTEGER, robot_b INTEGER, keyframe_a INTEGER,
    keyframe_b INTEGER, stamp_s REAL, T_mapA_mapB BLOB, inliers INTEGER, residual_px REAL);
CREATE TABLE IF NOT EXISTS constraints (
    seq INTEGER PRIMARY KEY, type TEXT, robot_a INTEGER, keyframe_a INTEGER, robot_b INTEGER,
    keyframe_b INTEGER, stamp_s REAL, T_camA_camB BLOB, inliers INTEGER, residual_px REAL);
CREATE TABLE IF NOT EXISTS groups (robot_id INTEGER PRIMARY KEY, root INTEGER, T_root_map BLOB);
CREATE TABLE IF NOT EXISTS acks (robot_id INTEGER PRIMARY KEY, session INTEGER, sequence INTEGER);
"""


class MapStoreError(CoopSlamError):
    """The map file cannot be created, read or continued (missing, not a coop_slam map, a newer
    schema, corrupt)."""


# --- encoding ---------------------------------------------------------------------------------


def _pose_blob(T: np.ndarray) -> bytes:
    return np.asarray(T, "<f8").reshape(16).tobytes()


def pose_from_blob(blob: bytes) -> np.ndarray:
    return np.frombuffer(blob, "<f8").reshape(4, 4).copy()


def encode_record(rec: KeyframeRecord, omit: tuple[str, ...] = ()) -> bytes:
    """A keyframe record as bytes: ``CSKF1``, a little-endian uint32 header length, a JSON header
    (scalars, camera, per array its name, numpy dtype string and shape, and ``omitted``: arrays
    left out because they equal the previous record of the same keyframe), then each array's raw
    bytes in header order."""
    arrays = [("T_map_cam", np.asarray(rec.T_map_cam, "<f8"))]
    arrays += [(n, np.ascontiguousarray(getattr(rec, n))) for n in ARRAY_FIELDS if n not in omit]
    header = {
        "omitted": list(omit),
        "robot_id": int(rec.robot_id),
        "keyframe_id": int(rec.keyframe_id),
        "stamp_s": float(rec.stamp_s),
        "camera": None if rec.camera is None else rec.camera.to_dict(),  # None: a removal
        "map_segment": int(rec.map_segment),
        "action": int(rec.action),
        "arrays": [[name, a.dtype.str, list(a.shape)] for name, a in arrays],
    }
    head = json.dumps(header).encode()
    return b"".join(
        [_RECORD_MAGIC, len(head).to_bytes(4, "little"), head] + [a.tobytes() for _, a in arrays]
    )


def decode_record(blob: bytes, previous: KeyframeRecord | None = None) -> KeyframeRecord:
    """The record :func:`encode_record` wrote; arrays it omitted come from ``previous`` (the
    record logged before for the same keyframe)."""
    try:
        if blob[: len(_RECORD_MAGIC)] != _RECORD_MAGIC:
            raise ValueError("not a stored keyframe")
        at = len(_RECORD_MAGIC)
        n = int.from_bytes(blob[at : at + 4], "little")
        header = json.loads(blob[at + 4 : at + 4 + n].decode())
        at += 4 + n
        arrays = {}
        for name, dtype, shape in header["arrays"]:
            dt = np.dtype(dtype)
            size = dt.itemsize * int(np.prod(shape, dtype=np.int64))
            if at + size > len(blob):
                raise ValueError(f"{name} is cut short")
            arrays[name] = np.frombuffer(blob, dt, int(np.prod(shape)), at).reshape(shape).copy()
            at += size
        T_map_cam = arrays.pop("T_map_cam").astype(float)
        for name in header.get("omitted", []):
            if previous is None:
                raise ValueError(f"{name} refers to a keyframe logged before, which is missing")
            arrays[name] = getattr(previous, name)
        return KeyframeRecord(
            robot_id=header["robot_id"],
            keyframe_id=header["keyframe_id"],
            stamp_s=header["stamp_s"],
            camera=None if header["camera"] is None else CameraModel(**header["camera"]),
            T_map_cam=T_map_cam,
            map_segment=header["map_segment"],
            action=header["action"],
            **arrays,
        )
    except (ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as exc:
        raise MapStoreError(
            f"a stored keyframe cannot be decoded ({exc}): the map is corrupt"
        ) from exc


def _json_args(**kwargs) -> bytes:
    def plain(v):
        return np.asarray(v).tolist() if isinstance(v, np.ndarray) else v

    return json.dumps({k: plain(v) for k, v in kwargs.items()}).encode()


# --- the store --------------------------------------------------------------------------------


@dataclass
class StoredInput:
    """One logged server input: a keyframe record, or a call's arguments."""

    seq: int
    kind: str
    record: KeyframeRecord | None = None
    args: dict | None = None


@dataclass
class RebuildReport:
    inputs: int
    keyframes: int
    time_s: float
    max_pose_diff_m: float  # rebuilt optimized poses against the stored ones
    remapped: dict[int, int]  # loaded robot id -> id in this server (multi-session)


class MapStore:
    """One map file: open (creating it when new), append inputs, read them back."""

    def __init__(self, path: str, robots: list[int] | None = None, vocabulary_sha256: str = ""):
        self.path = os.path.abspath(path)
        folder = os.path.dirname(self.path)
        if not os.path.isdir(folder):
            raise MapStoreError(f"map file folder does not exist: {folder}")
        new = not os.path.exists(self.path) or os.path.getsize(self.path) == 0
        try:
            self.db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=NORMAL")
            if new:
                self.db.executescript(_SCHEMA)
                self._set_meta(
                    schema_version=str(SCHEMA_VERSION),
                    created_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                    robots=json.dumps(sorted(robots or [])),
                    vocabulary_sha256=vocabulary_sha256,
                )
            meta = self.meta()
        except sqlite3.DatabaseError as exc:
            raise MapStoreError(f"{self.path} is not a coop_slam map file ({exc})") from exc
        version = meta.get("schema_version")
        if version is None:
            raise MapStoreError(f"{self.path} is not a coop_slam map file (no schema_version)")
        if int(version) > SCHEMA_VERSION:
            raise MapStoreError(
                f"{self.path} has map schema {version}; this coop_slam reads up to "
                f"{SCHEMA_VERSION}: update coop_slam"
            )
        self._in_tx = False
        self._written: list[int] | None = None
        self._static: dict[tuple[int, int], bytes] = {}  # digest of what a keyframe saw

    def _set_meta(self, **items) -> None:
        self.db.executemany(
            "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", list(items.items())
        )

    def meta(self) -> dict[str, str]:
        return dict(self.db.execute("SELECT key, value FROM meta"))

    def set_robots(self, robots: list[int]) -> None:
        self._set_meta(robots=json.dumps(sorted(robots)))

    @property
    def robots(self) -> list[int]:
        return json.loads(self.meta().get("robots", "[]"))

    @property
    def map_id(self) -> str:
        """This team map's id (made when first asked: files made before it have none)."""
        map_id = self.meta().get("map_id")
        if not map_id:
            map_id = uuid.uuid4().hex
            self._set_meta(map_id=map_id)
        return map_id

    def close(self) -> None:
        self.db.close()

    # --- writing (one transaction per input) --------------------------------------------------
    def begin(self) -> None:
        self.db.execute("BEGIN IMMEDIATE")
        self._in_tx = True

    def commit(self) -> None:
        self.db.execute("COMMIT")
        self._in_tx = False

    def rollback(self) -> None:
        if self._in_tx:
            self.db.execute("ROLLBACK")
            self._in_tx = False
            self._written = None

    def log_keyframe(self, rec: KeyframeRecord) -> None:
        key = (rec.robot_id, rec.keyframe_id)
        omit: tuple[str, ...] = ()
        if rec.action != ACTION_REMOVE:
            # An update after local BA moves the pose and points; what the camera saw is the
            # same, and is not written again.
            digest = rec.static_digest()
            if rec.action == ACTION_UPDATE and self._static.get(key) == digest:
                omit = STATIC_ARRAYS
            self._static[key] = digest
        self.db.execute(
            "INSERT INTO inputs (kind, robot_id, keyframe_id, action, stamp_s, payload) "
            "VALUES (?, ?, ?, ?, ?, ?)",
            (
                KIND_KEYFRAME,
                rec.robot_id,
                rec.keyframe_id,
                rec.action,
                rec.stamp_s,
                encode_record(rec, omit),
            ),
        )
        if rec.action == ACTION_REMOVE:
            self.db.execute("DELETE FROM keyframes WHERE robot_id=? AND keyframe_id=?", key)
        else:
            self.db.execute(
                "INSERT OR REPLACE INTO keyframes (robot_id, keyframe_id, map_segment, sensor, "
                "stamp_s, T_map_cam) VALUES (?, ?, ?, ?, ?, ?)",
                (*key, rec.map_segment, rec.camera.sensor, rec.stamp_s, _pose_blob(rec.T_map_cam)),
            )

    def log_call(self, kind: str, **args) -> None:
        """A sighting, rendezvous request (``robot_a``, ``robot_b``, ``stamp_s``,
        ``T_camA_bodyB``, ``T_body_cam``) or global-BA request (``robot_id``), as JSON."""
        self.db.execute(
            "INSERT INTO inputs (kind, robot_id, stamp_s, payload) VALUES (?, ?, ?, ?)",
            (
                kind,
                args.get("robot_a", args.get("robot_id")),
                args.get("stamp_s"),
                _json_args(**args),
            ),
        )

    def write_state(self, server, keys: list[tuple[int, int]] | None = None) -> None:
        """The derived tables from the server's state: merges and constraints not yet written,
        groups, and the optimized poses of the keyframes ``keys`` (default: all; after an
        optimization every pose may have moved, else only the keyframe just taken)."""
        if self._written is None:  # merges and constraints in the file
            self._written = [
                self.db.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0]
                for t in ("merges", "constraints")
            ]
        n_merges, n_constraints = self._written
        self._written = [len(server.merges), len(server.constraints)]
        for m in server.merges[n_merges:]:
            self.db.execute(
                "INSERT INTO merges (type, robot_a, robot_b, keyframe_a, keyframe_b, stamp_s, "
                "T_mapA_mapB, inliers, residual_px) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    m.type,
                    m.map_a,
                    m.map_b,
                    m.keyframe_a,
                    m.keyframe_b,
                    m.stamp_s,
                    _pose_blob(m.T_mapA_mapB),
                    m.inliers,
                    m.residual_px,
                ),
            )
        for c in server.constraints[n_constraints:]:
            self.db.execute(
                "INSERT INTO constraints (type, robot_a, keyframe_a, robot_b, keyframe_b, "
                "stamp_s, T_camA_camB, inliers, residual_px) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    c.type,
                    *c.key_a,
                    *c.key_b,
                    c.stamp_s,
                    _pose_blob(c.T_camA_camB),
                    c.inliers,
                    c.residual_px,
                ),
            )
        if keys is None or len(server.merges) > n_merges:  # groups and map transforms moved
            self.db.executemany(
                "INSERT OR REPLACE INTO groups (robot_id, root, T_root_map) VALUES (?, ?, ?)",
                [
                    (m, server.groups.root(m), _pose_blob(server.T_group_map(m)))
                    for m in server.groups.robots
                ],
            )
        if keys is None:
            keys = server.store.keys()
        rows = [
            (_pose_blob(server.T_group_cam(*key)), server.robot_of(key[0]), key[1])
            for key in keys
            if key in server.store
        ]
        self.db.executemany(
            "UPDATE keyframes SET T_group_cam=? WHERE robot_id=? AND keyframe_id=?", rows
        )

    def set_ack(self, robot_id: int, session: int, sequence: int) -> None:
        self.db.execute(
            "INSERT OR REPLACE INTO acks (robot_id, session, sequence) VALUES (?, ?, ?)",
            (robot_id, session, sequence),
        )

    # --- reading ------------------------------------------------------------------------------
    def acks(self) -> dict[int, tuple[int, int]]:
        """robot id -> (session, highest sequence stored)."""
        return {r: (s, q) for r, s, q in self.db.execute("SELECT * FROM acks")}

    def logged_keyframes(self) -> dict[int, tuple[set[int], int]]:
        """robot id -> (ids of every keyframe ever logged for it, culled ones included; highest
        map segment of its stored keyframes)."""
        out: dict[int, tuple[set[int], int]] = {}
        for r, kf in self.db.execute(
            "SELECT DISTINCT robot_id, keyframe_id FROM inputs WHERE kind=?", (KIND_KEYFRAME,)
        ):
            out.setdefault(int(r), (set(), 0))[0].add(int(kf))
        for r, seg in self.db.execute(
            "SELECT robot_id, MAX(map_segment) FROM keyframes GROUP BY robot_id"
        ):
            if int(r) in out:
                out[int(r)] = (out[int(r)][0], int(seg or 0))
        return out

    def count_inputs(self) -> int:
        return self.db.execute("SELECT COUNT(*) FROM inputs").fetchone()[0]

    def inputs(self) -> Iterator[StoredInput]:
        last: dict[tuple[int, int], KeyframeRecord] = {}  # for updates that omit arrays
        for seq, kind, key, payload in self.db.execute(
            "SELECT seq, kind, robot_id || ':' || keyframe_id, payload FROM inputs ORDER BY seq"
        ):
            if kind == KIND_KEYFRAME:
                rec = decode_record(payload, last.get(key))
                last[key] = rec
                # A copy: whoever takes the record may change it (a rebuild remaps robot ids).
                yield StoredInput(seq, kind, record=dataclasses.replace(rec))
            elif kind in (KIND_SIGHTING, KIND_RENDEZVOUS, KIND_GLOBAL_BA):
                yield StoredInput(seq, kind, args=json.loads(payload.decode()))
            else:
                raise MapStoreError(f"input {seq} of {self.path} has unknown kind '{kind}'")

    def stored_poses(self) -> dict[tuple[int, int, int], np.ndarray]:
        """(robot, map segment, keyframe) -> optimized pose as last written."""
        return {
            (r, s, k): pose_from_blob(b)
            for r, s, k, b in self.db.execute(
                "SELECT robot_id, map_segment, keyframe_id, T_group_cam FROM keyframes "
                "WHERE T_group_cam IS NOT NULL"
            )
        }

    def save_copy(self, path: str) -> None:
        """A self-contained copy of the map (consistent even while the server writes)."""
        path = os.path.abspath(path)
        if path == self.path:
            raise MapStoreError(f"cannot save the map onto its own live file {path}")
        folder = os.path.dirname(path)
        if not os.path.isdir(folder):
            raise MapStoreError(f"folder does not exist: {folder}")
        tmp = path + ".part"
        try:
            dest = sqlite3.connect(tmp)
            with dest:
                self.db.backup(dest)
            dest.execute("PRAGMA journal_mode=DELETE")  # one file, no -wal beside it
            dest.close()
            os.replace(tmp, path)  # a reader never sees a half-written map
        except (sqlite3.Error, OSError) as exc:
            raise MapStoreError(f"cannot write map file {path}: {exc}") from exc


def remove_map_file(path: str) -> None:
    """Delete a (closed) map file with the WAL files SQLite keeps beside it."""
    for name in (path, path + "-wal", path + "-shm"):
        if os.path.exists(name):
            os.remove(name)


def apply_input(server, item: StoredInput) -> None:
    """Feed one logged input to the server core, as the server node did when it was taken."""
    if item.kind == KIND_KEYFRAME:
        server.add_keyframe(item.record)
        return
    a = item.args

    def matrix(name):
        v = a.get(name)
        return None if v is None else np.asarray(v, float)

    if item.kind == KIND_SIGHTING:
        server.sighting(
            a["robot_a"], a["robot_b"], a["stamp_s"], matrix("T_camA_bodyB"), matrix("T_body_cam")
        )
    elif item.kind == KIND_RENDEZVOUS:
        server.request_rendezvous(
            a["robot_a"], a["robot_b"], a["stamp_s"], matrix("T_camA_bodyB"), matrix("T_body_cam")
        )
    elif item.kind == KIND_GLOBAL_BA:
        try:
            server.global_bundle_adjustment(a.get("robot_id"))
        except GlobalBaError:
            pass  # refused then too


def remap_input(item: StoredInput, remap: dict[int, int]) -> StoredInput:
    """A logged input with loaded robots' ids replaced (multi-session: no id collisions)."""
    if not remap:
        return item
    if item.record is not None:
        item.record.robot_id = remap.get(item.record.robot_id, item.record.robot_id)
    elif item.args is not None:
        for k in ("robot_a", "robot_b", "robot_id"):
            if item.args.get(k) is not None:
                item.args[k] = remap.get(item.args[k], item.args[k])
    return item


def collision_free_ids(loaded: list[int], active: list[int]) -> dict[int, int]:
    """Loaded robot id -> the id it gets beside the active robots: kept unless an active robot
    has it, then the smallest id free in both."""
    taken = set(active) | set(loaded)
    remap = {}
    for r in sorted(loaded):
        if r in active:
            new = 1
            while new in taken:
                new += 1
            taken.add(new)
            remap[r] = new
    return remap


def rebuild(
    source: MapStore,
    server,
    target: MapStore | None = None,
    remap: dict[int, int] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> RebuildReport:
    """Feed every input logged in ``source`` to ``server`` (a fresh TeamServer that knows the
    source's robots, remapped); when ``target`` is another store (loading a map into a new
    session), the inputs are logged there as well. Returns counts and the largest difference
    between rebuilt and stored optimized poses."""
    t0 = time.perf_counter()
    remap = remap or {}
    total = source.count_inputs()
    n = 0
    copy = target is not None and target is not source
    if copy:
        target.begin()
    try:
        for item in source.inputs():
            item = remap_input(item, remap)
            try:
                apply_input(server, item)
            except CoopSlamError as exc:
                log.warning(
                    "map rebuild: input %d (%s) refused again: %s", item.seq, item.kind, exc
                )
            if copy:
                if item.record is not None:
                    target.log_keyframe(item.record)
                else:
                    target.log_call(item.kind, **item.args)
            n += 1
            if progress is not None and (n % 50 == 0 or n == total):
                progress(n, total)
        if copy:
            target.write_state(server)
            target.commit()
    except BaseException:
        if copy:
            target.rollback()
        raise
    diff = 0.0
    if not remap:
        for (r, seg, k), T in source.stored_poses().items():
            mid = server.segments.find(r, seg)
            if mid is not None and (mid, k) in server.store:
                diff = max(
                    diff, float(np.linalg.norm(server.T_group_cam(mid, k)[:3, 3] - T[:3, 3]))
                )
        if diff > _POSE_MISMATCH_M:
            log.warning(
                "map rebuild: rebuilt poses differ from the stored ones by up to %.3f m (map "
                "written by another coop_slam version or server configuration?)",
                diff,
            )
    kfs = len(server.store)
    return RebuildReport(n, kfs, time.perf_counter() - t0, diff, remap)
