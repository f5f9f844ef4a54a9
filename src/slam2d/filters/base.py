"""The one estimator protocol shared by every back end, and the immutable snapshot it returns.

    est = SomeEstimator(SomeConfig(...))   # configuration only
    est.reset(initial_pose, rng=rng)       # fresh state
    for step in log:                       # odometry + observations (+ scan, gps) of one step; never ground truth
        est.step(step)
        snap = est.estimate()              # immutable snapshot

History is kept by the runner (``slam2d.lab.runner``), not by estimators. An estimator may also offer
``finalize()``: the runner calls it once after the last step (smoothers optimise to convergence there).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from slam2d.log import Step

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Estimate:
    """A snapshot of an estimator's belief after a step.

    Shapes: pose (3,), pose_cov (3,3) or None, landmarks (L,2), landmark_covs (L,2,2) or None, landmark_ids (L,) int
    (the estimator's own ids; for ``known`` association they equal the source's ids).
    ``extras`` carries back-end specific views, by convention:
    ``trajectory`` (T+1,3) when the back end re-estimates past poses (graph SLAM), ``state_dim`` (int),
    ``particles`` (M,3), ``n_eff`` (float), ``graph`` (nodes/edges for drawing), ``assoc`` (per-observation ids).
    """

    pose: Array
    pose_cov: Array | None = None
    landmarks: Array = field(default_factory=lambda: np.zeros((0, 2)))
    landmark_covs: Array | None = None
    landmark_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    extras: Mapping[str, Any] = field(default_factory=dict)


@runtime_checkable
class Estimator(Protocol):
    """What the runner, the lab and the web page need from a back end."""

    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        """Start afresh at ``initial_pose`` (3,), using ``rng`` for any randomness."""

    def step(self, step: Step) -> None:
        """Consume one step's odometry and measurements."""

    def estimate(self) -> Estimate:
        """The current belief as an immutable snapshot."""
