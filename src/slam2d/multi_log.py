"""``MultiRobotLog``: several robots recorded on one clock, and the sightings the robots made of each other.

Every robot keeps its own :class:`~slam2d.log.Log` (odometry, landmark observations, its ground truth), and all of
them share ONE step grid (identical ``stamps_s``): step ``t`` of robot a and step ``t`` of robot b are the same
instant. Robot-robot sightings (range and bearing from the observer to the observed robot, taken at the observer's
pose ``step``) are a separate table, because they constrain two robots' poses at once and no single-robot estimator
can use them. Ground truth, as in ``Log``, is never handed to an estimator by the runner.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.log import Log, Step

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class RobotSightings:
    """Range-bearing sightings of one robot by another, sorted by step.

    Shapes (S sightings): step (S,) int in 1..T (the pose index of both robots at that instant), observer (S,) int
    and observed (S,) int robot ids (as in ``MultiRobotLog.robots``), range_m (S,), bearing_rad (S,) in the
    observer's frame.
    """

    step: IntArray
    observer: IntArray
    observed: IntArray
    range_m: Array
    bearing_rad: Array

    def __post_init__(self) -> None:
        n = self.step.shape[0]
        for name in ("observer", "observed", "range_m", "bearing_rad"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"RobotSightings.{name} must have shape ({n},), got {getattr(self, name).shape}")
        if n and np.any(np.diff(self.step) < 0):
            raise ValueError("RobotSightings.step must be sorted")
        if np.any(self.observer == self.observed):
            raise ValueError("RobotSightings: a robot cannot sight itself")
        if np.any(~(self.range_m > 0)) or not np.all(np.isfinite(self.bearing_rad)):
            raise ValueError("RobotSightings: ranges must be > 0 and bearings finite")

    def __len__(self) -> int:
        return int(self.step.shape[0])

    @staticmethod
    def empty() -> RobotSightings:
        z = np.zeros(0, dtype=np.int64)
        return RobotSightings(z, z.copy(), z.copy(), np.zeros(0), np.zeros(0))

    def subset(self, mask: NDArray[np.bool_] | IntArray | slice) -> RobotSightings:
        return RobotSightings(self.step[mask], self.observer[mask], self.observed[mask], self.range_m[mask],
                              self.bearing_rad[mask])

    @property
    def z(self) -> Array:
        """(S, 2) array of [range, bearing]."""
        return np.stack([self.range_m, self.bearing_rad], axis=-1)


@dataclass(frozen=True)
class MultiStep:
    """Everything a multi-robot estimator may see at step ``index``: each robot's :class:`Step` (in the order of
    ``MultiRobotLog.robots``) and the robot-robot sightings taken at that instant."""

    index: int
    steps: tuple[Step, ...]
    sightings: RobotSightings


@dataclass(frozen=True, eq=False)
class MultiRobotLog:
    """Several robots on one step grid: ``logs[i]`` belongs to robot ``robots[i]``; ``sightings`` between them.

    Invariants (checked): every log has the same ``stamps_s`` (T+1,), robot ids are unique, and every sighting names
    two listed robots and a step in 1..T. ``metadata`` is JSON-serialisable (dataset, robots, clock origin, counts).
    """

    robots: tuple[int, ...]
    logs: tuple[Log, ...]
    sightings: RobotSightings = field(default_factory=RobotSightings.empty)
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.robots) != len(self.logs) or not self.logs:
            raise ValueError(f"MultiRobotLog: {len(self.robots)} robot ids for {len(self.logs)} logs (need >= 1)")
        if len(set(self.robots)) != len(self.robots):
            raise ValueError(f"MultiRobotLog: duplicate robot ids {self.robots}")
        ref = self.logs[0].stamps_s
        for r, log in zip(self.robots, self.logs, strict=True):
            if log.stamps_s.shape != ref.shape or not np.array_equal(log.stamps_s, ref):
                raise ValueError(f"MultiRobotLog: robot {r} is not on the shared step grid")
        s = self.sightings
        if len(s):
            known = np.asarray(self.robots)
            bad = ~(np.isin(s.observer, known) & np.isin(s.observed, known))
            if np.any(bad):
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(f"MultiRobotLog: sighting {i} names robot {int(s.observer[i])} -> "
                                 f"{int(s.observed[i])}, not in {self.robots}")
            if s.step[0] < 1 or s.step[-1] > self.num_steps:
                raise ValueError(f"MultiRobotLog: sighting steps must be within 1..{self.num_steps}")

    @property
    def stamps_s(self) -> Array:
        return self.logs[0].stamps_s

    @property
    def num_steps(self) -> int:
        return self.logs[0].num_steps

    def __len__(self) -> int:
        return self.num_steps

    def log_of(self, robot: int) -> Log:
        """The single-robot log of robot ``robot`` (KeyError naming the valid ids)."""
        if robot not in self.robots:
            raise KeyError(f"robot {robot} not in this log (robots {self.robots})")
        return self.logs[self.robots.index(robot)]

    def step(self, index: int) -> MultiStep:
        """The estimator-facing record of step ``index`` (1..T)."""
        starts = np.searchsorted(self.sightings.step, [index, index + 1])
        return MultiStep(index, tuple(log.step(index) for log in self.logs),
                         self.sightings.subset(slice(int(starts[0]), int(starts[1]))))

    def __iter__(self) -> Iterator[MultiStep]:
        for i in range(1, self.num_steps + 1):
            yield self.step(i)

    def head(self, steps: int) -> MultiRobotLog:
        """The first ``steps`` steps of every robot, and the sightings up to then (a new MultiRobotLog)."""
        steps = min(int(steps), self.num_steps)
        return dataclasses.replace(self, logs=tuple(log.head(steps) for log in self.logs),
                                   sightings=self.sightings.subset(self.sightings.step <= steps))
