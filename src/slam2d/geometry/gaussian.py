"""Gaussian helpers as numbers: Mahalanobis distances, chi-square gates, covariance ellipses."""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def mahalanobis_sq(residual: ArrayLike, cov: ArrayLike) -> Array:
    """Squared Mahalanobis distance ``r^T S^-1 r``, batched. Shapes: (...,n),(...,n,n) -> (...).

    Raises ``np.linalg.LinAlgError`` when a covariance is not positive definite (the Cholesky factor is used so
    that an indefinite S can never yield a negative distance).
    """
    r = np.asarray(residual, dtype=np.float64)
    s = np.asarray(cov, dtype=np.float64)
    chol = np.linalg.cholesky(s)
    r_b = np.broadcast_to(r, np.broadcast_shapes(r.shape, s.shape[:-1]))
    chol_b = np.broadcast_to(chol, r_b.shape[:-1] + chol.shape[-2:])
    y = np.linalg.solve(chol_b, r_b[..., None])[..., 0]
    return np.sum(y * y, axis=-1)


def mahalanobis(residual: ArrayLike, cov: ArrayLike) -> Array:
    """Mahalanobis distance (not squared)."""
    return np.sqrt(mahalanobis_sq(residual, cov))


def chi2_gate(probability: float, dof: int) -> float:
    """Squared-distance threshold that a correct match passes with ``probability`` (chi-square quantile)."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability}")
    if isinstance(dof, bool) or dof != int(dof) or dof < 1:
        raise ValueError(f"dof must be an integer >= 1, got {dof}")
    return _chi2_quantile(float(probability), int(dof))


@functools.lru_cache(maxsize=1024)
def _chi2_quantile(probability: float, dof: int) -> float:
    # scipy's chi2.ppf costs 0.5-5 ms a call and the same few quantiles are asked for at every step and frame
    from scipy import stats  # imported here: scipy.stats costs ~1 s, and most users of geometry never need it

    return float(stats.chi2.ppf(probability, dof))


class Ellipse(NamedTuple):
    """Covariance ellipse parameters: semi-axes (m) and orientation of the major axis (rad)."""

    semi_major: Array
    semi_minor: Array
    angle: Array


def covariance_ellipse(cov: ArrayLike, probability: float = 0.95) -> Ellipse:
    """Ellipse containing ``probability`` of a 2D Gaussian's mass. Shapes: (...,2,2) -> three (...) arrays."""
    c = np.asarray(cov, dtype=np.float64)
    a, b, d = c[..., 0, 0], 0.5 * (c[..., 0, 1] + c[..., 1, 0]), c[..., 1, 1]
    # closed-form eigen-decomposition of a symmetric 2x2 matrix
    mean = 0.5 * (a + d)
    rad = np.sqrt(np.maximum(0.25 * (a - d) ** 2 + b * b, 0.0))
    l1, l2 = mean + rad, np.maximum(mean - rad, 0.0)
    angle = 0.5 * np.arctan2(2 * b, a - d)
    k = np.sqrt(chi2_gate(probability, 2))
    return Ellipse(k * np.sqrt(l1), k * np.sqrt(l2), angle)
