"""A drone: the simulator flying one route through the warehouse, its own lidar front end (the ``lidar``
estimator: scan matching, keyframes, its own loops), and a ZeroMQ DEALER that sends only deltas to the map server.

What a drone sends per delta (one every ``send_every_s`` simulated seconds): each new keyframe's pose in the drone's
frame, a 17-byte range-histogram descriptor and at most 120 scan points as int16 centimetres, the floor markers
read at the keyframe (10 bytes each; with ``floor_markers``); the edge from the previous keyframe (see
:func:`keyframe_edge`) and the loops its own front end accepted. Deltas stay in the outbox until acknowledged:
after a timeout or a blackout the drone opens a new connection, says hello, drops what the server reports committed
and resends the rest in order (the server acknowledges a resend it already has without writing it again).

The drone's merged-frame pose: the server's newest corrected pose of a keyframe composed with the drone's own
motion since that keyframe.
"""

from __future__ import annotations

import secrets
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.fleet.protocol import (
    ProtocolError,
    decode,
    encode,
    info_upper,
    pack_descriptor,
    pack_markers,
    pack_points,
)
from slam2d.geometry import se2
from slam2d.graph.lidar import LidarSLAM, LidarSLAMConfig, scan_points
from slam2d.maps.store import range_histogram
from slam2d.models.motion import MotionNoise, odometry_covariance
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator
from slam2d.sim.warehouse import WarehouseConfig

Array = NDArray[np.float64]

#: information of the drone's own loops (its front end does not export them)
LOOP_SIGMA = (0.05, 0.05, 0.015)
#: standard deviation of a keyframe-to-keyframe scan match across the track (m) and in heading (rad); along the
#: track a scan match carries no information (see :func:`keyframe_edge`). Measured on drone 0, seed 0 (3 min):
#: across 3.0 cm rms, heading 2 mrad rms; the heading keeps the lidar estimator's floor (5 mrad).
SCAN_SIGMA_ACROSS_M = 0.03
SCAN_SIGMA_THETA_RAD = 0.005
MAX_TIMEOUT_S = 30.0


def keyframe_edge(z_scan: Array, z_odo: Array, cov_odo: Array) -> tuple[Array, Array]:
    """The edge between two consecutive keyframes, ``(z, info)`` for the between factor: the front end's scan-matched
    relative pose ``z_scan`` fused with the wheel odometry ``z_odo`` composed over the same steps (covariance
    ``cov_odo`` in [dx, dy, dtheta] of the start keyframe, propagated from the odometry noise model).

    Why: in an aisle the lidar sees two parallel walls and nothing ahead within range, so a scan match does not
    fix the motion along the track; the front end's match then leans on whatever moves with it (a forklift ahead)
    and measured along-track errors of 25 cm rms per 1 m keyframe (3 m at worst) while its covariance claimed
    6 mm. The odometry is calibrated (chi-square 3.2 for 3 dof) but drifts in heading. So the scan match gives
    information across the track (direction of the odometry's translation) and in heading only, the odometry gives
    everything with its own covariance, and the two are added in information form."""
    t = float(np.hypot(z_odo[0], z_odo[1]))
    a = float(np.arctan2(z_odo[1], z_odo[0])) if t > 1e-6 else 0.0
    across = np.array([-np.sin(a), np.cos(a), 0.0])
    info_scan = (np.outer(across, across) / SCAN_SIGMA_ACROSS_M**2
                 + np.diag([0.0, 0.0, 1.0 / SCAN_SIGMA_THETA_RAD**2]))
    info_odo = np.linalg.inv(cov_odo)
    info = info_scan + info_odo
    d = np.asarray(z_scan, np.float64) - z_odo
    d[2] = float(np.arctan2(np.sin(d[2]), np.cos(d[2])))
    z = z_odo + np.linalg.solve(info, info_scan @ d)
    z[2] = float(np.arctan2(np.sin(z[2]), np.cos(z[2])))
    # the between factor's translation error is in the END frame: rotate the covariance (as odometry_factor does)
    cov_e = se2.covariance_in_frame(np.linalg.inv(info), z[2])
    return z, np.asarray(np.linalg.inv(cov_e), np.float64)


class DroneError(ValueError):
    """The server refused this drone (duplicate id, protocol error) or never answered."""


@dataclass(frozen=True, slots=True, kw_only=True)
class DroneConfig:
    """How one drone flies and talks."""

    scenario: str = "warehouse"
    minutes: float = 2.0
    """simulated flight time (min)."""
    seed: int = 0
    """seed of the fleet; drone K simulates with seed * 1000 + K."""
    send_every_s: float = 1.0
    """simulated seconds between deltas."""
    ack_timeout_s: float = 3.0
    """wall seconds without an answer to the oldest unacknowledged message before reconnecting (doubled after
    each silent reconnect, up to 30 s; back to this after any answer)."""
    window: int = 16
    """deltas in flight at most."""
    rate: float = 0.0
    """simulated seconds per wall second (0: as fast as the front end runs)."""
    blackout: tuple[float, float] | None = None
    """(start, duration) in simulated seconds: no link to the server during that time."""
    flush_timeout_s: float = 300.0
    """wall seconds to wait at the end without any acknowledgement before giving up on the unacknowledged deltas."""
    keyframe_distance_m: float = 1.0
    """the front end's keyframe spacing (m; the lidar estimator's own default is 0.3 m, for a single robot)."""
    keyframe_angle_rad: float = 0.5
    floor_markers: bool = False
    """fly with floor markers (the scenario's markers, read by the downward camera): the front end uses them and
    the deltas carry each keyframe's readings."""


def start_pose(sim: Simulator, drone: int) -> tuple[Array, Array]:
    """Drone K starts at waypoint 3K of the scenario's route (mod its length), facing the next one; its route is
    the same loop started there. Returns (start pose, waypoints)."""
    wp = np.roll(sim.waypoints, -3 * drone, axis=0)
    d = wp[1] - wp[0]
    return np.array([wp[0, 0], wp[0, 1], np.arctan2(d[1], d[0])]), wp


@dataclass
class DroneResult:
    drone: int
    steps: int
    keyframes: int
    deltas: int
    reconnects: int
    errors: list[str]
    up_bytes: NDArray[np.int64]  # bytes sent per simulated second
    down_bytes: NDArray[np.int64]
    truth: Array  # (K, 3) true pose of each keyframe
    local: Array  # (K, 3) the drone's own final keyframe estimates
    merged: Array  # (K, 3) the server's newest corrections (nan where none arrived)
    tiles: int
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"drone": self.drone, "steps": self.steps, "keyframes": self.keyframes, "deltas": self.deltas,
                "reconnects": self.reconnects, "errors": self.errors, "up_bytes": self.up_bytes.tolist(),
                "down_bytes": self.down_bytes.tolist(), "truth": self.truth.tolist(), "local": self.local.tolist(),
                "merged": [[None if np.isnan(v) else float(v) for v in row] for row in self.merged],
                "tiles": self.tiles,
                **self.extra}


class Drone:
    """One drone process's state; :meth:`run` flies the whole flight."""

    def __init__(self, server: str, drone: int, config: DroneConfig | None = None, *, session: str | None = None,
                 log: Any = None) -> None:
        self.server = server
        self.drone = int(drone)
        self.config = cfg = config or DroneConfig()
        self.session = session or secrets.token_hex(8)
        self.log = log or (lambda s: None)
        scenario = ScenarioConfig(name=cfg.scenario, warehouse=WarehouseConfig(floor_markers=cfg.floor_markers))
        self.sim = Simulator(scenario, seed=cfg.seed * 1000 + self.drone, record=False)
        pose, wp = start_pose(self.sim, self.drone)
        self.sim.pose, self.sim.initial_pose, self.sim.waypoints = pose.copy(), pose.copy(), wp
        self.dock = pose
        self.est = LidarSLAM(LidarSLAMConfig(keyframe_distance_m=cfg.keyframe_distance_m,
                                             keyframe_angle_rad=cfg.keyframe_angle_rad))
        self.est.reset(pose, rng=np.random.default_rng(self.drone))
        self.outbox: list[tuple[int, bytes]] = []  # (seq, message) not yet acknowledged, in order
        self.in_flight = 0
        self.seq = 0
        self.sock: Any = None
        self.welcomed = False
        self.waiting_since = 0.0
        self.reconnects = -1
        self.errors: list[str] = []
        self.pending_kf: list[dict[str, Any]] = []
        self.pending_edges: list[dict[str, Any]] = []
        self.kf_step: dict[int, int] = {}
        self.truth: list[Array] = []
        self.merged = np.zeros((0, 3))
        self.up: dict[int, int] = {}
        self.down: dict[int, int] = {}
        self.tiles = 0
        self.deltas = 0
        self._driver: Any = None
        self.acked_max = 0
        self.timeout_s = cfg.ack_timeout_s
        self.lost_acked = 0
        self.marker_sightings = 0
        self.motion: MotionNoise = self.sim.config.motion  # the drone's odometry calibration
        self._odo = np.zeros(3)  # wheel odometry since the newest keyframe, and its covariance
        self._odo_cov = np.zeros((3, 3))

    # ------------------------------------------------------------------ transport
    def _connect(self) -> None:
        import zmq

        self._close()
        self.reconnects += 1
        self.sock = zmq.Context.instance().socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(self.server)
        self.welcomed = False
        self.in_flight = 0
        self._send(self.hello())

    def hello(self) -> bytes:
        return encode({"type": "hello", "drone": self.drone, "session": self.session,
                       "dock": [float(v) for v in self.dock]})

    def _close(self) -> None:
        if self.sock is not None:
            self.sock.close(0)
            self.sock = None

    def _send(self, data: bytes) -> None:
        if self.in_flight == 0 or not self.welcomed:
            self.waiting_since = time.monotonic()
        self.sock.send(data)
        self.up[int(self.sim.time_s)] = self.up.get(int(self.sim.time_s), 0) + len(data)

    def pump(self) -> None:
        """Read every waiting reply, send what the window allows, reconnect after a silence."""
        import zmq

        if self.sock is None:
            self._connect()
        while self.sock.poll(0, zmq.POLLIN):
            data = self.sock.recv()
            self.down[int(self.sim.time_s)] = self.down.get(int(self.sim.time_s), 0) + len(data)
            self.deliver(data)
        if self.welcomed:
            for seq, data in self.outbox[self.in_flight: self.config.window]:
                self._send(data)
                self.in_flight += 1
                del seq
        waiting = not self.welcomed or self.in_flight > 0
        if waiting and time.monotonic() - self.waiting_since > self.timeout_s:
            self.log(f"drone {self.drone}: no answer for {self.timeout_s:.0f} s, reconnecting")
            # back off: a busy server must not be buried under resends
            self.timeout_s = min(2 * self.timeout_s, MAX_TIMEOUT_S)
            self._connect()

    def deliver(self, data: bytes) -> None:
        """Take one reply of the server (welcome, ack or error)."""
        try:
            msg = decode(data)
        except ProtocolError as e:
            self.errors.append(f"bad reply: {e}")
            return
        kind = msg["type"]
        self.waiting_since = time.monotonic()
        self.timeout_s = self.config.ack_timeout_s
        if kind == "welcome":
            acked = int(msg["acked_seq"])
            if acked > self.seq:  # this session's id was used by another process: its deltas are not ours
                raise DroneError(f"server {self.server} holds {acked} deltas of drone {self.drone} from this session, "
                                 f"but this drone made {self.seq}; use a new --drone id")
            if acked < self.acked_max:  # the server forgot a delta it acknowledged: must never happen
                self.lost_acked += self.acked_max - acked
                self.errors.append(f"server lost acknowledged deltas {acked + 1}..{self.acked_max}")
            self.outbox = [(s, m) for s, m in self.outbox if s > acked]
            self.welcomed = True
            self.in_flight = 0
        elif kind == "ack":
            seq = int(msg["seq"])
            self.acked_max = max(self.acked_max, seq)
            before = len(self.outbox)
            self.outbox = [(s, m) for s, m in self.outbox if s > seq]
            self.in_flight = max(0, self.in_flight - (before - len(self.outbox)))
            ids = np.frombuffer(msg["ids"], "<u4")
            poses = np.frombuffer(msg["poses"], "<f4").reshape(-1, 3).astype(np.float64)
            if len(ids):
                grow = int(ids.max()) + 1 - len(self.merged)
                if grow > 0:
                    self.merged = np.vstack([self.merged, np.full((grow, 3), np.nan)])
                self.merged[ids] = poses
            self.tiles += len(msg.get("tiles", []))
        elif kind == "error":
            text = f"{msg.get('code')}: {msg.get('message')}"
            if msg.get("code") == "not-registered":
                # the server restarted under this connection (deltas queued in the socket reached it before any
                # hello): not a refusal of our data; say hello again on a fresh connection and resend from the ack
                self.log(f"drone {self.drone}: the server does not know this connection, saying hello again")
                if self.welcomed:
                    self._connect()
                return
            self.errors.append(text)
            if msg.get("code") == "duplicate-drone":
                raise DroneError(f"server {self.server} refused drone {self.drone}: {msg.get('message')}")

    # ------------------------------------------------------------------ flying
    def _collect(self, step_index: int, scan: Any, markers: Any = None) -> None:
        """New keyframes and own loops of the last step into the pending delta (``markers``: the step's floor-marker
        readings, which a keyframe made at this step carries)."""
        n_before = len(self.kf_step)
        steps = self.est.keyframe_steps
        poses = self.est.keyframe_poses
        for k in range(n_before, len(steps)):
            self.kf_step[int(steps[k])] = k
            pts = scan_points(scan, self.est.config.min_range_m, self.est.config.max_range_m)
            self.pending_kf.append({"id": k, "stamp": round(self.sim.time_s, 3), "pose": [float(v) for v in poses[k]],
                                    "desc": pack_descriptor(range_histogram(scan.ranges_m, scan.max_range_m)),
                                    "pts": pack_points(pts)})
            if markers is not None and len(markers) and int(steps[k]) == step_index:
                ids = np.asarray(markers.ids, np.int64)
                sigma = np.full(len(ids), self.est.config.markers.camera.std_m)
                self.pending_kf[-1]["mk"] = pack_markers(ids, markers.xy_m, sigma)
                self.marker_sightings += len(ids)
            self.truth.append(self.sim.pose.copy())
            if k > 0:
                z, info = keyframe_edge(se2.between(poses[k - 1], poses[k]), self._odo,
                                        self._odo_cov + np.diag([1e-6, 1e-6, 1e-8]))
                self.pending_edges.append({"a": k - 1, "b": k, "z": [float(v) for v in z], "info": info_upper(info)})
            self._odo, self._odo_cov = np.zeros(3), np.zeros((3, 3))
        for ev in self.est.estimate().new_loops:
            if ev.accepted and ev.a in self.kf_step and ev.b in self.kf_step:
                self.pending_edges.append({"a": self.kf_step[ev.a], "b": self.kf_step[ev.b],
                                           "z": [float(v) for v in ev.T_a_b],
                                           "info": info_upper(np.diag(np.asarray(LOOP_SIGMA) ** -2))})

    def _queue_delta(self) -> None:
        if not self.pending_kf and not self.pending_edges:
            return
        self.seq += 1
        msg = encode({"type": "delta", "drone": self.drone, "seq": self.seq, "keyframes": self.pending_kf,
                      "edges": self.pending_edges})
        self.outbox.append((self.seq, msg))
        self.pending_kf, self.pending_edges = [], []
        self.deltas += 1

    def _linked(self) -> bool:
        b = self.config.blackout
        return b is None or not (b[0] <= self.sim.time_s < b[0] + b[1])

    @property
    def total_steps(self) -> int:
        return round(self.config.minutes * 60.0 / float(self.sim.config.dt_s or 0.1))

    def advance(self, seconds: float) -> bool:
        """Fly ``seconds`` of simulated time (not past the flight's end) and queue what it produced as one delta;
        False once the flight is over."""
        if self.sim.index >= self.total_steps:
            return False
        end = self.sim.time_s + seconds - 1e-9
        while self.sim.index < self.total_steps and self.sim.time_s < end:
            if self._driver is None:
                self._driver = self.sim.driver()
            v, w = self._driver.command(self.sim.pose, self.sim.world.solid_segments(self.sim.time_s))
            s = self.sim.step(v, w)
            self.est.step(s)
            ja, jb = se2.compose_jacobians(self._odo, s.odometry)
            self._odo_cov = ja @ self._odo_cov @ ja.T + jb @ odometry_covariance(s.odometry, self.motion) @ jb.T
            self._odo = se2.compose(self._odo, s.odometry)
            if s.scan is not None:
                self._collect(s.index, s.scan, s.markers)
        self._queue_delta()
        return True

    def run(self) -> DroneResult:
        """The whole flight over the network: a delta per ``send_every_s``, then wait until all are acked."""
        cfg = self.config
        t0 = time.monotonic()
        try:
            while self.advance(cfg.send_every_s):
                if self._linked():
                    self.pump()
                elif self.sock is not None:
                    self.log(f"drone {self.drone}: link down at t = {self.sim.time_s:.0f} s")
                    self._close()
                if cfg.rate > 0:
                    ahead = self.sim.time_s / cfg.rate - (time.monotonic() - t0)
                    if ahead > 0:
                        time.sleep(ahead)
            self._flush()
        finally:
            self._close()
        return self.result()

    def _flush(self) -> None:
        deadline = time.monotonic() + self.config.flush_timeout_s
        left = len(self.outbox)
        while self.outbox or not self.welcomed:
            if len(self.outbox) < left:  # a busy server that still acknowledges is waited for
                left, deadline = len(self.outbox), time.monotonic() + self.config.flush_timeout_s
            if time.monotonic() > deadline:
                raise DroneError(f"drone {self.drone}: {len(self.outbox)} deltas still unacknowledged, none for "
                                 f"{self.config.flush_timeout_s:.0f} s (is the server at {self.server} running?)")
            self.pump()
            if self.sock is not None:
                self.sock.poll(50)
        self.sock.send(encode({"type": "bye"}))

    def result(self) -> DroneResult:
        secs = int(self.sim.time_s) + 1
        up, down = np.zeros(secs, np.int64), np.zeros(secs, np.int64)
        for k, v in self.up.items():
            up[min(k, secs - 1)] += v
        for k, v in self.down.items():
            down[min(k, secs - 1)] += v
        n = len(self.truth)
        merged = np.full((n, 3), np.nan)
        merged[: min(n, len(self.merged))] = self.merged[:n]
        self.est.finalize()
        return DroneResult(self.drone, self.sim.index, n, self.deltas, max(self.reconnects, 0), self.errors, up, down,
                           np.asarray(self.truth).reshape(-1, 3), self.est.keyframe_poses[:n].copy(), merged,
                           self.tiles, {"lost_acked": self.lost_acked, "acked_max": self.acked_max,
                                        "dock": self.dock.tolist(), "marker_sightings": self.marker_sightings,
                                        "marker_resightings": self.est.markers.resightings})
