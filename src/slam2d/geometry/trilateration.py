"""Placing a point from ranges to known positions (range-only beacons)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def trilaterate(positions: ArrayLike, ranges: ArrayLike) -> Array:
    """Least-squares point from ranges to known positions (K>=3 not collinear): subtract the first equation.

    Linear (no start needed) but not the maximum-likelihood point; :func:`refine_point` improves it.
    Shapes: (K,2),(K,) -> (2,).
    """
    p, r = np.asarray(positions, dtype=np.float64), np.asarray(ranges, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or r.shape != (p.shape[0],):
        raise ValueError(f"trilaterate: positions must be (K, 2) and ranges (K,), got {p.shape} and {r.shape}")
    if len(p) < 3:
        raise ValueError(f"trilateration needs >= 3 ranges (got {len(p)})")
    a = 2 * (p[1:] - p[0])
    b = np.sum(p[1:] ** 2, axis=1) - np.sum(p[0] ** 2) - r[1:] ** 2 + r[0] ** 2
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    return np.asarray(sol, dtype=np.float64)


def refine_point(positions: ArrayLike, ranges: ArrayLike, start: ArrayLike, *,
                 iterations: int = 10) -> tuple[Array, Array]:
    """Gauss-Newton on ``sum (|x - p_k| - r_k)^2`` from ``start``; returns the point and ``(J^T J)^-1``
    (multiply by the range variance for the point's covariance). Shapes: (K,2),(K,),(2,) -> (2,),(2,2)."""
    p, r = np.asarray(positions, dtype=np.float64), np.asarray(ranges, dtype=np.float64)
    x = np.asarray(start, dtype=np.float64).copy()
    jtj = np.eye(2)
    for _ in range(iterations):
        d = x - p
        n = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        J = d / n[:, None]
        jtj = J.T @ J
        step = np.linalg.solve(jtj, J.T @ (r - n))
        x += step
        if float(np.hypot(*step)) < 1e-9:
            break
    return x, np.asarray(np.linalg.inv(jtj), dtype=np.float64)
