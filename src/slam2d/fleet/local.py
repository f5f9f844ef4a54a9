"""A fleet in one process: drones hand their deltas straight to :meth:`MapServer.handle` (no sockets). For the
scaling benchmark and the tests of the merge; the same code paths as over the network except the transport."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam2d.fleet.drone import Drone, DroneConfig
from slam2d.fleet.joint import JointConfig
from slam2d.fleet.protocol import encode
from slam2d.fleet.server import MapServer

Array = NDArray[np.float64]


@dataclass
class LocalRun:
    server: MapServer
    drones: list[Drone]
    update_s: list[float]  # wall time of each delta's handling (commit + merge + loops + solve)


def run_local(db: str | Path, drones: int, config: DroneConfig, joint: JointConfig | None = None) -> LocalRun:
    """Fly ``drones`` drones second by second in turn, every delta handled by one in-process server."""
    server = MapServer(db, joint)
    fleet = [Drone("inproc", k, config) for k in range(drones)]
    ident = [f"drone-{k}".encode() for k in range(drones)]
    for d, i in zip(fleet, ident, strict=True):
        d.deliver(server.handle(i, d.hello()))
    times: list[float] = []
    active = list(range(drones))
    while active:
        for k in list(active):
            d = fleet[k]
            if not d.advance(config.send_every_s):
                active.remove(k)
            for _, msg in list(d.outbox):
                t0 = time.perf_counter()
                reply = server.handle(ident[k], msg)
                times.append(time.perf_counter() - t0)
                d.deliver(reply)
            if k not in active:  # landed: says bye as over the network (the server settles its graph)
                server.handle(ident[k], encode({"type": "bye"}))
    return LocalRun(server, fleet, times)


def merged_ate(truth: Array, merged: Array) -> float:
    """RMS position error (m) of merged-frame keyframe poses against the truth, no alignment (the docks put every
    drone in the warehouse frame); rows without a merged pose are skipped."""
    ok = np.all(np.isfinite(merged), axis=1)
    if not ok.any():
        return float("nan")
    e = merged[ok, :2] - truth[ok, :2]
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
