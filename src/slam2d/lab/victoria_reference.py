"""Victoria Park: check a run on the raw log against the processed graph file (``victoriaPark.txt``).

The processed file is the same drive with the association solved by another tree detector; from its odometry chain,
Gauss-Newton-type solvers stop in poor stationary points (chi2 503276 with LM, 250028 with dog leg; see the graph
tests). Started instead from an estimate made on the raw log with unknown association, LM reaches a far lower
minimum (chi2 6183.93 from every estimator tried: the start only has to be in its wide basin), and the estimate
can then be scored against that optimum: its trajectory pose by pose, its map landmark by landmark. Poses are
matched to raw steps by distance travelled (:func:`slam2d.io.datasets.victoria.processed_pose_steps`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.eval.gps import gps_ate
from slam2d.eval.mapping import MapError, map_error
from slam2d.eval.trajectory import ate
from slam2d.geometry import se2
from slam2d.graph import OptimizerConfig, Values, chi2, optimize
from slam2d.graph.initialization import initial_points
from slam2d.io import read_graph
from slam2d.io.datasets.victoria import CAR_B_M, processed_pose_steps
from slam2d.log import Log

Array = NDArray[np.float64]

PROCESSED_FILE = "victoriaPark.txt"


@dataclass(frozen=True)
class ReferenceResult:
    """What :func:`compare_with_processed_graph` found. Trajectory errors are in metres."""

    chi2_initial: float
    """chi2 of the processed graph at the estimate-derived start."""
    chi2_final: float
    """chi2 of the optimum reached from there (LM)."""
    optimum: Values
    """the optimum: rear-axle poses and landmarks of the processed file, in its frame."""
    steps: NDArray[np.int64]
    """raw log step of each processed pose."""
    trajectory_vs_optimum_m: Array
    """per processed pose: distance of the estimate (SE(2)-aligned, laser frame) to the optimum's laser pose."""
    map_vs_optimum: MapError
    """the estimate's landmarks (same alignment) against the optimum's, one-to-one within ``max_distance_m``."""
    optimum_gps_ate_m: float
    """GPS ATE of the optimum's laser poses (for scale: the GPS has jumps of tens of metres)."""


def compare_with_processed_graph(log: Log, trajectory: ArrayLike, landmarks: ArrayLike, *,
                                 processed_path: str | Path | None = None,
                                 max_distance_m: float = 5.0) -> ReferenceResult:
    """Solve the processed graph from ``trajectory`` (T+1, 3) laser poses of ``log`` and compare.

    ``log`` is the raw Victoria Park log the estimate was made on (its metadata names the dataset folder and the
    laser offset); ``landmarks`` (L, 2) the estimate's map. ``processed_path`` defaults to the staged file next to
    the raw folder.
    """
    folder = Path(log.metadata["dataset_path"])
    path = Path(processed_path) if processed_path is not None else folder.parent / PROCESSED_FILE
    gf = read_graph(path)
    steps = processed_pose_steps(folder, gf.values.poses)
    laser = np.array([log.metadata["vehicle"]["a_m"], CAR_B_M, 0.0])
    est = np.asarray(trajectory, dtype=np.float64)
    rear = se2.compose(est[steps], se2.inverse(laser))
    rear = se2.compose(se2.inverse(rear[0]), rear)  # the processed frame: its first pose at the origin
    start = Values(gf.values.pose_keys, rear, gf.values.point_keys,
                   initial_points(gf.graph, gf.values.pose_keys, rear, gf.values.point_keys))
    c0 = chi2(gf.graph, start)
    out, stats = optimize(gf.graph, start, OptimizerConfig(relative_decrease_tol=1e-10, max_iterations=300))
    opt_laser = se2.compose(out.poses, laser)
    a = ate(est[steps], opt_laser)
    lm = map_error(np.asarray(landmarks, dtype=np.float64).reshape(-1, 2), out.points, alignment=a.alignment,
                   max_distance_m=max_distance_m)
    # the optimum on the raw steps (held between matched poses) for the GPS score
    order = np.searchsorted(steps, np.arange(log.num_steps + 1), side="right") - 1
    full = opt_laser[order.clip(0, steps.size - 1)]
    return ReferenceResult(c0, stats.chi2_final, out, steps, a.errors_m, lm, gps_ate(full, log).rmse_m)
