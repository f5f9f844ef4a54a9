"""Synthetic pose graphs for tests, benchmarks and the lab: a Manhattan-style walk with loop closures, and
generated false loop closures (outliers) to show what robust kernels do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.geometry import se2
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.initialization import spanning_tree_poses

Array = NDArray[np.float64]


@dataclass
class SyntheticGraph:
    """A generated problem. Shapes: truth (P, 3); odometry_chain (P, 3)."""

    graph: FactorGraph
    truth: Values
    initial: Values
    num_loop_closures: int
    sigmas: tuple[float, float, float]


def _information(sigmas: tuple[float, float, float]) -> Array:
    return np.diag(1.0 / np.square(sigmas))


def manhattan_walk(rng: np.random.Generator, *, num_poses: int = 300, grid_m: float = 1.0, world_cells: int = 6,
                   sigmas: tuple[float, float, float] = (0.05, 0.05, 0.01), loop_radius_m: float = 0.5,
                   max_loops_per_pose: int = 2) -> SyntheticGraph:
    """A robot stepping one grid cell per pose (turning left/right/straight at random, bouncing off the world
    border); odometry and loop closures (between poses closer than ``loop_radius_m``, at least 10 steps apart) are
    ground-truth relative poses plus Gaussian noise with standard deviations ``sigmas`` (m, m, rad)."""
    truth = np.zeros((num_poses, 3))
    for k in range(1, num_poses):
        turn = rng.choice([-np.pi / 2, 0.0, 0.0, np.pi / 2])
        th = se2.wrap_angle(truth[k - 1, 2] + turn)
        nxt = truth[k - 1, :2] + grid_m * np.array([np.cos(th), np.sin(th)])
        if np.any(np.abs(nxt) > world_cells * grid_m):
            th = se2.wrap_angle(th + np.pi)
            nxt = truth[k - 1, :2] + grid_m * np.array([np.cos(th), np.sin(th)])
        truth[k] = [nxt[0], nxt[1], th]
    om = _information(sigmas)
    noise = rng.standard_normal((num_poses - 1, 3)) * np.asarray(sigmas)
    z = se2.between(truth[:-1], truth[1:]) + noise
    g = FactorGraph()
    keys = np.arange(num_poses)
    g.add_between(keys[:-1], keys[1:], z, om)
    d = np.hypot(truth[:, None, 0] - truth[None, :, 0], truth[:, None, 1] - truth[None, :, 1])
    ii, jj = np.nonzero((d < loop_radius_m) & (keys[None, :] - keys[:, None] >= 10))
    # keep at most max_loops_per_pose closures per later pose
    keep = np.zeros(ii.size, bool)
    counts: dict[int, int] = {}
    for e in rng.permutation(ii.size):
        if counts.get(int(jj[e]), 0) < max_loops_per_pose:
            keep[e] = True
            counts[int(jj[e])] = counts.get(int(jj[e]), 0) + 1
    ii, jj = ii[keep], jj[keep]
    if ii.size:
        zl = se2.between(truth[ii], truth[jj]) + rng.standard_normal((ii.size, 3)) * np.asarray(sigmas)
        g.add_between(ii, jj, zl, om)
    init = Values(keys, spanning_tree_poses(g, keys))
    return SyntheticGraph(g, Values(keys, truth), init, int(ii.size), sigmas)


def false_loop_closures(rng: np.random.Generator, num_poses: int, count: int, *, min_gap: int = 20,
                        spread_m: float = 3.0) -> tuple[NDArray[np.int64], NDArray[np.int64], Array]:
    """``count`` wrong loop closures between random pose pairs at least ``min_gap`` apart, each claiming a random
    relative pose within ``spread_m`` (so they look like plausible, confident closures). Returns (i, j, z)."""
    i = rng.integers(0, num_poses - min_gap, size=count)
    j = i + rng.integers(min_gap, num_poses - i)
    j = np.minimum(j, num_poses - 1)
    z = np.column_stack([rng.uniform(-spread_m, spread_m, (count, 2)), rng.uniform(-np.pi, np.pi, count)])
    return i.astype(np.int64), j.astype(np.int64), z
