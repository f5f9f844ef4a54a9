"""The map server against hostile or broken input that used to kill it: finite but absurd numbers in a delta,
keyframes no edge ties to the graph, a numerically singular joint solve, and a journal that is corrupt or
read-only at start. Every refusal is an error reply to the sender; the server (and a restart on its file) goes on."""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slam2d.fleet.joint import JointGraph
from slam2d.fleet.journal import Journal, JournalError
from slam2d.fleet.protocol import (
    Delta,
    Edge,
    Keyframe,
    decode,
    encode,
    info_upper,
    pack_descriptor,
    pack_markers,
    pack_points,
)
from slam2d.fleet.server import MapServer

A = b"conn-a"
INFO = info_upper(np.diag([100.0, 100.0, 400.0]))


def _kf(k: int, pose: list[float] | None = None) -> dict[str, Any]:
    pts = np.random.default_rng(k).uniform(-5, 5, (60, 2))
    return {"id": k, "stamp": float(k), "pose": pose or [float(k), 0.0, 0.0],
            "desc": pack_descriptor(np.full(17, 1 / 17)), "pts": pack_points(pts)}


def _delta(seq: int, kfs: list[dict[str, Any]], edges: list[dict[str, Any]]) -> bytes:
    return encode({"type": "delta", "drone": 0, "seq": seq, "keyframes": kfs, "edges": edges})


def _chain(first: int, n: int, z: list[float] | None = None, info: list[float] | None = None) -> list[dict[str, Any]]:
    return [{"a": k - 1, "b": k, "z": z or [1.0, 0.0, 0.0], "info": info or INFO}
            for k in range(max(first, 1), first + n)]


def _server(path: Path) -> MapServer:
    s = MapServer(path)
    assert decode(s.handle(A, encode({"type": "hello", "drone": 0, "session": "s", "dock": [0.0, 0.0, 0.0]})))[
        "type"] == "welcome"
    return s


def _rows(s: MapServer) -> tuple[int, ...]:
    return tuple(s.journal.count(t) for t in ("deltas", "keyframes", "edges"))


def _refused_and_alive(tmp_path: Path, bad: bytes, code: str = "garbled") -> None:
    """``bad`` (delta 1 of drone 0) is refused with ``code`` and writes nothing; a good delta 1 is then acknowledged
    and a restart on the file works."""
    s = _server(tmp_path / "m.db")
    before = _rows(s)
    reply = decode(s.handle(A, bad))
    assert reply["type"] == "error" and reply["code"] == code and reply["message"], reply
    assert _rows(s) == before
    good = decode(s.handle(A, _delta(1, [_kf(k) for k in range(60)], _chain(0, 60))))
    assert good["type"] == "ack" and not good["duplicate"]
    s.close()
    MapServer(tmp_path / "m.db").close()


@pytest.mark.parametrize("where", ["pose", "z", "theta"])
def test_absurd_but_finite_numbers_are_refused_before_the_commit(tmp_path: Path, where: str) -> None:
    """A pose of 1e308 used to overflow the graph after the commit: OverflowError out of the server, and the same
    on every restart on its journal."""
    kfs = [_kf(0), _kf(1)]
    edges = _chain(0, 2)
    if where == "pose":
        kfs[0]["pose"] = [1e308, 1e308, 0.0]
    elif where == "z":
        kfs.append(_kf(2))
        edges = _chain(0, 3, z=[1e308, 0.0, 0.0])
    else:
        kfs[0]["pose"] = [0.0, 0.0, 1e300]
    _refused_and_alive(tmp_path, _delta(1, kfs, edges))


@pytest.mark.parametrize("info", [[1e308, 0, 0, 1e308, 0, 1e308],  # the solve overflowed (non-finite step)
                                  [1e-300, 0, 0, 1e-300, 0, 1.0],  # the graph refused it as singular
                                  [1e10, 1e10 - 1e-3, 0, 1e10, 0, 1.0]])  # ill-conditioned: the same
def test_edge_information_the_joint_solve_cannot_take_is_refused(tmp_path: Path, info: list[float]) -> None:
    """60 keyframes make a solve due in the same delta: these informations crashed it (after the commit)."""
    _refused_and_alive(tmp_path, _delta(1, [_kf(k) for k in range(60)], _chain(0, 60, info=info)))


def test_a_keyframe_without_an_edge_is_refused(tmp_path: Path) -> None:
    """Keyframes no edge reaches are unconstrained: the next whole-graph solve failed (H singular), killing the
    server and every restart on its journal."""
    _refused_and_alive(tmp_path, _delta(1, [_kf(k) for k in range(60)], _chain(0, 30)), "unlinked-keyframe")


def test_a_solve_that_cannot_factor_leaves_the_estimate_and_the_server_alive(tmp_path: Path) -> None:
    """Defence in depth (and journals written before the checks above): a keyframe tied to the graph only by a
    floor-marker reading keeps its heading free, the Gauss-Newton system is singular; the solve falls back instead
    of raising, and a server restarts on such a file."""
    g = JointGraph()
    g.add_drone(0, np.zeros(3))
    mk = pack_markers(np.array([5]), np.array([[1.0, 0.0]]), np.array([0.01]))
    kfs = [Keyframe(k, float(k), np.array([float(k), 0.0, 0.0]), pack_descriptor(np.full(17, 1 / 17)),
                    pack_points(np.zeros((30, 2))), mk) for k in range(3)]
    g.add_keyframes(0, kfs, [])
    g.solve()  # raised SolverError
    assert np.all(np.isfinite(g.poses))
    j = Journal(tmp_path / "old.db")
    j.claim(0, "s", np.zeros(3))
    j.commit_delta(Delta(0, 1, tuple(kfs), (Edge(0, 1, np.array([1.0, 0, 0]), np.asarray(INFO)),), "x"))
    j.close()
    s = MapServer(tmp_path / "old.db")  # raised SolverError at start
    assert s.drones[0].keyframes == 3
    assert decode(s.handle(A, encode({"type": "hello", "drone": 0, "session": "s", "dock": [0, 0, 0]})))[
        "acked_seq"] == 1
    s.close()


def _journal_with_data(path: Path) -> int:
    s = _server(path)
    for seq in range(1, 30):
        assert decode(s.handle(A, _delta(seq, [_kf(k) for k in range(5 * seq - 5, 5 * seq)],
                                         _chain(5 * seq - 5, 5))))["type"] == "ack"
    s.close()
    return path.stat().st_size


def test_a_torn_or_damaged_journal_is_a_clear_error_at_start(tmp_path: Path) -> None:
    """A journal cut inside its last page used to start and then raise GraphError from the garbage rows (or a bare
    sqlite3.DatabaseError, the CLI's 'internal error', as one with damaged pages did)."""
    db = tmp_path / "m.db"
    size = _journal_with_data(db)
    data = db.read_bytes()
    torn = tmp_path / "torn.db"
    torn.write_bytes(data[: size - 1000])
    damaged = tmp_path / "damaged.db"
    flipped = bytearray(data)
    for i in range(3 * 4096, size, 997):
        flipped[i] ^= 0xFF
    damaged.write_bytes(bytes(flipped))
    for bad in (torn, damaged):
        with pytest.raises(JournalError, match=f"{bad.name}: .*corrupt"):
            MapServer(bad)
    MapServer(db).close()  # the intact file still opens


@pytest.mark.skipif(shutil.which("chattr") is None, reason="needs chattr (an immutable file refuses even root)")
def test_a_read_only_journal_is_a_clear_error(tmp_path: Path) -> None:
    db = tmp_path / "ro.db"
    Journal(db).close()
    if subprocess.run(["chattr", "+i", str(db)], capture_output=True).returncode:
        pytest.skip("the file system does not support immutable files")
    try:
        with pytest.raises(JournalError, match="ro.db: cannot write the fleet map database"):
            Journal(db)  # was sqlite3.OperationalError: attempt to write a readonly database
    finally:
        subprocess.run(["chattr", "-i", str(db)], check=True)


def test_a_journal_in_a_missing_directory_says_it_cannot_be_created(tmp_path: Path) -> None:
    with pytest.raises(JournalError, match="cannot create the fleet map database"):  # was "not a fleet map database"
        Journal(tmp_path / "missing" / "m.db")


def test_a_foreign_database_is_refused_and_left_unchanged(tmp_path: Path) -> None:
    """It used to be switched to WAL mode (a change stored in its header) before it was refused."""
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as c:
        c.execute("CREATE TABLE t (x)")
    before = other.read_bytes()
    with pytest.raises(JournalError, match="not a fleet map database"):
        Journal(other)
    assert other.read_bytes() == before
