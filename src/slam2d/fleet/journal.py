"""The map server's durable state: one SQLite file in WAL mode, one transaction per accepted delta.

What is stored is what cannot be recomputed: each drone's claim (session token, dock pose), its committed
keyframes (drone-frame pose, descriptor, compact points) and edges, the sequence number and content digest of every
committed delta, and the inter-robot loop closures the server accepted. The merged poses are not stored: a
restarted server rebuilds the joint graph from these rows and optimises it again.

A commit is in the WAL file when it returns and the server acknowledges a delta only after its commit, so an
acknowledged delta survives ``kill -9`` of the server (the process dies, the OS keeps the written file).
``synchronous=NORMAL`` (WAL fsynced at checkpoints, not per commit): a power cut may lose the last commits;
``Journal(path, durable=True)`` (``synchronous=FULL``) survives that too, at an fsync per delta (measured 8 ms per
commit on the loaded test machine, the server's largest cost).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam2d.fleet.protocol import Delta, Edge, Keyframe

APPLICATION_ID = int.from_bytes(b"S2DF", "big")
SCHEMA_VERSION = 2  # 2: floor-marker sightings of keyframes (a version-1 file gains the table when opened)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS drones (drone INTEGER PRIMARY KEY, session TEXT NOT NULL, x REAL NOT NULL,
                                   y REAL NOT NULL, theta REAL NOT NULL);
CREATE TABLE IF NOT EXISTS deltas (drone INTEGER NOT NULL, seq INTEGER NOT NULL, digest TEXT NOT NULL,
                                   PRIMARY KEY (drone, seq));
CREATE TABLE IF NOT EXISTS keyframes (drone INTEGER NOT NULL, id INTEGER NOT NULL, stamp REAL NOT NULL,
                                      x REAL NOT NULL, y REAL NOT NULL, theta REAL NOT NULL, descriptor BLOB NOT NULL,
                                      points BLOB NOT NULL, PRIMARY KEY (drone, id));
CREATE TABLE IF NOT EXISTS keyframe_markers (drone INTEGER NOT NULL, id INTEGER NOT NULL, markers BLOB NOT NULL,
                                             PRIMARY KEY (drone, id));
CREATE TABLE IF NOT EXISTS edges (drone INTEGER NOT NULL, a INTEGER NOT NULL, b INTEGER NOT NULL, dx REAL NOT NULL,
                                  dy REAL NOT NULL, dtheta REAL NOT NULL, information BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS loops (id INTEGER PRIMARY KEY, drone_a INTEGER NOT NULL, a INTEGER NOT NULL,
                                  drone_b INTEGER NOT NULL, b INTEGER NOT NULL, dx REAL NOT NULL, dy REAL NOT NULL,
                                  dtheta REAL NOT NULL, information BLOB NOT NULL, stamp REAL NOT NULL);
"""


class JournalError(ValueError):
    """The file is not a fleet journal (or a newer one), is corrupt, or cannot be opened for writing."""


def _why(e: sqlite3.Error, existed: bool) -> str:
    text = str(e).lower()
    if "readonly" in text or "read-only" in text:
        return "cannot write the fleet map database (read-only file or directory)"
    if not existed:
        return "cannot create the fleet map database there"
    if isinstance(e, sqlite3.DatabaseError) and ("malformed" in text or "not a database" in text):
        return "not a fleet map database, or a corrupt one"
    return "cannot open the fleet map database"


@dataclass(frozen=True)
class DroneRow:
    drone: int
    session: str
    dock: np.ndarray
    acked_seq: int
    keyframes: int


@dataclass(frozen=True)
class LoopRow:
    drone_a: int
    a: int
    drone_b: int
    b: int
    z: np.ndarray
    info: np.ndarray  # (3, 3)
    stamp: float


class Journal:
    """Open (or create) the fleet journal at ``path``."""

    def __init__(self, path: str | Path, *, durable: bool = False) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise IsADirectoryError(21, "is a directory, not a map database", str(self.path))
        existed = self.path.exists()
        con: sqlite3.Connection | None = None
        try:
            self.db = con = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            app = self.db.execute("PRAGMA application_id").fetchone()[0]
            ver = self.db.execute("PRAGMA user_version").fetchone()[0]
            tables = self.db.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]
            if tables and app != APPLICATION_ID:
                raise JournalError(f"{self.path}: an SQLite file that is not a fleet map database (application_id "
                                   f"{app:#x}); give a new path")
            if ver > SCHEMA_VERSION:
                raise JournalError(f"{self.path}: fleet schema {ver} is newer than this slam2d ({SCHEMA_VERSION})")
            # a torn or damaged file fails here, at start, not on the first delta that reads the damaged page
            check = self.db.execute("PRAGMA quick_check(3)").fetchall() if tables else [("ok",)]
            if check != [("ok",)]:
                found = "; ".join(" ".join(str(r[0]).split()) for r in check)
                raise JournalError(f"{self.path}: corrupt fleet map database (integrity check: {found}); restore a "
                                   "copy or give a new path")
            # only now switch to WAL: the switch is stored in the file, and a refused file must be left as it was
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute(f"PRAGMA synchronous={'FULL' if durable else 'NORMAL'}")
            with self.transaction():
                for statement in _SCHEMA.split(";"):
                    if statement.strip():
                        self.db.execute(statement)
                self.db.execute(f"PRAGMA application_id={APPLICATION_ID}")
                self.db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        except (sqlite3.Error, JournalError) as e:
            if con is not None:
                con.close()
            if isinstance(e, JournalError):
                raise
            raise JournalError(f"{self.path}: {_why(e, existed)} ({e})") from None

    def close(self) -> None:
        self.db.close()

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        self.db.execute("BEGIN IMMEDIATE")
        try:
            yield self.db
        except BaseException:
            self.db.execute("ROLLBACK")
            raise
        self.db.execute("COMMIT")

    # ------------------------------------------------------------------ reads
    def drones(self) -> list[DroneRow]:
        rows = self.db.execute(
            "SELECT d.drone, d.session, d.x, d.y, d.theta, "
            "(SELECT coalesce(max(seq), 0) FROM deltas WHERE drone = d.drone), "
            "(SELECT count(*) FROM keyframes WHERE drone = d.drone) FROM drones d ORDER BY d.drone").fetchall()
        return [DroneRow(r[0], r[1], np.array(r[2:5]), r[5], r[6]) for r in rows]

    def digest(self, drone: int, seq: int) -> str | None:
        r = self.db.execute("SELECT digest FROM deltas WHERE drone=? AND seq=?", (drone, seq)).fetchone()
        return None if r is None else str(r[0])

    def keyframes(self, drone: int) -> list[Keyframe]:
        rows = self.db.execute("SELECT k.id, k.stamp, k.x, k.y, k.theta, k.descriptor, k.points, m.markers FROM "
                               "keyframes k LEFT JOIN keyframe_markers m ON m.drone = k.drone AND m.id = k.id "
                               "WHERE k.drone=? ORDER BY k.id", (drone,)).fetchall()
        return [Keyframe(r[0], r[1], np.array(r[2:5]), bytes(r[5]), bytes(r[6]), bytes(r[7] or b""))
                for r in rows]

    def edges(self, drone: int) -> list[Edge]:
        rows = self.db.execute("SELECT a, b, dx, dy, dtheta, information FROM edges WHERE drone=? ORDER BY rowid",
                               (drone,)).fetchall()
        return [Edge(r[0], r[1], np.array(r[2:5]), np.frombuffer(r[5], "<f8").copy()) for r in rows]

    def loops(self) -> list[LoopRow]:
        rows = self.db.execute("SELECT drone_a, a, drone_b, b, dx, dy, dtheta, information, stamp FROM loops "
                               "ORDER BY id").fetchall()
        return [LoopRow(r[0], r[1], r[2], r[3], np.array(r[4:7]), np.frombuffer(r[7], "<f8").reshape(3, 3).copy(),
                        r[8]) for r in rows]

    def count(self, table: str) -> int:
        assert table in ("drones", "deltas", "keyframes", "keyframe_markers", "edges", "loops")
        return int(self.db.execute(f"SELECT count(*) FROM {table}").fetchone()[0])

    # ------------------------------------------------------------------ writes (one transaction each)
    def claim(self, drone: int, session: str, dock: np.ndarray) -> None:
        with self.transaction() as db:
            db.execute("INSERT INTO drones VALUES (?, ?, ?, ?, ?)", (drone, session, *map(float, dock)))

    def commit_delta(self, d: Delta) -> None:
        with self.transaction() as db:
            db.execute("INSERT INTO deltas VALUES (?, ?, ?)", (d.drone, d.seq, d.digest))
            db.executemany("INSERT INTO keyframes VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                           [(d.drone, k.id, k.stamp, *map(float, k.pose), k.desc, k.pts) for k in d.keyframes])
            db.executemany("INSERT INTO keyframe_markers VALUES (?, ?, ?)",
                           [(d.drone, k.id, k.mk) for k in d.keyframes if k.mk])
            db.executemany("INSERT INTO edges VALUES (?, ?, ?, ?, ?, ?, ?)",
                           [(d.drone, e.a, e.b, *map(float, e.z), np.asarray(e.info, "<f8").tobytes())
                            for e in d.edges])

    def add_loops(self, loops: list[LoopRow]) -> None:
        with self.transaction() as db:
            db.executemany("INSERT INTO loops (drone_a, a, drone_b, b, dx, dy, dtheta, information, stamp) "
                           "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           [(lp.drone_a, lp.a, lp.drone_b, lp.b, *map(float, lp.z),
                             np.asarray(lp.info, "<f8").tobytes(), lp.stamp) for lp in loops])
