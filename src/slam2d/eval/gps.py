"""Scoring a trajectory against sparse GPS fixes (datasets whose only truth is GPS, e.g. Victoria Park).

The GPS frame differs from the estimate's frame, so positions are aligned first (SE(2) least squares, as ATE).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from slam2d.eval.trajectory import ATEResult, ate
from slam2d.log import Log


def gps_ate(trajectory: ArrayLike, log: Log, *, align: bool = True) -> ATEResult:
    """Position errors at the log's GPS steps after SE(2) alignment of the trajectory onto the GPS fixes.

    Shapes: trajectory (T+1,3) (one pose per step of ``log``). Raises ValueError when the log has fewer than two
    GPS fixes or the trajectory length does not match the log. ``errors_m`` are per fix; ``rmse_m`` is the ATE.
    """
    traj = np.asarray(trajectory, dtype=np.float64)
    if traj.ndim != 2 or traj.shape != (log.num_steps + 1, 3):
        raise ValueError(f"trajectory must have shape ({log.num_steps + 1}, 3) for this log, got {traj.shape}")
    if log.gps_step is None or log.gps_xy is None or log.gps_step.size < 2:
        raise ValueError("the log has fewer than two GPS fixes")
    est = traj[log.gps_step]
    return ate(est, np.column_stack([log.gps_xy, np.zeros(len(log.gps_xy))]), align=align)
