"""The fleet as separate OS processes on ZeroMQ over 127.0.0.1: ``slam2d map-server`` killed with SIGKILL mid-run
and restarted on its file loses no acknowledged keyframe and the drone resynchronises; clients speaking garbage, an
old version, a taken drone id, unknown keyframes, replays and out-of-order deltas get an error each while a real
drone process next to them finishes untouched."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

zmq = pytest.importorskip("zmq")

from slam2d.fleet.client import status  # noqa: E402
from slam2d.fleet.journal import Journal  # noqa: E402
from slam2d.fleet.protocol import VERSION, decode, encode, info_upper, pack_descriptor, pack_points  # noqa: E402

SRC = str(Path(__file__).resolve().parents[2] / "src")
ENV = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", ""), "OPENBLAS_NUM_THREADS": "1"}


def slam2d(*args: str, **kw: Any) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "slam2d", *args], env=ENV, **kw)


def start_server(db: Path, port: int = 0) -> tuple[subprocess.Popen[bytes], str]:
    """``slam2d map-server`` on 127.0.0.1; returns the process and the endpoint it printed."""
    p = slam2d("map-server", "--db", str(db), "--port", str(port), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout is not None
    ready, _, _ = select.select([p.stdout], [], [], 60)
    line = p.stdout.readline().decode() if ready else ""
    if "listening on" not in line:
        p.kill()
        raise AssertionError(f"map-server did not start: {line!r} {p.stderr.read().decode() if p.stderr else ''}")
    return p, line.split("listening on ")[1].split()[0]


@pytest.fixture
def procs() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for p in started:
        if p.poll() is None:
            p.kill()
            p.wait()
        for f in (p.stdout, p.stderr):
            if f is not None:
                f.close()


def wait_for(cond: Any, timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def committed(ep: str, drone: int) -> int:
    for d in status(ep, timeout_s=10)["drones"]:
        if d["drone"] == drone:
            return int(d["keyframes"])
    return 0


def test_kill9_of_the_server_loses_no_acknowledged_keyframe(tmp_path: Path,
                                                           procs: list[subprocess.Popen[bytes]]) -> None:
    db = tmp_path / "map.db"
    server, ep = start_server(db)
    procs.append(server)
    port = ep.rsplit(":", 1)[1]
    out = tmp_path / "drone.json"
    drone = slam2d("drone", "--server", ep, "--drone", "0", "--minutes", "0.6", "--rate", "5", "--json", str(out),
                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    procs.append(drone)
    before = wait_for(lambda: committed(ep, 0) >= 8 and committed(ep, 0), 60, "8 committed keyframes")
    server.send_signal(signal.SIGKILL)
    server.wait()
    assert drone.poll() is None  # killed mid-run
    # what the server had committed (and so possibly acknowledged) is all in the file
    j = Journal(db)
    on_disk = j.count("keyframes")
    j.close()
    assert on_disk >= before
    server2, ep2 = start_server(db, int(port))
    procs.append(server2)
    assert ep2 == ep
    assert committed(ep, 0) >= on_disk  # rebuilt from the file (the drone may already have sent more)
    text = drone.communicate(timeout=120)[0].decode()
    assert drone.returncode == 0, text
    rec = json.loads(out.read_text())
    assert rec["lost_acked"] == 0
    assert rec["reconnects"] >= 1
    assert rec["errors"] == []
    assert committed(ep, 0) == rec["keyframes"] > on_disk  # resynchronised: everything it flew is in the map
    full = status(ep, full=True)["drones"][0]
    merged = np.frombuffer(full["poses"], "<f8").reshape(-1, 3)
    truth = np.asarray(rec["truth"])
    assert np.all(np.isfinite(merged)) and merged.shape == truth.shape


class Client:
    """A raw DEALER connection (one identity for hello and its deltas)."""

    def __init__(self, ep: str) -> None:
        self.sock = zmq.Context.instance().socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(ep)

    def ask(self, data: bytes | list[bytes]) -> dict[str, Any]:
        if isinstance(data, list):
            self.sock.send_multipart(data)
        else:
            self.sock.send(data)
        assert self.sock.poll(20000), "no reply"
        return decode(self.sock.recv())

    def close(self) -> None:
        self.sock.close(0)


def delta(drone: int, seq: int, first: int, n: int, edges: list[tuple[int, int]]) -> bytes:
    rng = np.random.default_rng(seq)
    kfs = [{"id": k, "stamp": float(k), "pose": [5.0 + k, 3.0, 0.0], "desc": pack_descriptor(np.full(17, 1 / 17)),
            "pts": pack_points(rng.uniform(-4, 4, (50, 2)))} for k in range(first, first + n)]
    info = info_upper(np.diag([100.0, 100.0, 400.0]))
    return encode({"type": "delta", "drone": drone, "seq": seq, "keyframes": kfs,
                   "edges": [{"a": a, "b": b, "z": [1.0, 0.0, 0.0], "info": info} for a, b in edges]})


def test_bad_clients_get_errors_and_a_real_drone_is_unaffected(tmp_path: Path,
                                                              procs: list[subprocess.Popen[bytes]]) -> None:
    db = tmp_path / "map.db"
    server, ep = start_server(db)
    procs.append(server)
    out = tmp_path / "drone.json"
    drone = slam2d("drone", "--server", ep, "--drone", "0", "--minutes", "0.5", "--rate", "4", "--json", str(out),
                   "--floor-markers", stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    procs.append(drone)
    wait_for(lambda: committed(ep, 0) > 0, 60, "the drone's first keyframes")

    bad = Client(ep)
    try:
        assert bad.ask(b"\x93garbage")["code"] == "garbled"
        assert bad.ask([b"two", b"frames"])["code"] == "garbled"
        old = msgpack.packb({"v": VERSION - 1, "type": "hello", "drone": 5, "session": "x", "dock": [1, 1, 0]})
        r = bad.ask(old)
        assert r["code"] == "version" and str(VERSION) in r["message"]
        r = bad.ask(encode({"type": "hello", "drone": 0, "session": "impostor", "dock": [1, 1, 0]}))
        assert r["code"] == "duplicate-drone" and "0" in r["message"]
        assert bad.ask(delta(0, 99, 0, 1, []))["code"] == "not-registered"
        assert bad.ask(encode({"type": "hello", "drone": 7, "session": "b7", "dock": [5, 3, 0]}))["type"] == "welcome"
        assert bad.ask(delta(7, 1, 0, 2, [(0, 1), (1, 4)]))["code"] == "unknown-keyframe"
        assert bad.ask(delta(7, 2, 0, 2, [(0, 1)]))["code"] == "out-of-order"
        assert bad.ask(delta(7, 1, 0, 2, [(0, 1)]))["type"] == "ack"
        assert bad.ask(delta(7, 1, 0, 2, [(0, 1)]))["duplicate"] is True  # a resend: acknowledged again
        assert bad.ask(delta(7, 1, 0, 3, [(0, 1)]))["code"] == "replay"  # same seq, other content
        assert bad.ask(delta(0, 2, 0, 1, []))["code"] == "wrong-drone"
    finally:
        bad.close()
    text = drone.communicate(timeout=120)[0].decode()
    assert drone.returncode == 0, text
    rec = json.loads(out.read_text())
    assert rec["errors"] == [] and rec["lost_acked"] == 0
    assert server.poll() is None
    assert committed(ep, 0) == rec["keyframes"]
    assert committed(ep, 7) == 2  # only the one good delta of the bad client
    j = Journal(db)
    try:
        assert j.count("deltas") == rec["acked_max"] + 1
        # the drone docks over a floor marker: its keyframes' readings reached the journal
        assert rec["marker_sightings"] > 0 and j.count("keyframe_markers") > 0
    finally:
        j.close()


def test_cli_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from slam2d.cli.main import main

    for args, needle in ((["map-server", "--db", str(tmp_path)], "is a directory"),
                         (["drone", "--server", "tcp://127.0.0.1:1", "--drone", "0", "--blackout", "soon"],
                          "--blackout"),
                         (["drone", "--server", "tcp://127.0.0.1:1", "--drone", "-3"], "--drone")):
        assert main(args) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0], lines


def test_a_second_server_on_the_same_database_is_refused(tmp_path: Path,
                                                         procs: list[subprocess.Popen[bytes]]) -> None:
    """Two servers on one file would hand out the same drone ids and keyframe keys (the second crashed on the first
    drone it met): the second is refused at start, the first serves on."""
    db = tmp_path / "one.db"
    first, ep = start_server(db)
    procs.append(first)
    second = slam2d("map-server", "--db", str(db), "--port", "0", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    procs.append(second)
    _, err = second.communicate(timeout=120)
    assert second.returncode == 2, err.decode()
    assert f"another map-server has {db} open (lock one.db.lock is held)" in err.decode()
    assert first.poll() is None and status(ep, timeout_s=10)["drones"] == []
