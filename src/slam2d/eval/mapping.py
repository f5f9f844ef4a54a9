"""Landmark map error: associate estimated to true landmarks one-to-one, then measure the matched distances.

Estimated landmark ids are the estimator's own and need not equal the world's, so the association is geometric: the
assignment minimising the total distance (Hungarian method, ``scipy.optimize.linear_sum_assignment``) among pairs
closer than ``max_distance_m``. Estimated landmarks left unmatched are *spurious*; true ones left unmatched are
*missed*. Optionally the estimated map is first moved by the ATE alignment, so that a map that is right up to the
same rigid motion as its trajectory is not penalised for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from slam2d.geometry import se2

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class MapError:
    """Result of :func:`map_error`.

    Shapes: pairs (K,2) int rows ``(estimated index, true index)``; errors_m (K,) distances of the matched pairs.
    """

    pairs: IntArray
    errors_m: Array
    spurious: int
    missed: int

    @property
    def matched(self) -> int:
        return int(self.pairs.shape[0])

    @property
    def rmse_m(self) -> float:
        """Root mean square distance of the matched pairs (nan when nothing matched)."""
        return float(np.sqrt(np.mean(self.errors_m**2))) if self.errors_m.size else float("nan")


def _points(a: ArrayLike, name: str) -> Array:
    """``a`` as finite (L, 2) positions (an empty array of any shape is no points); ValueError naming ``name``."""
    p = np.asarray(a, dtype=np.float64)
    if p.size == 0:
        return np.zeros((0, 2))
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"{name} must have shape (L, 2) (one landmark per row), got {p.shape}")
    bad = ~np.all(np.isfinite(p), axis=1)
    if np.any(bad):
        raise ValueError(f"{name} landmark {int(np.flatnonzero(bad)[0])} has a non-finite position")
    return p


def map_error(estimated: ArrayLike, truth: ArrayLike, *, max_distance_m: float = 2.0,
              alignment: ArrayLike | None = None) -> MapError:
    """Match estimated landmarks to true ones (one-to-one, each pair closer than ``max_distance_m``) and score.

    ``alignment`` is a pose ``[tx, ty, theta]`` applied to the estimated positions first (e.g.
    ``ate(...).alignment``). Shapes: (L,2),(N,2) -> :class:`MapError`.
    """
    if not max_distance_m > 0:
        raise ValueError(f"max_distance_m must be > 0 (got {max_distance_m})")
    est = _points(estimated, "estimated")
    ref = _points(truth, "truth")
    if alignment is not None:
        tf = np.asarray(alignment, dtype=np.float64)
        if tf.shape != (3,) or not np.all(np.isfinite(tf)):
            raise ValueError(f"alignment must be a finite pose [tx, ty, theta], got {tf.tolist()}")
        if est.shape[0]:
            est = se2.transform_points(tf, est)
    if est.shape[0] == 0 or ref.shape[0] == 0:
        return MapError(np.zeros((0, 2), dtype=np.int64), np.zeros(0), int(est.shape[0]), int(ref.shape[0]))
    d = np.hypot(est[:, None, 0] - ref[None, :, 0], est[:, None, 1] - ref[None, :, 1])
    allowed = d <= max_distance_m
    # Pairs beyond the gate get a cost larger than any feasible assignment could save, so the solver never prefers
    # them; any that it is forced to use (rectangular problems are fine, but a row may have no allowed column) are
    # dropped afterwards.
    big = 1.0 + max_distance_m * (min(est.shape[0], ref.shape[0]) + 1)
    cost = np.where(allowed, d, big)
    rows, cols = linear_sum_assignment(cost)
    keep = allowed[rows, cols]
    rows, cols = rows[keep], cols[keep]
    pairs = np.stack([rows, cols], axis=-1).astype(np.int64)
    return MapError(pairs, d[rows, cols], int(est.shape[0] - len(rows)), int(ref.shape[0] - len(rows)))
