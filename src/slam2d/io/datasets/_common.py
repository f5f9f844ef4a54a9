"""Shared pieces of the dataset loaders: strict text-table reading, velocity integration, step grids, noise fits.

Every loader turns a folder of files into a :class:`slam2d.log.Log`. The helpers here do the parts that are the
same for every dataset: read numeric tables with ``file:line`` errors that name the offending token, integrate
piecewise-constant velocity commands exactly (arcs), put measurement times onto the step grid, interpolate ground
truth, and estimate :class:`MotionNoise` / sensor noise from data against ground truth.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import nnls

from slam2d.geometry import se2
from slam2d.geometry.angles import angle_diff, wrap_angle
from slam2d.io import bounded
from slam2d.log import Log
from slam2d.models.motion import odometry_to_rtr

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


#: smallest noise floor (m or rad) written into fitted MotionNoise parameters
MIN_FLOOR = 1e-4


class DatasetFormatError(ValueError):
    """A dataset file is missing, malformed or inconsistent; the message names ``file:line`` and the token."""


@dataclass(frozen=True)
class Table:
    """A numeric table read from a text file. Shapes: data (N, C); lines (N,) 1-based source line numbers."""

    path: Path
    data: Array
    lines: IntArray

    def where(self, row: int) -> str:
        """``file:line`` of data row ``row``."""
        return f"{self.path}:{int(self.lines[row])}"


#: largest magnitude a dataset value may have (times in ns since 1970 are ~1e18); beyond it sums and squares overflow
MAX_ABS_VALUE = 1e100

F = TypeVar("F", bound=Callable[..., Log])


def content_errors(what: str) -> Callable[[F], F]:
    """Decorator of a loader ``fn(path, ...)``: every failure caused by the files' content leaves as
    :class:`DatasetFormatError` naming the folder (the specific checks name ``file:line``), and a log with
    non-finite odometry, stamps or observations is refused instead of returned."""

    def wrap(fn: F) -> F:
        @functools.wraps(fn)
        def loader(path: str | Path, *args: Any, **kw: Any) -> Log:
            try:
                with np.errstate(all="ignore"):
                    log = fn(path, *args, **kw)
            except (DatasetFormatError, FileNotFoundError):
                raise
            except (ValueError, IndexError, KeyError, TypeError, ZeroDivisionError, OverflowError, FloatingPointError,
                    np.linalg.LinAlgError) as e:
                raise DatasetFormatError(f"{path}: inconsistent {what} data ({type(e).__name__}: {e})") from None
            bad = [n for n in ("stamps_s", "odometry", "obs_range_m") if not np.all(np.isfinite(getattr(log, n)))]
            if bad or np.any(np.diff(log.stamps_s) < 0):
                raise DatasetFormatError(f"{path}: {what} data gives non-finite or backward values ({bad or 'stamps'})")
            return log

        return loader  # type: ignore[return-value]

    return wrap


def require_file(path: Path, what: str) -> Path:
    """``path`` if it is a file, else a :class:`DatasetFormatError` saying which file of which dataset is missing."""
    if not path.is_file():
        raise DatasetFormatError(f"{path}: missing {what}")
    return path


def read_table(path: str | Path, columns: Sequence[str], *, delimiter: str | None = None,
               comment: str = "#", min_rows: int = 1) -> Table:
    """Read a whitespace- (or ``delimiter``-) separated numeric table with ``len(columns)`` columns.

    Blank lines and lines starting with ``comment`` are skipped; a trailing delimiter is tolerated. Every value must
    be a finite number. Errors are :class:`DatasetFormatError` naming ``file:line``, the column and the token.
    Shapes: returns data (N, len(columns)).
    """
    path = Path(path)
    try:
        text_lines = bounded.read_lines(path, DatasetFormatError, errors="strict")
    except FileNotFoundError:
        raise DatasetFormatError(f"{path}: no such file") from None
    except OSError as e:
        raise DatasetFormatError(f"{path}: cannot read ({e.strerror or e})") from None
    ncol = len(columns)
    rows: list[list[str]] = []
    lines: list[int] = []
    for no, raw in enumerate(text_lines, start=1):
        s = raw.strip()
        if not s or s.startswith(comment):
            continue
        toks = s.split(delimiter)
        if delimiter is not None:
            toks = [t.strip() for t in toks]
            if toks and toks[-1] == "":
                toks = toks[:-1]
        if len(toks) != ncol:
            raise DatasetFormatError(
                f"{path}:{no}: expected {ncol} columns ({', '.join(columns)}), got {len(toks)}: {s[:80]!r}")
        rows.append(toks)
        lines.append(no)
    if len(rows) < min_rows:
        raise DatasetFormatError(f"{path}: expected at least {min_rows} data rows, found {len(rows)}")
    try:
        data = np.array(rows, dtype=np.float64).reshape(len(rows), ncol)
        bad = ~np.isfinite(data)
    except ValueError:
        data = np.zeros((len(rows), ncol))
        bad = np.zeros((len(rows), ncol), dtype=bool)
        for i, toks in enumerate(rows):
            for j, tok in enumerate(toks):
                try:
                    data[i, j] = float(tok)
                except ValueError:
                    raise DatasetFormatError(
                        f"{path}:{lines[i]}: column {j + 1} ({columns[j]}): {tok!r} is not a number") from None
        bad = ~np.isfinite(data)
    bad |= ~(np.abs(np.where(bad, 0.0, data)) <= MAX_ABS_VALUE)
    if bad.any():
        i, j = (int(k) for k in np.argwhere(bad)[0])
        raise DatasetFormatError(
            f"{path}:{lines[i]}: column {j + 1} ({columns[j]}): {rows[i][j]!r} is not a finite number of magnitude "
            f"<= {MAX_ABS_VALUE:g}")
    return Table(path, data, np.asarray(lines, dtype=np.int64))


def check_integer(table: Table, col: int, name: str) -> IntArray:
    """Column ``col`` as integers; a non-integral value raises naming ``file:line``."""
    v = table.data[:, col]
    bad = np.flatnonzero(v != np.round(v))
    if bad.size:
        raise DatasetFormatError(f"{table.where(int(bad[0]))}: {name} must be an integer, got {v[bad[0]]!r}")
    return np.round(v).astype(np.int64)


def check_nondecreasing(table: Table, col: int, name: str) -> None:
    """Raise naming ``file:line`` where column ``col`` (a time) goes backwards."""
    v = table.data[:, col]
    bad = np.flatnonzero(np.diff(v) < 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise DatasetFormatError(
            f"{table.where(i)}: {name} goes backwards ({v[i]!r} after {v[i - 1]!r} on line {int(table.lines[i - 1])})")


# ---------------------------------------------------------------------------------------------------- kinematics
def _arc(v: Array, w: Array, dt: Array) -> Array:
    """Relative motion [dx, dy, dtheta] of a unicycle holding (v, w) for dt: ``exp([v dt, 0, w dt])``. (N,)->(N,3)."""
    th = w * dt
    small = np.abs(th) < 1e-9
    ths = np.where(small, 1.0, th)
    # sin(th)/th and (1-cos(th))/th with their series limits near 0
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, th / 2.0, (1.0 - np.cos(ths)) / ths)
    d = v * dt
    return np.stack([d * a, d * b, th], axis=-1)


def integrate_velocity(t_cmd: ArrayLike, v: ArrayLike, w: ArrayLike, t_query: ArrayLike) -> Array:
    """Dead-reckoned poses at ``t_query`` from commands (v, w) held from each ``t_cmd[i]`` to the next (exact arcs).

    Pose at ``t_query[0]`` is the origin [0, 0, 0]. Before ``t_cmd[0]`` the robot is taken to stand still; the last
    command is held after ``t_cmd[-1]``. Shapes: t_cmd (M,), v (M,), w (M,), t_query (Q,) sorted -> (Q, 3).
    Vectorised: headings are a cumulative sum, positions a cumulative sum of arc chords rotated by the heading at
    the start of each piece.
    """
    tc, v, w = (np.asarray(a, dtype=np.float64) for a in (t_cmd, v, w))
    tq = np.asarray(t_query, dtype=np.float64)
    knots = np.union1d(tc[(tc > tq[0]) & (tc < tq[-1])], tq)  # sorted, unique; contains every query time
    # command in force on [knots[k], knots[k+1]): the last command whose time is <= knots[k]
    idx = np.searchsorted(tc, knots[:-1], side="right") - 1
    active = idx >= 0
    vi = np.where(active, v[np.maximum(idx, 0)], 0.0)
    wi = np.where(active, w[np.maximum(idx, 0)], 0.0)
    rel = _arc(vi, wi, np.diff(knots))
    heading = np.concatenate([[0.0], np.cumsum(rel[:, 2])])  # unwrapped
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    step_xy = np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]], axis=-1)
    xy = np.vstack([np.zeros((1, 2)), np.cumsum(step_xy, axis=0)])
    at = np.searchsorted(knots, tq)
    return np.column_stack([xy[at], wrap_angle(heading[at])])


def increments(poses: ArrayLike) -> Array:
    """Per-step odometry ``between(p[t-1], p[t])``. Shapes: (T+1,3) -> (T,3)."""
    p = np.asarray(poses, dtype=np.float64)
    return se2.between(p[:-1], p[1:])


def interpolate_poses(t: ArrayLike, poses: ArrayLike, t_query: ArrayLike) -> Array:
    """Linear interpolation of x, y and the unwrapped heading at ``t_query`` (inside [t[0], t[-1]]).

    Shapes: t (N,) non-decreasing, poses (N,3), t_query (Q,) -> (Q,3).
    """
    t = np.asarray(t, dtype=np.float64)
    p = np.asarray(poses, dtype=np.float64)
    tq = np.asarray(t_query, dtype=np.float64)
    th = np.unwrap(p[:, 2])
    return np.column_stack([np.interp(tq, t, p[:, 0]), np.interp(tq, t, p[:, 1]), wrap_angle(np.interp(tq, t, th))])


def step_grid(t0: float, t1: float, dt: float, events: ArrayLike, min_gap_s: float) -> Array:
    """Step times: a regular grid ``t0, t0+dt, ...`` up to ``t1`` merged with the event times in (t0, t1].

    Grid points closer than ``min_gap_s`` to an event are dropped (the event time replaces them), so every event
    falls exactly on a step and consecutive steps are at most ``dt + 2 min_gap_s`` apart. Returns sorted unique
    times starting at t0.
    """
    grid = t0 + dt * np.arange(1, int(np.floor((t1 - t0) / dt)) + 1)
    ev = np.unique(np.asarray(events, dtype=np.float64))
    ev = ev[(ev > t0) & (ev <= t1)]
    if ev.size and grid.size:
        j = np.searchsorted(ev, grid)
        d_next = np.abs(ev[np.minimum(j, ev.size - 1)] - grid)
        d_prev = np.abs(grid - ev[np.maximum(j - 1, 0)])
        grid = grid[np.minimum(d_next, d_prev) >= min_gap_s]
    return np.concatenate([[t0], np.union1d(grid, ev)])


def nearest_step(stamps: ArrayLike, t: ArrayLike) -> IntArray:
    """Index of the stamp nearest to each time. Shapes: stamps (T+1,) sorted, t (K,) -> (K,) int."""
    s = np.asarray(stamps, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    j = np.clip(np.searchsorted(s, t), 1, s.size - 1)
    left_closer = (t - s[j - 1]) <= (s[j] - t)
    return np.where(left_closer, j - 1, j).astype(np.int64)


def cap_log(log: Log, max_steps: int | None, max_time_s: float | None) -> Log:
    """``log`` cut to at most ``max_steps`` steps and ``max_time_s`` seconds after pose 0 (noise fits stay those of
    the whole run, so a cut log assumes the same noise as the full one). ``metadata['cut']`` records the cut."""
    steps = log.num_steps
    if max_time_s is not None:
        if not max_time_s > 0:
            raise ValueError(f"max_time_s must be > 0 (got {max_time_s})")
        steps = min(steps, int(np.searchsorted(log.stamps_s, log.stamps_s[0] + max_time_s, side="right")) - 1)
    if max_steps is not None:
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 (got {max_steps})")
        steps = min(steps, int(max_steps))
    if steps < 1:
        raise ValueError("the requested cut leaves no step")
    if steps == log.num_steps:
        return log
    meta = {**log.metadata, "cut": {"steps": steps, "of": log.num_steps, "max_steps": max_steps,
                                    "max_time_s": max_time_s}}
    return dataclasses.replace(log.head(steps), metadata=meta)


# ---------------------------------------------------------------------------------------------------- noise fits
def fit_motion_noise(odometry: ArrayLike, true_poses: ArrayLike, steps_per_window: int, *,
                     min_trans_m: float = 0.005) -> dict[str, Any]:
    """Estimate :class:`~slam2d.models.motion.MotionNoise` parameters from odometry against ground truth.

    Method: cut the run into non-overlapping windows of ``steps_per_window`` steps; per window compare the composed
    odometry with the true relative motion: translation error ``e_t = |t_odo| - |t_true|`` and rotation error
    ``e_r = angle_diff(dth_odo, dth_true)``. Fit, by non-negative least squares on the squared errors (refitted
    without windows beyond 5 sigma of a first fit, as motion-capture glitches),
    ``E[e_t^2] = a3 T^2 + a4 (R1^2 + R2^2) + c_t`` and ``E[e_r^2] = a1 (R1^2 + R2^2) + 2 a2 T^2 + c_r``
    with (R1, T, R2) the window's TRUE rot1-trans-rot2 (rot1 = 0 when T < ``min_trans_m``). If the per-step errors
    were independent, a window of n equal steps has n times the per-step variance of steps n times shorter, so
    per-step alphas are ``n * a`` and the per-step floors ``sqrt(c / n)`` (at least ``MIN_FLOOR``; ``c_r`` counts
    two rotations). Correlated (systematic) odometry errors make this an under-estimate for horizons much longer
    than the window.

    Shapes: odometry (T,3), true_poses (T+1,3). Returns a dict of MotionNoise fields (floats).
    """
    u = np.asarray(odometry, dtype=np.float64)
    gt = np.asarray(true_poses, dtype=np.float64)
    n = int(steps_per_window)
    if n < 1 or u.shape[0] < 4 * n:
        raise ValueError(f"need at least 4 windows of {n} steps to fit motion noise (have {u.shape[0]} steps)")
    # compose the odometry into one dead-reckoned chain (sequential by nature; T is at most ~1e5)
    dr = se2.compose_chain(np.zeros(3), u)
    ends = np.arange(0, u.shape[0] + 1, n)
    w_odo = se2.between(dr[ends[:-1]], dr[ends[1:]])
    w_gt = se2.between(gt[ends[:-1]], gt[ends[1:]])
    # features from the TRUE motion (the noise model is driven by it; features from the noisy odometry bias the
    # fit low: errors in variables). Windows that barely translate count as pure rotations (rot1 = 0), because the
    # direction of a motion-capture displacement of a few millimetres is noise.
    m = odometry_to_rtr(w_gt)
    still = m[:, 1] < min_trans_m
    m[still, 0] = 0.0
    m[still, 2] = w_gt[still, 2]
    e_t = odometry_to_rtr(w_odo)[:, 1] - m[:, 1]
    e_r = angle_diff(w_odo[:, 2], w_gt[:, 2])
    rr = m[:, 0] ** 2 + m[:, 2] ** 2
    tt = m[:, 1] ** 2

    def fit(features: Array, err2: Array) -> Array:
        coef, _ = nnls(features, err2)
        # second pass without windows beyond 5 sigma of the first fit (motion-capture glitches); a Gaussian loses
        # ~1e-6 of its windows this way, so the variances stay unbiased (a percentile cut would bias them low)
        pred = np.maximum(features @ coef, 1e-300)
        keep = err2 <= 25.0 * pred
        if keep.sum() >= features.shape[1] and not keep.all():
            coef, _ = nnls(features[keep], err2[keep])
        return coef

    ct = fit(np.column_stack([tt, rr, np.ones_like(tt)]), e_t**2)
    cr = fit(np.column_stack([rr, 2 * tt, 2 * np.ones_like(tt)]), e_r**2)
    # floors of 1e-4 keep a standstill step's covariance positive definite even when the fit finds no floor
    return {
        "alpha_rot_rot": float(n * cr[0]),
        "alpha_rot_trans": float(n * cr[1]),
        "alpha_trans_trans": float(n * ct[0]),
        "alpha_trans_rot": float(n * ct[1]),
        "min_trans_std_m": max(MIN_FLOOR, float(np.sqrt(ct[2] / n))),
        "min_rot_std_rad": max(MIN_FLOOR, float(np.sqrt(cr[2] / n))),
    }


def robust_std(residuals: ArrayLike) -> dict[str, float]:
    """Spread of residuals about ZERO for a zero-mean noise model: ``sqrt(median^2 + (1.4826 MAD)^2)``.

    The bias is folded in because the filters assume zero-mean noise. Returns median, MAD-based std and the total
    (at least ``MIN_FLOOR``).
    """
    r = np.asarray(residuals, dtype=np.float64)
    med = float(np.median(r))
    mad_std = float(1.4826 * np.median(np.abs(r - med)))
    # floored like the motion noise: a zero std would make the sensor config invalid (and the filter singular)
    return {"median": med, "mad_std": mad_std, "std": max(MIN_FLOOR, float(np.hypot(med, mad_std)))}
