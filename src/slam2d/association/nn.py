"""Nearest neighbour in measurement space: the naive baseline.

Each observation independently takes the candidate closest in plain Euclidean distance over [range (m),
bearing (rad)] stacked (bearing difference through ``angle_diff``), if that distance is at most ``nn_max_distance``.
There is deliberately no covariance and no mutual exclusion: two observations may claim the same landmark, which
is the failure the other methods exist to prevent. Unmatched observations follow the shared NEW / CLUTTER rule.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam2d.association.gating import Problem

IntArray = NDArray[np.int64]


def nearest_neighbour(problem: Problem, max_distance: float) -> tuple[IntArray, IntArray]:
    """Returns (obs (n,), cand (n,)) sorted by observation. Shapes: vectorised over the (K, L) distance matrix."""
    if problem.num_obs == 0 or problem.num_candidates == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    dist = np.sqrt(np.sum(problem.nu * problem.nu, axis=-1))
    dist = np.where(problem.allowed, dist, np.inf)
    best = np.argmin(dist, axis=1)
    ok = dist[np.arange(problem.num_obs), best] <= max_distance
    return np.flatnonzero(ok).astype(np.int64), best[ok].astype(np.int64)
