"""Trajectory metrics: ATE after SE(2) alignment, and RPE over a fixed step offset.

Alignment is the 2D case of Umeyama (IEEE TPAMI 1991, eqs. 34-42) without scale: the rotation and translation
minimising the sum of squared position differences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle

Array = NDArray[np.float64]


def _trajectory(a: ArrayLike, name: str, widths: tuple[int, ...]) -> Array:
    """``a`` as a float64 (N, w) array, w in ``widths``, with finite values; ValueError naming ``name`` otherwise (a
    NaN pose would make every metric NaN)."""
    t = np.asarray(a, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] not in widths:
        want = " or ".join(f"(N, {w})" for w in widths)
        raise ValueError(f"{name} must have shape {want} (one pose per row), got {t.shape}")
    bad = ~np.all(np.isfinite(t), axis=1)
    if np.any(bad):
        raise ValueError(f"{name} has a non-finite value in row {int(np.flatnonzero(bad)[0])}")
    return t


def align_se2(estimate: ArrayLike, reference: ArrayLike) -> Array:
    """The pose ``T_ref_est`` = [tx, ty, theta] that best maps estimated positions onto reference positions.

    Shapes: (N,2|3),(N,2|3) -> (3,). Raises ValueError for fewer than 2 points.
    """
    p = _trajectory(estimate, "estimate", (2, 3))[:, :2]
    q = _trajectory(reference, "reference", (2, 3))[:, :2]
    if p.shape != q.shape or p.shape[0] < 2:
        raise ValueError(f"need two equal-length trajectories of >= 2 poses, got {p.shape} and {q.shape}")
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    pc, qc = p - mp, q - mq
    # 2D cross-covariance -> optimal rotation angle in closed form
    sxx = np.sum(pc[:, 0] * qc[:, 0] + pc[:, 1] * qc[:, 1])
    sxy = np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0])
    theta = float(np.arctan2(sxy, sxx))
    c, s = np.cos(theta), np.sin(theta)
    t = mq - np.array([c * mp[0] - s * mp[1], s * mp[0] + c * mp[1]])
    return np.array([t[0], t[1], theta])


@dataclass(frozen=True)
class ATEResult:
    """Absolute trajectory error: per-pose position errors (m) after alignment, and the alignment used."""

    errors_m: Array
    alignment: Array

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.errors_m**2))) if self.errors_m.size else float("nan")


def ate(estimate: ArrayLike, reference: ArrayLike, *, align: bool = True) -> ATEResult:
    """ATE of an estimated trajectory against a reference (same length, same time stamps). Shapes: (N,3),(N,3)
    (or (N,2) positions). Raises ValueError for mismatched shapes or non-finite poses."""
    est = _trajectory(estimate, "estimate", (2, 3))
    ref = _trajectory(reference, "reference", (2, 3))
    if est.shape[0] != ref.shape[0]:
        raise ValueError(f"trajectories differ in length: {est.shape[0]} vs {ref.shape[0]}")
    tf = align_se2(est, ref) if align else np.zeros(3)
    moved = se2.transform_points(tf, est[:, :2])
    return ATEResult(np.hypot(*(moved - ref[:, :2]).T), tf)


@dataclass(frozen=True)
class RPEResult:
    """Relative pose error over ``delta`` steps: translation (m) and rotation (rad) error per pair."""

    trans_errors_m: Array
    rot_errors_rad: Array
    delta: int

    @property
    def trans_rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.trans_errors_m**2))) if self.trans_errors_m.size else float("nan")

    @property
    def rot_rmse_rad(self) -> float:
        return float(np.sqrt(np.mean(self.rot_errors_rad**2))) if self.rot_errors_rad.size else float("nan")


def rpe(estimate: ArrayLike, reference: ArrayLike, *, delta: int = 1) -> RPEResult:
    """RPE: compare ``between(x_i, x_{i+delta})`` of estimate and reference (no alignment needed)."""
    est = _trajectory(estimate, "estimate", (3,))
    ref = _trajectory(reference, "reference", (3,))
    if est.shape != ref.shape:
        raise ValueError(f"trajectories differ in shape: {est.shape} vs {ref.shape}")
    if isinstance(delta, bool) or not isinstance(delta, int | np.integer) or delta < 1:
        raise ValueError(f"delta must be an integer >= 1 (got {delta!r})")
    delta = int(delta)
    d_est = se2.between(est[:-delta], est[delta:])
    d_ref = se2.between(ref[:-delta], ref[delta:])
    err = se2.between(d_ref, d_est)
    return RPEResult(np.hypot(err[:, 0], err[:, 1]), np.abs(wrap_angle(err[:, 2])), delta)
