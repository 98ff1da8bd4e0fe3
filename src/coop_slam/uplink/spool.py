"""A client's spool: the keyframe messages it numbered and the server has not acknowledged yet,
on the robot's own disk, so that a killed client loses none of them: the restarted client sends
them first (:class:`coop_slam.uplink.engine.ClientUplink`).

One SQLite file per robot (default ``$ROS_HOME/coop_slam/robot_<k>/spool.db``), in WAL mode with
``synchronous=NORMAL`` as the team map file: one transaction per message numbered (written before
it is published) and per acknowledgement; a committed row survives a kill -9 of the process, a
power cut may lose the last few. Schema (``SCHEMA_VERSION`` 1):

- ``meta(key TEXT PRIMARY KEY, value TEXT)``: ``schema_version``, ``robot_id``, ``format`` (the
  serialization of the payloads: a spool of another message version is not decoded), ``session``
  and ``last_sequence`` (the last message numbered), ``max_keyframe_id`` and ``max_map_segment``
  (the highest this robot ever sent: a restarted client continues above them), ``map_id`` (the
  server's team map the messages were made for).
- ``messages(session, sequence, keyframe_id, map_segment, new_keyframe, created_s, payload BLOB,
  PRIMARY KEY(session, sequence))``: the messages as serialized, numbered in ``session``.

A file that cannot be continued (another robot's, another format, another map) is set aside:
renamed ``<file>.stale-<time>``, never decoded nor deleted. An exclusive lock on
``<file>.lock``, held while the spool is open (the kernel drops it when the process dies), keeps
two clients of one robot from sharing a spool.
"""

from __future__ import annotations

import fcntl
import os
import sqlite3
import time
from dataclasses import dataclass, field

from ..config import require
from ..errors import CoopSlamError

SCHEMA_VERSION = 1
SPOOL_OFF = "off"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS messages (
    session INTEGER, sequence INTEGER, keyframe_id INTEGER, map_segment INTEGER,
    new_keyframe INTEGER, created_s REAL, payload BLOB NOT NULL,
    PRIMARY KEY (session, sequence));
"""


class SpoolError(CoopSlamError):
    """The spool cannot be opened or written (a folder that cannot be made, a file another client
    holds, a full disk, a corrupt file)."""


def default_spool_path(robot_id: int) -> str:
    """``$ROS_HOME/coop_slam/robot_<k>/spool.db`` (``$ROS_HOME``: ``~/.ros`` by default)."""
    home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    return os.path.join(home, "coop_slam", f"robot_{robot_id}", "spool.db")


@dataclass
class SpoolConfig:
    """Where a client keeps what the server has not acknowledged (client parameters ``~spool``,
    ``~spool_max_mb``)."""

    path: str = ""  # the file; "" = default_spool_path(robot id); "off" = none (kept in memory)
    max_mb: float = 200.0  # beyond this the newest messages are refused [MB of payload]

    def validate(self) -> None:
        require(self.max_mb > 0, f"spool_max_mb must be > 0 [MB], got {self.max_mb}")

    @property
    def off(self) -> bool:
        return self.path.strip() == SPOOL_OFF

    def file(self, robot_id: int) -> str:
        return os.path.abspath(
            os.path.expanduser(self.path.strip() or default_spool_path(robot_id))
        )


@dataclass
class SpooledMessage:
    """One message kept: its numbers, what it is about, and its serialized bytes."""

    session: int
    sequence: int
    keyframe_id: int
    map_segment: int
    new_keyframe: bool
    payload: bytes


@dataclass
class SpoolState:
    """What a spool holds when opened."""

    session: int = 0  # of the last message numbered (0: none ever)
    last_sequence: int = 0
    messages: list[SpooledMessage] = field(default_factory=list)  # in sequence order
    max_keyframe_id: int = 0  # the highest ever kept (0: none)
    max_map_segment: int = -1  # (-1: none)
    map_id: str = ""  # the team map they were made for ("" = not known)


class Spool:
    """One robot's spool file, open and locked. ``format_id`` names the payloads' serialization;
    ``max_bytes`` bounds the payloads kept (:meth:`fits`)."""

    def __init__(self, path: str, robot_id: int, format_id: str, max_bytes: int):
        self.path, self.robot_id, self.format_id = path, int(robot_id), format_id
        self.max_bytes = int(max_bytes)
        self.set_aside_as: list[tuple[str, str]] = []  # (new path, why): files set aside
        folder = os.path.dirname(path)
        try:
            os.makedirs(folder, exist_ok=True)
            self._lock_fh = open(path + ".lock", "a+")
        except OSError as exc:
            raise SpoolError(f"cannot make the spool {path}: {exc} (set ~spool)") from exc
        try:
            fcntl.flock(self._lock_fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._lock_fh.close()
            raise SpoolError(
                f"spool {path} is in use by another process (a second client of robot "
                f"{robot_id}?): give each client its own robot_id, or its own ~spool"
            ) from None
        self._lock_fh.seek(0)
        self._lock_fh.truncate()
        self._lock_fh.write(f"{os.getpid()}\n")
        self._lock_fh.flush()
        self.db: sqlite3.Connection | None = None
        self._open()
        why = self._foreign()
        if why:
            self.set_aside(why)

    # --- opening ----------------------------------------------------------------------------------
    def _open(self) -> None:
        try:
            self.db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=NORMAL")
            self.db.executescript(_SCHEMA)
            meta = self.meta()
            if "schema_version" not in meta:
                self._set_meta(
                    schema_version=SCHEMA_VERSION, robot_id=self.robot_id, format=self.format_id
                )
            self.count, self.bytes = self.db.execute(
                "SELECT COUNT(*), COALESCE(SUM(LENGTH(payload)), 0) FROM messages"
            ).fetchone()
        except sqlite3.DatabaseError as exc:
            self._close_db()
            self._rename_aside(f"not a readable spool ({exc})")
            self._open()

    def _foreign(self) -> str:
        """Why the open file cannot be continued by this client ("" = it can)."""
        meta = self.meta()
        if int(meta.get("schema_version", 0)) > SCHEMA_VERSION:
            return f"spool schema {meta['schema_version']} is newer than this coop_slam's"
        if int(meta.get("robot_id", self.robot_id)) != self.robot_id:
            return f"it is robot {meta['robot_id']}'s"
        if meta.get("format", self.format_id) != self.format_id:
            return f"its messages are of another version ({meta['format']})"
        return ""

    def set_aside(self, why: str) -> str:
        """Rename the file (``<file>.stale-<time>``) and start an empty one; returns the new
        name. Its messages are never sent."""
        self._close_db()
        aside = self._rename_aside(why)
        self._open()
        return aside

    def _rename_aside(self, why: str) -> str:
        aside = f"{self.path}.stale-{time.strftime('%Y%m%d-%H%M%S')}"
        n = 1
        while os.path.exists(aside):
            aside, n = f"{self.path}.stale-{time.strftime('%Y%m%d-%H%M%S')}-{n}", n + 1
        try:
            for suffix in ("", "-wal", "-shm"):
                if os.path.exists(self.path + suffix):
                    os.replace(self.path + suffix, aside + suffix)
        except OSError as exc:
            raise SpoolError(f"cannot set the spool {self.path} aside ({why}): {exc}") from exc
        self.set_aside_as.append((aside, why))
        return aside

    def _close_db(self) -> None:
        if self.db is not None:
            self.db.close()
            self.db = None

    def close(self) -> None:
        self._close_db()
        self._lock_fh.close()  # releases the lock

    # --- reading ----------------------------------------------------------------------------------
    def meta(self) -> dict[str, str]:
        return dict(self.db.execute("SELECT key, value FROM meta"))

    def _set_meta(self, **items) -> None:
        self.db.executemany(
            "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
            [(k, str(v)) for k, v in items.items()],
        )

    def load(self) -> SpoolState:
        meta = self.meta()
        rows = self.db.execute(
            "SELECT session, sequence, keyframe_id, map_segment, new_keyframe, payload "
            "FROM messages ORDER BY session, sequence"
        ).fetchall()
        return SpoolState(
            session=int(meta.get("session", 0)),
            last_sequence=int(meta.get("last_sequence", 0)),
            messages=[
                SpooledMessage(int(s), int(q), int(k), int(g), bool(n), bytes(p))
                for s, q, k, g, n, p in rows
            ],
            max_keyframe_id=int(meta.get("max_keyframe_id", 0)),
            max_map_segment=int(meta.get("max_map_segment", -1)),
            map_id=meta.get("map_id", ""),
        )

    def fits(self, payload_bytes: int) -> bool:
        """A message of this size fits within ``max_bytes`` (any fits an empty spool: it would
        never fit otherwise)."""
        return self.count == 0 or self.bytes + payload_bytes <= self.max_bytes

    # --- writing (one transaction each) -----------------------------------------------------------
    def _write(self, what: str, fn):
        try:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                out = fn()
            except BaseException:
                self.db.execute("ROLLBACK")
                raise
            self.db.execute("COMMIT")
            return out
        except sqlite3.Error as exc:
            raise SpoolError(f"spool {self.path}: cannot {what}: {exc} (disk full?)") from exc

    def append(self, m: SpooledMessage) -> None:
        """Keep a message just numbered (committed before it is published)."""
        meta = self.meta()

        def write():
            self.db.execute(
                "INSERT INTO messages VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    m.session,
                    m.sequence,
                    m.keyframe_id,
                    m.map_segment,
                    int(m.new_keyframe),
                    time.time(),
                    sqlite3.Binary(m.payload),
                ),
            )
            self._set_meta(
                session=m.session,
                last_sequence=m.sequence,
                max_keyframe_id=max(int(meta.get("max_keyframe_id", 0)), m.keyframe_id),
                max_map_segment=max(int(meta.get("max_map_segment", -1)), m.map_segment),
            )

        self._write("keep a message", write)
        self.count += 1
        self.bytes += len(m.payload)

    def ack(self, session: int, sequence: int) -> int:
        """The server stored ``session``'s messages up to ``sequence``: delete them; returns
        how many."""

        def delete():
            row = self.db.execute(
                "SELECT COUNT(*), COALESCE(SUM(LENGTH(payload)), 0) FROM messages "
                "WHERE session=? AND sequence<=?",
                (session, sequence),
            ).fetchone()
            self.db.execute(
                "DELETE FROM messages WHERE session=? AND sequence<=?", (session, sequence)
            )
            return row

        n, size = self._write("delete acknowledged messages", delete) if self.count else (0, 0)
        self.count -= n
        self.bytes -= size
        return n

    def renumber(self, session: int) -> None:
        """Number every message kept anew, 1, 2, ... in ``session``, in their order."""

        def write():
            rows = self.db.execute(
                "SELECT session, sequence FROM messages ORDER BY session, sequence"
            ).fetchall()
            self.db.execute("UPDATE messages SET session=-session, sequence=-sequence")
            self.db.executemany(
                "UPDATE messages SET session=?, sequence=? WHERE session=? AND sequence=?",
                [(session, i + 1, -s, -q) for i, (s, q) in enumerate(rows)],
            )
            self._set_meta(session=session, last_sequence=len(rows))

        self._write("number the messages anew", write)

    def new_map(self, map_id: str) -> None:
        """The server's team map is another than the one the spool knew: the highest ids sent
        there say nothing about this one (only those of what is kept now count)."""

        def write():
            top_kf, top_seg = self.db.execute(
                "SELECT MAX(keyframe_id), MAX(map_segment) FROM messages"
            ).fetchone()
            self._set_meta(
                map_id=map_id,
                max_keyframe_id=top_kf or 0,
                max_map_segment=-1 if top_seg is None else top_seg,
            )

        self._write("note the map", write)

    def set_map_id(self, map_id: str) -> None:
        """The team map the messages are made for (from now on)."""
        if map_id and self.meta().get("map_id") != map_id:
            self._write("note the map", lambda: self._set_meta(map_id=map_id))
