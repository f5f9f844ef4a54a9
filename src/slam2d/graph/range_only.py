"""Batch range-only graph SLAM (Plaza-style radio beacons): odometry factors plus range factors to beacons.

Ranges carry no bearing, so a beacon cannot be placed from one sighting. Its first estimate comes from linear
trilateration against the dead-reckoned path (differences of squared-range equations, solved by least squares);
then the whole graph -- every pose and every beacon -- is optimised with Levenberg-Marquardt, with a robust kernel on
the ranges because radio ranges have multipath outliers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.estimator import Estimate, EstimatorLifecycle
from slam2d.geometry import se2
from slam2d.geometry.trilateration import trilaterate
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.optimizer import OptimizerConfig, Summary, optimize
from slam2d.log import Log, Step
from slam2d.models.motion import ODOMETRY_FLOOR_VAR, MotionNoise, odometry_factor
from slam2d.models.sensors import SensorConfig

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class RangeOnlyConfig:
    """Range-only batch SLAM settings."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise (the log's, by default)."""
    range_std_m: float = 1.0
    """range noise standard deviation (m)."""
    range_bias_m: float = 0.0
    """constant range offset subtracted from every measurement (m), e.g. a calibrated radio delay."""
    robust_kernel: str = "huber"
    """kernel on the range factors: none, huber, cauchy or dcs."""
    robust_param: float = 1.5
    """kernel parameter in units of the whitened error."""

    def __post_init__(self) -> None:
        if not self.range_std_m > 0:
            raise ValueError(f"RangeOnlyConfig.range_std_m must be > 0 (got {self.range_std_m})")
        if self.robust_kernel not in ("none", "huber", "cauchy", "dcs"):
            raise ValueError(f"RangeOnlyConfig.robust_kernel must be none, huber, cauchy or dcs "
                             f"(got {self.robust_kernel!r})")


@dataclass(frozen=True)
class RangeOnlyResult:
    """Optimised trajectory (T+1,3), beacon positions (B,2) with their ids (B,), the dead-reckoned start, summary."""

    trajectory: Array
    beacons: Array
    beacon_ids: NDArray[np.int64]
    dead_reckoning: Array
    summary: Summary | None
    """None when no beacon could be placed (the trajectory is then the dead-reckoned one)."""


def range_only_slam(log: Log, config: RangeOnlyConfig | None = None) -> RangeOnlyResult:
    """Batch range-only SLAM over a whole log whose observations are ranges to identified beacons."""
    return solve_range_only(log.initial_pose, log.odometry, log.obs_step, log.obs_id, log.obs_range_m,
                            config or RangeOnlyConfig())


def solve_range_only(initial_pose: Array, odometry: Array, obs_step: NDArray[np.int64], obs_id: NDArray[np.int64],
                     obs_range: Array, cfg: RangeOnlyConfig) -> RangeOnlyResult:
    """The batch problem from arrays. Shapes: (3,), (T,3), (K,), (K,), (K,)."""
    dr = se2.compose_chain(initial_pose, odometry)
    known = obs_id >= 0
    # a beacon ranged fewer than 3 times cannot be placed: its ranges are left out
    counts = dict(zip(*np.unique(obs_id[known], return_counts=True), strict=True))
    known &= np.array([counts.get(int(i), 0) >= 3 for i in obs_id], dtype=bool)
    if not np.any(known):
        return RangeOnlyResult(dr, np.zeros((0, 2)), np.zeros(0, np.int64), dr, None)
    steps, ids = obs_step[known], obs_id[known]
    ranges = obs_range[known] - cfg.range_bias_m
    beacon_ids = np.unique(ids)
    beacons = np.array([trilaterate(dr[steps[ids == b], :2], ranges[ids == b]) for b in beacon_ids])

    graph = FactorGraph()
    t = np.arange(1, len(odometry) + 1)
    # a standstill's odometry covariance is zero (MRCLAM logs many): only those steps get the floor
    still = ~np.any(odometry != 0, axis=1)
    odo_info = np.empty((len(odometry), 3, 3))
    odo_info[~still] = odometry_factor(odometry[~still], cfg.motion)[1]
    odo_info[still] = odometry_factor(odometry[still], cfg.motion, floor_var=ODOMETRY_FLOOR_VAR)[1]
    graph.add_between(t - 1, t, np.array(odometry, dtype=np.float64), odo_info)
    info = np.full((len(steps), 1, 1), 1.0 / cfg.range_std_m**2)
    kernel = None if cfg.robust_kernel == "none" else cfg.robust_kernel
    graph.add_range(steps, ids, ranges[:, None], info, robust=kernel, robust_param=cfg.robust_param)
    values = Values(np.arange(len(odometry) + 1), dr, beacon_ids, beacons)
    out, summary = optimize(graph, values, OptimizerConfig(method="lm", max_iterations=500))
    order = np.argsort(out.point_keys)
    return RangeOnlyResult(out.poses, out.points[order], out.point_keys[order].astype(np.int64), dr, summary)


@dataclass(frozen=True, slots=True, kw_only=True)
class RangeOnlyGraphConfig:
    """``--estimator range-only-graph``: dead reckoning while driving, the batch range-only optimum at the end."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise (filled from the log's metadata)."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """the range sensor (its ``range_std_m`` is used; filled from the log's metadata)."""
    range_bias_m: float = 0.0
    """constant range offset subtracted from every measurement (m)."""
    robust_kernel: str = "huber"
    """kernel on the range factors."""

    def __post_init__(self) -> None:
        RangeOnlyConfig(range_std_m=self.sensor.range_std_m, robust_kernel=self.robust_kernel)  # same rules


class RangeOnlyGraph(EstimatorLifecycle):
    """Estimator-protocol shell: records odometry and ranges, solves the batch problem in ``finalize``."""

    def __init__(self, config: RangeOnlyGraphConfig | None = None) -> None:
        self.config = config or RangeOnlyGraphConfig()

    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        self._start = np.asarray(initial_pose, dtype=np.float64).copy()
        self._pose = self._start.copy()
        self._odo: list[Array] = []
        self._obs: list[tuple[int, NDArray[np.int64], Array]] = []
        self._result: RangeOnlyResult | None = None
        self._lifecycle_reset()

    def step(self, step: Step) -> None:
        self._check_step()
        self._pose = se2.compose(self._pose, step.odometry)
        self._odo.append(np.asarray(step.odometry, dtype=np.float64))
        if len(step.observations):
            self._obs.append((step.index, step.observations.landmark_id, step.observations.range_m))
        self._result = None

    def finalize(self) -> None:
        if not self._lifecycle_finalize():
            return
        c = self.config
        steps = np.concatenate([np.full(len(i), s) for s, i, _ in self._obs]).astype(np.int64) if self._obs else \
            np.zeros(0, np.int64)
        ids = np.concatenate([i for _, i, _ in self._obs]).astype(np.int64) if self._obs else np.zeros(0, np.int64)
        rng_ = np.concatenate([r for _, _, r in self._obs]) if self._obs else np.zeros(0)
        cfg = RangeOnlyConfig(motion=c.motion, range_std_m=c.sensor.range_std_m, range_bias_m=c.range_bias_m,
                              robust_kernel=c.robust_kernel)
        self._result = solve_range_only(self._start, np.array(self._odo).reshape(-1, 3), steps, ids, rng_, cfg)

    def estimate(self) -> Estimate:
        self._check_ready()
        r = self._result
        if r is None:
            return Estimate(pose=self._pose.copy())
        return Estimate(pose=r.trajectory[-1].copy(), landmarks=r.beacons.copy(), landmark_ids=r.beacon_ids.copy(),
                        trajectory=r.trajectory.copy(), state_dim=int(r.trajectory.size + r.beacons.size))
