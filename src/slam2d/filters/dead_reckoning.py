"""Dead reckoning: integrate odometry, propagate the pose covariance, ignore every landmark.

It is the baseline every SLAM back end must beat, and the "drift" lesson of the lab.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.estimator import Estimate, EstimatorLifecycle
from slam2d.log import Step
from slam2d.models.motion import MotionNoise, odometry_covariance, odometry_predict, odometry_predict_jacobians

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class DeadReckoningConfig:
    """Dead-reckoning settings."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise assumed by the filter (defaults to the log's, when the log records it)."""


def dead_reckoning_step(pose: Array, cov: Array, u: Array, noise: MotionNoise) -> tuple[Array, Array]:
    """One prediction: ``x' = x (+) u``, ``P' = G P G^T + V Q V^T``. Shapes: (3,),(3,3),(3,) -> (3,),(3,3)."""
    g, v = odometry_predict_jacobians(pose, u)
    q = odometry_covariance(u, noise)
    new_cov = g @ cov @ g.T + v @ q @ v.T
    return odometry_predict(pose, u), 0.5 * (new_cov + new_cov.T)


class DeadReckoning(EstimatorLifecycle):
    """Odometry integration with covariance propagation (implements the estimator protocol)."""

    def __init__(self, config: DeadReckoningConfig | None = None) -> None:
        self.config = config or DeadReckoningConfig()
        self._pose = np.zeros(3)
        self._cov = np.zeros((3, 3))

    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        self._pose = np.asarray(initial_pose, dtype=np.float64).copy()
        self._cov = np.zeros((3, 3))
        self._lifecycle_reset()

    def step(self, step: Step) -> None:
        self._check_step()
        self._pose, self._cov = dead_reckoning_step(self._pose, self._cov, step.odometry, self.config.motion)

    def estimate(self) -> Estimate:
        self._check_ready()
        return Estimate(pose=self._pose.copy(), pose_cov=self._cov.copy())

    def finalize(self) -> None:
        self._lifecycle_finalize()
