"""Filter consistency: NEES and NIS, and the two-sided chi-square band for their Monte-Carlo averages.

A consistent filter's estimation error ``e`` (dimension ``d``) with stated covariance ``P`` has
``NEES = e^T P^-1 e ~ chi2(d)``. Averaged over ``n`` independent runs, ``n * mean NEES ~ chi2(n d)``, so the mean
lies in ``[chi2.ppf(a/2, n d) / n, chi2.ppf(1 - a/2, n d) / n]`` with probability ``1 - a``
(Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001, sec. 5.4.2).
NIS is the same test applied to innovations ``nu`` with their covariance ``S``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from slam2d.estimator import Estimator
from slam2d.geometry.angles import angle_diff
from slam2d.geometry.gaussian import mahalanobis_sq
from slam2d.log import Log

Array = NDArray[np.float64]


def pose_error(estimate: ArrayLike, truth: ArrayLike) -> Array:
    """Pose error ``estimate - truth`` with the heading difference wrapped. Shapes: (...,3),(...,3) -> (...,3)."""
    est = np.asarray(estimate, dtype=np.float64)
    ref = np.asarray(truth, dtype=np.float64)
    if est.shape != ref.shape or est.shape[-1] != 3:
        raise ValueError(f"poses must have equal shapes (...,3), got {est.shape} and {ref.shape}")
    err = est - ref
    err[..., 2] = angle_diff(est[..., 2], ref[..., 2])
    return err


def nees(error: ArrayLike, cov: ArrayLike) -> Array:
    """Normalised estimation error squared ``e^T P^-1 e``, batched. Shapes: (...,d),(...,d,d) -> (...).

    Raises ``np.linalg.LinAlgError`` if a covariance is not positive definite (a zero covariance, e.g. the initial
    pose of a filter, has no NEES; drop those entries first).
    """
    return mahalanobis_sq(error, cov)


def nis(innovation: ArrayLike, innovation_cov: ArrayLike) -> Array:
    """Normalised innovation squared ``nu^T S^-1 nu``, batched. Shapes: (...,m),(...,m,m) -> (...)."""
    return mahalanobis_sq(innovation, innovation_cov)


def pose_nees(estimates: ArrayLike, covs: ArrayLike, truth: ArrayLike) -> Array:
    """NEES of a pose trajectory (3 dof per pose). Shapes: (T,3),(T,3,3),(T,3) -> (T,)."""
    return nees(pose_error(estimates, truth), covs)


def online_pose_nees(est: Estimator, log: Log, rng: np.random.Generator, steps: int) -> Array:
    """(steps,) pose NEES of ``est`` run online from the start of ``log`` (reset with ``rng``): each step's estimate
    against the log's true pose, ``e^T P^-1 e``; NaN past the log's end."""
    if log.true_poses is None:
        raise ValueError("online_pose_nees: the log has no true poses")
    out = np.full(steps, np.nan)
    est.reset(log.initial_pose, rng=rng)
    for t, step in enumerate(log.head(steps)):
        est.step(step)
        snap = est.estimate()
        if snap.pose_cov is None:
            raise ValueError("online_pose_nees: the estimator reports no pose covariance")
        e = pose_error(snap.pose, log.true_poses[t + 1])
        out[t] = e @ np.linalg.solve(snap.pose_cov, e)
    return out


@dataclass(frozen=True)
class Band:
    """Two-sided acceptance interval for the mean of ``runs`` NEES/NIS values of ``dof`` degrees of freedom."""

    low: float
    high: float
    dof: int
    runs: int
    probability: float

    def contains(self, values: ArrayLike) -> NDArray[np.bool_]:
        """Elementwise ``low <= v <= high``. Shapes: (...) -> (...)."""
        v = np.asarray(values, dtype=np.float64)
        return (v >= self.low) & (v <= self.high)

    def fraction_inside(self, values: ArrayLike) -> float:
        """Fraction of the (finite) values inside the band; nan when there are none."""
        v = np.asarray(values, dtype=np.float64).ravel()
        v = v[np.isfinite(v)]
        return float(np.mean(self.contains(v))) if v.size else float("nan")


def chi2_band(dof: int, runs: int = 1, probability: float = 0.95) -> Band:
    """Band for the average of ``runs`` independent chi2(``dof``) values, holding it with ``probability``.

    ``runs * mean ~ chi2(runs * dof)``; the band splits ``1 - probability`` equally between the two tails.
    """
    if dof < 1:
        raise ValueError(f"dof must be >= 1 (got {dof})")
    if runs < 1:
        raise ValueError(f"runs must be >= 1 (got {runs})")
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1) (got {probability})")
    tail = 0.5 * (1.0 - probability)
    lo, hi = stats.chi2.ppf([tail, 1.0 - tail], dof * runs) / runs
    return Band(float(lo), float(hi), dof, runs, probability)


@dataclass(frozen=True)
class ConsistencySummary:
    """Monte-Carlo NEES (or NIS) per step averaged over runs, with the band and the fraction of steps inside."""

    mean: Array
    band: Band
    fraction_inside: float
    overall_mean: float


def monte_carlo_consistency(values: ArrayLike, dof: int, probability: float = 0.95) -> ConsistencySummary:
    """Average NEES/NIS values over runs and test each step against the chi-square band.

    Shapes: values (R,T) (R runs, T steps; nan marks a missing entry, which is left out of that step's average).
    The band uses ``R`` runs; steps with fewer than ``R`` finite values are compared with the band of their own count.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[0] < 1:
        raise ValueError(f"values must have shape (runs, steps), got {v.shape}")
    finite = np.isfinite(v)
    counts = finite.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, np.where(finite, v, 0.0).sum(axis=0) / np.maximum(counts, 1), np.nan)
    band = chi2_band(dof, v.shape[0], probability)
    inside = np.zeros(v.shape[1], dtype=bool)
    for c in np.unique(counts[counts > 0]):
        b = band if c == v.shape[0] else chi2_band(dof, int(c), probability)
        sel = counts == c
        inside[sel] = b.contains(mean[sel])
    has = counts > 0
    frac = float(np.mean(inside[has])) if has.any() else float("nan")
    overall = float(np.nanmean(mean)) if has.any() else float("nan")
    return ConsistencySummary(mean, band, frac, overall)
