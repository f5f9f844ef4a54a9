"""Drivers that turn the robot's situation into (v, w) commands: waypoints, auto-explore, or manual."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.geometry.angles import angle_diff
from slam2d.models.lidar import cast_rays

Array = NDArray[np.float64]


@dataclass
class WaypointFollower:
    """Steer toward each waypoint in turn (proportional heading control, slowing in sharp turns); loops forever."""

    waypoints: Array
    speed_mps: float
    max_turn_rate_rps: float = 1.2
    reach_m: float = 0.6
    gain: float = 2.0
    index: int = 0

    def command(self, pose: Array, world_segments: Array | None = None) -> tuple[float, float]:
        target = self.waypoints[self.index % len(self.waypoints)]
        if np.hypot(*(target - pose[:2])) < self.reach_m:
            self.index += 1
            target = self.waypoints[self.index % len(self.waypoints)]
        err = float(angle_diff(np.arctan2(target[1] - pose[1], target[0] - pose[0]), pose[2]))
        w = float(np.clip(self.gain * err, -self.max_turn_rate_rps, self.max_turn_rate_rps))
        v = self.speed_mps * max(0.15, np.cos(err)) if abs(err) < 1.2 else 0.1 * self.speed_mps
        return v, w


@dataclass
class AutoExplorer:
    """Wander: drive straight, jitter the heading now and then, and steer away from walls seen by feeler rays.

    Seven feelers (straight ahead, +-0.3, +-0.6 and +-1.2 rad) look for walls. Too close ahead or at the front
    corners: turn toward the more open side, and keep turning that way until the way is clear (no dithering in
    corners); very close ahead: turn on the spot. ``world_segments`` should include the world's edge
    (:meth:`World.solid_segments`) so that open worlds are explored too.
    """

    speed_mps: float
    rng: np.random.Generator
    clearance_m: float = 1.8
    max_turn_rate_rps: float = 1.2
    _turn: float = field(default=0.0)
    _avoid: float = field(default=0.0)

    FEELERS = np.array([-1.2, -0.6, -0.3, 0.0, 0.3, 0.6, 1.2])

    def command(self, pose: Array, world_segments: Array | None = None) -> tuple[float, float]:
        segs = np.zeros((0, 4)) if world_segments is None else world_segments
        feel = cast_rays(pose, self.FEELERS, segs, 10.0)
        ahead = float(feel[2:5].min())
        if ahead < self.clearance_m or min(feel[1], feel[5]) < 0.6 * self.clearance_m or \
                min(feel[0], feel[6]) < 0.25 * self.clearance_m:
            if self._avoid == 0.0:  # choose a side once, then keep it until the way is clear
                self._avoid = 1.0 if feel[4:].sum() >= feel[:3].sum() else -1.0
            v = 0.0 if ahead < 0.5 * self.clearance_m else 0.2 * self.speed_mps
            return v, self._avoid * self.max_turn_rate_rps
        self._avoid = 0.0
        if self.rng.random() < 0.05:
            self._turn = float(self.rng.uniform(-0.6, 0.6))
        return self.speed_mps, self._turn


@dataclass
class ManualDriver:
    """Replay a fixed array of (v, w) commands; the last one repeats."""

    commands: Array

    _i: int = 0

    def command(self, pose: Array, world_segments: Array | None = None) -> tuple[float, float]:
        c = self.commands[min(self._i, len(self.commands) - 1)]
        self._i += 1
        return float(c[0]), float(c[1])
