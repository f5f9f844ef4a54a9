"""The map server's message handling in one process (MapServer.handle, no sockets): every refusal of bad input
goes to the sender only, writes nothing, and leaves the other drones working; resends are idempotent; a restarted
server resumes from its journal."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from slam2d.fleet.journal import Journal, JournalError
from slam2d.fleet.protocol import (
    MAX_MARKERS,
    VERSION,
    decode,
    encode,
    info_upper,
    pack_descriptor,
    pack_markers,
    pack_points,
    parse_delta,
    unpack_markers,
)
from slam2d.fleet.server import MapServer

A, B = b"conn-a", b"conn-b"


def hello(drone: int, session: str = "s") -> bytes:
    return encode({"type": "hello", "drone": drone, "session": session, "dock": [1.0, 2.0, 0.0]})


def keyframe(k: int, rng: np.random.Generator) -> dict[str, Any]:
    pts = rng.uniform(-5, 5, (60, 2))
    hist = np.full(17, 1 / 17)
    return {"id": k, "stamp": float(k), "pose": [1.0 + k, 2.0, 0.0], "desc": pack_descriptor(hist),
            "pts": pack_points(pts)}


def delta(drone: int, seq: int, first: int, n: int, rng: np.random.Generator,
          edges: list[tuple[int, int]] | None = None) -> bytes:
    kfs = [keyframe(k, rng) for k in range(first, first + n)]
    if edges is None:
        edges = [(k - 1, k) for k in range(max(first, 1), first + n)]
    info = info_upper(np.diag([100.0, 100.0, 400.0]))
    return encode({"type": "delta", "drone": drone, "seq": seq, "keyframes": kfs,
                   "edges": [{"a": a, "b": b, "z": [1.0, 0.0, 0.0], "info": info} for a, b in edges]})


def counts(server: MapServer) -> tuple[int, ...]:
    j = server.journal
    return tuple(j.count(t) for t in ("drones", "deltas", "keyframes", "edges", "loops"))


@pytest.fixture
def server(tmp_path: Path) -> MapServer:
    s = MapServer(tmp_path / "map.db")
    rng = np.random.default_rng(0)
    assert decode(s.handle(A, hello(0, "sa")))["type"] == "welcome"
    assert decode(s.handle(A, delta(0, 1, 0, 3, rng)))["type"] == "ack"
    return s


def refused(server: MapServer, ident: bytes, data: bytes, code: str) -> dict[str, Any]:
    before = counts(server)
    by_code = server.status()["errors_by_code"].get(code, 0)
    reply = decode(server.handle(ident, data))
    assert reply["type"] == "error", reply
    assert reply["code"] == code, reply
    assert reply["message"]
    assert counts(server) == before  # nothing written
    assert server.status()["errors_by_code"][code] == by_code + 1  # the status says why it refused
    return reply


def still_works(server: MapServer) -> None:
    """Drone 0 on its own connection goes on as if nothing happened."""
    st = server.drones[0]
    r = decode(server.handle(A, delta(0, st.acked_seq + 1, st.keyframes, 2, np.random.default_rng(5))))
    assert r["type"] == "ack" and not r["duplicate"]


def test_garbled_and_old_version(server: MapServer) -> None:
    refused(server, B, b"\xc1\x00garbage", "garbled")
    refused(server, B, b"", "garbled")
    refused(server, B, msgpack.packb([1, 2, 3]), "garbled")
    refused(server, B, msgpack.packb({"v": VERSION - 1, "type": "hello", "drone": 1, "session": "x",
                                      "dock": [0, 0, 0]}), "version")
    refused(server, B, msgpack.packb({"v": "1", "type": "hello"}), "version")
    refused(server, B, encode({"type": "teleport"}), "unknown-type")
    refused(server, B, encode({"type": "hello", "drone": -1, "session": "x", "dock": [0, 0, 0]}), "garbled")
    refused(server, B, encode({"type": "hello", "drone": 1, "session": "x", "dock": [0, float("nan"), 0]}),
            "garbled")
    still_works(server)


def test_duplicate_drone_id(server: MapServer) -> None:
    reply = refused(server, B, hello(0, "another-session"), "duplicate-drone")
    assert "drone id 0" in reply["message"]
    # the connection that was refused cannot send deltas either
    refused(server, B, delta(0, 2, 3, 1, np.random.default_rng(1)), "not-registered")
    still_works(server)
    # the same session on a new connection (a reconnect) is welcome and told what was committed
    w = decode(server.handle(B, hello(0, "sa")))
    assert w["type"] == "welcome" and w["acked_seq"] == 2 and w["keyframes"] == 5


def test_delta_for_another_drone_is_refused(server: MapServer) -> None:
    assert decode(server.handle(B, hello(1, "sb")))["type"] == "welcome"
    refused(server, B, delta(0, 2, 3, 1, np.random.default_rng(1)), "wrong-drone")
    still_works(server)


def test_unknown_keyframes(server: MapServer) -> None:
    rng = np.random.default_rng(2)
    refused(server, A, delta(0, 2, 3, 1, rng, edges=[(2, 3), (3, 9)]), "unknown-keyframe")  # edge to nowhere
    refused(server, A, delta(0, 2, 7, 1, rng, edges=[]), "unknown-keyframe")  # ids skip 3..6
    refused(server, A, delta(0, 2, 0, 0, rng, edges=[(1, 5)]), "unknown-keyframe")
    still_works(server)


def test_out_of_order_and_replay(server: MapServer) -> None:
    rng = np.random.default_rng(3)
    refused(server, A, delta(0, 3, 3, 1, rng), "out-of-order")  # 2 not yet sent
    refused(server, A, delta(0, 1, 0, 2, rng), "replay")  # seq 1 again, other content
    # seq 1 resent with its original content: acknowledged again, nothing written
    before = counts(server)
    r = decode(server.handle(A, delta(0, 1, 0, 3, np.random.default_rng(0))))
    assert r["type"] == "ack" and r["duplicate"] and r["seq"] == 1
    assert counts(server) == before
    still_works(server)


def test_garbled_delta_fields(server: MapServer) -> None:
    rng = np.random.default_rng(4)
    good = msgpack.unpackb(delta(0, 2, 3, 1, rng))
    for change in ({"keyframes": "x"}, {"seq": 0}, {"edges": [{"a": 2, "b": 3, "z": [1, 0], "info": [1] * 6}]},
                   {"edges": [{"a": 2, "b": 3, "z": [1, 0, 0], "info": [-1, 0, 0, 1, 0, 1]}]},
                   {"keyframes": [{**good["keyframes"][0], "desc": b"short"}]},
                   {"keyframes": [{**good["keyframes"][0], "pts": b"\x00" * 4001}]},
                   # floor-marker field: not bytes, not whole records, too many, a repeated id, a zero sigma
                   {"keyframes": [{**good["keyframes"][0], "mk": "x"}]},
                   {"keyframes": [{**good["keyframes"][0], "mk": b"\x00" * 7}]},
                   {"keyframes": [{**good["keyframes"][0], "mk": pack_markers(np.arange(MAX_MARKERS + 1),
                                                                              np.zeros((MAX_MARKERS + 1, 2)),
                                                                              np.full(MAX_MARKERS + 1, 0.01))}]},
                   {"keyframes": [{**good["keyframes"][0], "mk": pack_markers(np.array([3, 3]), np.zeros((2, 2)),
                                                                              np.full(2, 0.01))}]},
                   {"keyframes": [{**good["keyframes"][0], "mk": pack_markers(np.array([3]), np.zeros((1, 2)),
                                                                              np.ones(1))[:8] + b"\x00\x00"}]}):
        refused(server, A, msgpack.packb({**good, **change}), "garbled")
    still_works(server)


def test_ack_carries_corrections_and_restart_resumes(tmp_path: Path) -> None:
    db = tmp_path / "map.db"
    s = MapServer(db)
    rng = np.random.default_rng(6)
    s.handle(A, hello(3, "s3"))
    ack = decode(s.handle(A, delta(3, 1, 0, 4, rng)))
    ids = np.frombuffer(ack["ids"], "<u4")
    assert ids.tolist() == [0, 1, 2, 3]  # first ack: every pose is new to the drone
    ack2 = decode(s.handle(A, delta(3, 2, 4, 1, rng)))
    assert np.frombuffer(ack2["ids"], "<u4").tolist() == [4]  # only the new one
    s.close()
    s2 = MapServer(db)  # a restart: state from the journal only
    assert s2.drones[3].acked_seq == 2 and s2.drones[3].keyframes == 5
    assert len(s2.joint.poses) == 5
    w = decode(s2.handle(B, hello(3, "s3")))
    assert w["acked_seq"] == 2 and w["keyframes"] == 5
    refused(s2, B, hello(3, "impostor"), "duplicate-drone")
    s2.close()


def test_journal_refuses_foreign_files(tmp_path: Path) -> None:
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"not a database at all" * 100)
    with pytest.raises(JournalError, match="junk.db"):
        Journal(junk)
    import sqlite3

    other = tmp_path / "other.db"
    with sqlite3.connect(other) as c:
        c.execute("CREATE TABLE t (x)")
    with pytest.raises(JournalError, match="not a fleet map database"):
        Journal(other)


def test_marker_field_round_trip_and_restart() -> None:
    ids, xy, sigma = np.array([7, 70000]), np.array([[0.4321, -0.9876], [-1.5, 0.25]]), np.array([0.01, 0.0123])
    got_ids, got_xy, got_sigma = unpack_markers(pack_markers(ids, xy, sigma))
    assert got_ids.tolist() == [7, 70000]
    assert np.abs(got_xy - xy).max() <= 0.0005 and np.abs(got_sigma - sigma).max() <= 0.00005
    kf = {**keyframe(0, np.random.default_rng(1)), "mk": pack_markers(ids, xy, sigma)}
    d = parse_delta(decode(encode({"type": "delta", "drone": 0, "seq": 1, "keyframes": [kf], "edges": []})))
    assert d.keyframes[0].mk == kf["mk"]


def _marker_delta(drone: int, scale: float, rel: list[float], sigma: float) -> bytes:
    """Five keyframes 1 m apart along x (reported with odometry scale ``scale``, edges of ``sigma``), the last
    reading marker 9 at ``rel`` in its frame."""
    rng = np.random.default_rng(drone)
    kfs = [keyframe(k, rng) for k in range(5)]
    for k in kfs:
        k["pose"] = [scale * k["id"], 0.0, 0.0]
    kfs[-1]["mk"] = pack_markers(np.array([9]), np.array([rel]), np.array([0.01]))
    info = info_upper(np.diag([sigma**-2, sigma**-2, 400.0]))
    return encode({"type": "delta", "drone": drone, "seq": 1, "keyframes": kfs,
                   "edges": [{"a": k - 1, "b": k, "z": [scale, 0.0, 0.0], "info": info} for k in range(1, 5)]})


@pytest.mark.parametrize("markers", [True, False])
def test_a_marker_read_by_two_drones_ties_them(tmp_path: Path, markers: bool) -> None:
    """Drone 0 (docked at y = 0, exact odometry of 1 cm) and drone 1 (docked at y = 1, odometry 20 % long, 30 cm)
    both end at x = 4 over marker 9 at (4, 0.5). With the marker, drone 1's last keyframe is pulled to x = 4 (the
    readings are 1 cm); without it, it stays at the 4.8 m its odometry says."""
    s = MapServer(tmp_path / "m.db")
    s.handle(A, encode({"type": "hello", "drone": 0, "session": "a", "dock": [0.0, 0.0, 0.0]}))
    s.handle(B, encode({"type": "hello", "drone": 1, "session": "b", "dock": [0.0, 1.0, 0.0]}))
    d0, d1 = _marker_delta(0, 1.0, [0.0, 0.5], 0.01), _marker_delta(1, 1.2, [0.0, -0.5], 0.3)
    if not markers:  # the same deltas without their marker fields
        d0, d1 = (encode({k: v for k, v in {**decode(d), "keyframes": [{f: x for f, x in kf.items() if f != "mk"}
                                                                      for kf in decode(d)["keyframes"]]}.items()
                          if k != "v"}) for d in (d0, d1))
    assert decode(s.handle(A, d0))["type"] == "ack"
    # drone 1 is reported in its own (dock) frame: y = 0 there is y = 1 in the warehouse
    d1m = decode(d1)
    for k in d1m["keyframes"]:
        k["pose"][1] = 1.0
    assert decode(s.handle(B, encode({k: v for k, v in d1m.items() if k != "v"})))["type"] == "ack"
    s.joint.solve(10)
    last = s.joint.drone_poses(1)[-1]
    st = s.status()["markers"]
    if markers:
        assert abs(last[0] - 4.0) < 0.05 and st["count"] == 1 and st["shared"] == 1 and st["links"] == 1
        assert s.journal.count("keyframe_markers") == 2
    else:
        assert abs(last[0] - 4.8) < 0.05 and st["count"] == 0
    s.close()
    s2 = MapServer(tmp_path / "m.db")  # restart: the markers come back from the journal
    assert len(s2.joint.marker_ids) == (1 if markers else 0)
    s2.close()


def test_a_surveyed_marker_anchors_a_drifting_drone(tmp_path: Path) -> None:
    """One drone, odometry 20 % long (30 cm edges), reads marker 9 from its last keyframe; the survey puts marker 9
    at (4, 0.5): the last keyframe is pulled to x = 4 (without the survey, nothing contradicts the odometry)."""
    from slam2d.fleet.joint import JointConfig

    s = MapServer(tmp_path / "s.db", JointConfig(surveyed_markers=((9, 4.0, 0.5),)))
    s.handle(B, encode({"type": "hello", "drone": 1, "session": "b", "dock": [0.0, 0.0, 0.0]}))
    assert decode(s.handle(B, _marker_delta(1, 1.2, [0.0, 0.5], 0.3)))["type"] == "ack"
    s.joint.solve(10)
    assert abs(s.joint.drone_poses(1)[-1, 0] - 4.0) < 0.05
    assert np.allclose(s.joint.markers[0], [4.0, 0.5], atol=0.01)
    s.close()
