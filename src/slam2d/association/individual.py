"""Individual compatibility with mutual exclusion (the ``mahalanobis`` method).

A pair is a candidate match when it passes the 2-dof chi-square gate (and the descriptor gate); among those, one
optimal assignment picks the matching with the most pairs and, among those, the least total squared Mahalanobis
distance, so no landmark is ever taken by two observations. Correlations between landmarks are ignored: that is
what ``jcbb`` and ``ransac`` add.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam2d.association.gating import Problem, max_matching

IntArray = NDArray[np.int64]


def individual_compatibility(problem: Problem) -> tuple[IntArray, IntArray]:
    """Returns (obs (n,), cand (n,)) sorted by observation."""
    return max_matching(problem.d2, problem.ic)
