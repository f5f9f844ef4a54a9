"""The map server: a ZeroMQ ROUTER that commits drones' deltas to the journal, merges them into the joint graph and
answers with corrections. :meth:`MapServer.handle` is the whole logic (one message in, one reply out) and runs
without a socket in tests; :meth:`MapServer.serve` is the transport loop.

Order of work for a delta: validate (envelope, registration, sequence, keyframe ids, edge ends) -> commit to SQLite
(one transaction) -> add to the joint graph -> inter-robot loop search (loops committed in a second transaction)
-> solve when due -> ack with the drone's changed keyframe poses and changed map tiles near it. Nothing is written
for a refused message, and a refusal goes to the sending client only.
"""

from __future__ import annotations

import signal
import sqlite3
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.fleet.joint import JointConfig, JointGraph
from slam2d.fleet.journal import Journal, JournalError
from slam2d.fleet.protocol import Delta, ProtocolError, decode, encode, parse_delta, parse_hello

Array = NDArray[np.float64]

POSE_MOVED_M = 0.02
POSE_TURNED_RAD = 0.005
TILE_RADIUS_M = 12.0
TILES_PER_ACK = 1


@dataclass
class _DroneState:
    session: str
    acked_seq: int
    keyframes: int
    identity: bytes | None = None
    last_seen: float = 0.0
    told: Array = field(default_factory=lambda: np.zeros((0, 3)))  # merged poses last sent (nan: never)
    tiles_sent: dict[tuple[int, int], int] = field(default_factory=dict)
    bytes_in: int = 0
    bytes_out: int = 0


class MapServer:
    """The server's state (journal + joint graph + per-drone bookkeeping); see the module docstring."""

    def __init__(self, db: str | Path, config: JointConfig | None = None, *, durable: bool = False) -> None:
        self.journal = Journal(db, durable=durable)
        self.joint = JointGraph(config)
        self.drones: dict[int, _DroneState] = {}
        self.by_identity: dict[bytes, int] = {}
        self.errors: Counter[str] = Counter()  # refusals by code (status reports them, so a run can say why)
        self.started = time.time()
        try:
            for row in self.journal.drones():  # rebuild from what was committed
                self.drones[row.drone] = _DroneState(row.session, row.acked_seq, row.keyframes)
                self.joint.add_drone(row.drone, row.dock)
                self.joint.add_keyframes(row.drone, self.journal.keyframes(row.drone), self.journal.edges(row.drone))
            for lp in self.journal.loops():
                self.joint.add_loop(lp)
            if len(self.joint.poses):
                self.joint.solve(10)
        except (sqlite3.Error, ValueError, IndexError, KeyError) as e:  # rows a valid delta never makes: damage
            self.journal.close()
            raise JournalError(f"{db}: corrupt fleet map database ({type(e).__name__}: {e}); restore a copy or "
                               "give a new path") from None

    def close(self) -> None:
        self.journal.close()

    # ------------------------------------------------------------------ one message
    def handle(self, identity: bytes, data: bytes) -> bytes:
        """The reply to one message from the client ``identity``; errors become an ``error`` reply."""
        try:
            msg = decode(data)
            kind = msg["type"]
            if kind == "hello":
                reply = self._hello(identity, msg)
            elif kind == "delta":
                reply = self._delta(identity, msg, len(data))
            elif kind == "status":
                reply = self.status(full=bool(msg.get("full", False)))
            elif kind == "bye":
                d = self.by_identity.pop(identity, None)
                if d is not None:
                    self.drones[d].identity = None
                    self.joint.settle()
                reply = {"type": "bye"}
            else:
                raise ProtocolError("unknown-type", f"unknown message type {kind!r}")
        except ProtocolError as e:
            self.errors[e.code] += 1
            reply = {"type": "error", "code": e.code, "message": str(e)}
            if e.seq is not None:
                reply["seq"] = e.seq
        out = encode(reply)
        d = self.by_identity.get(identity)
        if d is not None:
            self.drones[d].bytes_out += len(out)
        return out

    def _hello(self, identity: bytes, msg: dict[str, Any]) -> dict[str, Any]:
        drone, session, dock = parse_hello(msg)
        st = self.drones.get(drone)
        if st is not None and st.session != session:
            raise ProtocolError("duplicate-drone", f"drone id {drone} is held by another session; pick another "
                                                   "--drone id")
        if identity in self.by_identity and self.by_identity[identity] != drone:
            raise ProtocolError("duplicate-drone", f"this connection already speaks for drone "
                                                   f"{self.by_identity[identity]}")
        if st is None:
            self.journal.claim(drone, session, dock)
            st = self.drones[drone] = _DroneState(session, 0, 0)
            self.joint.add_drone(drone, dock)
        if st.identity is not None and st.identity != identity:
            self.by_identity.pop(st.identity, None)  # the same drone on a new connection (it reconnected)
        st.identity = identity
        st.last_seen = time.time()
        st.told = np.full((st.keyframes, 3), np.nan)  # resynchronise: the next ack sends every pose
        st.tiles_sent = {}
        self.by_identity[identity] = drone
        return {"type": "welcome", "drone": drone, "acked_seq": st.acked_seq, "keyframes": st.keyframes}

    def _delta(self, identity: bytes, msg: dict[str, Any], size: int) -> dict[str, Any]:
        drone = self.by_identity.get(identity)
        if drone is None:
            raise ProtocolError("not-registered", "send 'hello' before deltas")
        d = parse_delta(msg)
        if d.drone != drone:
            raise ProtocolError("wrong-drone", f"this connection speaks for drone {drone}, not {d.drone}", d.seq)
        st = self.drones[drone]
        st.last_seen = time.time()
        st.bytes_in += size
        if d.seq <= st.acked_seq:
            if self.journal.digest(drone, d.seq) != d.digest:
                raise ProtocolError("replay", f"delta {d.seq} was already committed with different content", d.seq)
            # a resend: acknowledged again, nothing else (the corrections come with the next new delta)
            return {"type": "ack", "seq": d.seq, "duplicate": True, "ids": b"", "poses": b"", "tiles": []}
        if d.seq != st.acked_seq + 1:
            raise ProtocolError("out-of-order", f"delta {d.seq} arrived before {st.acked_seq + 1}", d.seq)
        self._check_references(st, d)
        self.journal.commit_delta(d)
        st.acked_seq = d.seq
        st.keyframes += len(d.keyframes)
        st.told = np.vstack([st.told, np.full((len(d.keyframes), 3), np.nan)])
        new = self.joint.add_keyframes(drone, d.keyframes, d.edges)
        loops = self.joint.search_loops(new, max((k.stamp for k in d.keyframes), default=0.0))
        if loops:
            self.journal.add_loops(loops)
            for lp in loops:
                self.joint.add_loop(lp)
        if self.joint.needs_solve():
            self.joint.solve()
        return self._ack(drone, d.seq, duplicate=False)

    @staticmethod
    def _check_references(st: _DroneState, d: Delta) -> None:
        if d.keyframes and d.keyframes[0].id != st.keyframes:
            raise ProtocolError("unknown-keyframe", f"delta {d.seq}: keyframe ids must continue at {st.keyframes} "
                                                    f"(got {d.keyframes[0].id})", d.seq)
        known = st.keyframes + len(d.keyframes)
        for e in d.edges:
            if max(e.a, e.b) >= known:
                raise ProtocolError("unknown-keyframe", f"delta {d.seq}: edge {e.a}->{e.b} references keyframe "
                                                        f"{max(e.a, e.b)}, unknown (this drone has {known})", d.seq)
        # a keyframe no edge ties to an earlier one is unconstrained: the joint solve would fail on it (after the
        # commit, and again at every restart on the journal)
        linked = {max(e.a, e.b) for e in d.edges}
        for k in d.keyframes:
            if k.id > 0 and k.id not in linked:
                raise ProtocolError("unlinked-keyframe", f"delta {d.seq}: keyframe {k.id} comes with no edge from an "
                                                         "earlier keyframe (send the odometry edge with it)", d.seq)

    def _ack(self, drone: int, seq: int, *, duplicate: bool) -> dict[str, Any]:
        st = self.drones[drone]
        poses = self.joint.drone_poses(drone)
        moved = (np.isnan(st.told[:, 0]) | (np.hypot(*(poses[:, :2] - st.told[:, :2]).T) > POSE_MOVED_M)
                 | (np.abs(poses[:, 2] - st.told[:, 2]) > POSE_TURNED_RAD))
        ids = np.flatnonzero(moved)
        st.told[ids] = poses[ids]
        tiles: list[dict[str, Any]] = []
        if len(poses):
            for t in self.joint.tiles_near(poses[-1, :2], TILE_RADIUS_M):
                if self.joint.tile_version[t] > st.tiles_sent.get(t, -1) and len(tiles) < TILES_PER_ACK:
                    tiles.append({"i": t[0], "j": t[1], "cells": self.joint.tile_raster(t)})
                    st.tiles_sent[t] = self.joint.tile_version[t]
        return {"type": "ack", "seq": seq, "duplicate": duplicate,
                "ids": ids.astype("<u4").tobytes(), "poses": poses[ids].astype("<f4").tobytes(), "tiles": tiles}

    def status(self, *, full: bool = False) -> dict[str, Any]:
        """A snapshot for watchers: per drone its keyframe positions (float32 x, y; every keyframe when ``full``,
        else at most 400), and every inter-robot loop with its two positions."""
        now = time.time()
        drones = []
        for d, st in sorted(self.drones.items()):
            p = self.joint.drone_poses(d)
            step = 1 if full else max(1, len(p) // 400)
            drones.append({"drone": d, "keyframes": st.keyframes, "acked_seq": st.acked_seq,
                           "connected": st.identity is not None, "idle_s": round(now - st.last_seen, 1),
                           "bytes_in": st.bytes_in, "bytes_out": st.bytes_out,
                           "poses": (p if full else p[::step, :2]).astype("<f8" if full else "<f4").tobytes()})
        loops = []
        for lp in self.joint.loops:
            pa = self.joint.poses[self.joint.key(lp.drone_a, lp.a)]
            pb = self.joint.poses[self.joint.key(lp.drone_b, lp.b)]
            loops.append({"a": [lp.drone_a, lp.a], "b": [lp.drone_b, lp.b], "stamp": lp.stamp,
                          "xy": [float(pa[0]), float(pa[1]), float(pb[0]), float(pb[1])]})
        solves = self.joint.solves[-50:]
        j = self.joint
        shared = sum(len(ds) > 1 for ds in j.marker_drones().values())
        markers = {"count": len(j.marker_ids), "shared": shared, "sightings": len(j._mk_key),
                   "links": j.marker_links, "resightings": j.marker_resightings}
        return {"type": "status", "drones": drones, "loops": loops, "errors": sum(self.errors.values()),
                "errors_by_code": dict(self.errors), "markers": markers,
                "solves": [[s.nodes, s.edges, round(s.seconds, 5)] for s in solves],
                "failed_solves": self.joint.failed_solves,
                "uptime_s": round(now - self.started, 1)}

    # ------------------------------------------------------------------ transport
    def serve(self, host: str = "127.0.0.1", port: int = 0, *, ready: Any = None,
              stop_event: threading.Event | None = None) -> None:
        """Bind a ROUTER socket on tcp://host:port (port 0: any free port) and answer until SIGTERM / SIGINT (in the
        main thread) or ``stop_event``. ``ready(endpoint)`` is called once bound."""
        import zmq

        sock: Any = zmq.Context.instance().socket(zmq.ROUTER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, 8 << 20)
        if port:
            sock.bind(f"tcp://{host}:{port}")
        else:
            port = sock.bind_to_random_port(f"tcp://{host}")
        stop = []

        def _stop(signum: int, frame: Any) -> None:
            stop.append(signum)

        main = threading.current_thread() is threading.main_thread()
        old = {s: signal.signal(s, _stop) for s in (signal.SIGTERM, signal.SIGINT)} if main else {}
        if ready is not None:
            ready(f"tcp://{host}:{port}")
        try:
            while not stop and not (stop_event is not None and stop_event.is_set()):
                if not sock.poll(200):
                    continue
                frames = sock.recv_multipart()
                if len(frames) != 2:  # a DEALER sends one frame; anything else is not our client
                    if frames:
                        sock.send_multipart([frames[0], encode({"type": "error", "code": "garbled",
                                                                "message": "expected one frame per message"})])
                    continue
                sock.send_multipart([frames[0], self.handle(frames[0], frames[1])])
        finally:
            for s, h in old.items():
                signal.signal(s, h)
            sock.close(0)
