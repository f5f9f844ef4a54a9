"""Tracking of the lidar back end (:mod:`slam2d.graph.lidar`): one scan against the local map, with a correlative
re-match when ICP's fit degrades.

ICP from the odometry guess converges to the nearest minimum. When the guess is far off -- an in-place spin whose
odometry under- or over-counts the turn by 0.1-0.2 rad a scan, or wheel odometry that stalls and then reports the
stalled motion at once -- that minimum can be a wrong one: on ACES (scans 4289-4290) ICP settled with a residual RMS
of 0.14-0.16 m (the log's 99.9th percentile is 0.03 m) and half its points matched, tracking lost 0.3 rad there, and
no loop recovered it. A fit that bad (residual above ``track_rematch_rmse_m``, too few matches, or no convergence) is
redone: an exhaustive correlative search (:mod:`slam2d.frontend.correlative`) of the scan against the local map
over a window that covers such a guess error, then ICP from its best pose; the re-match replaces the first one when
it fits better (more matches at a residual no worse, or a residual within the limit where the first was not).

A fit can also be good and wrong: on mit-csail the odometry stalls for scans 1579-1582 while tracking follows the
turn, then reports the whole 1.49 rad at scan 1583, on top; from that guess ICP slid 1.9 rad, into a corridor's turned
alignment, with a 3 mm residual (in a run with ``loop_every=3`` the track ended 180 degrees off). A fit farther from
its guess than the re-match window reaches is not trusted: ICP starts again from the steady guess (the last tracked
motion repeated), which wins when it fits and stays near its start, else the re-match runs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from slam2d.frontend.correlative import CorrelativeConfig, correlative_match
from slam2d.frontend.icp import ICPConfig, ICPResult, ICPTarget, icp
from slam2d.geometry import se2

__all__ = ["TrackResult", "track_scan"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TrackResult:
    """The chosen tracking match and whether it came from the correlative re-match."""

    match: ICPResult
    rematched: bool
    """the first fit was redone (it was poor, or it slid): from the steady guess or by a correlative re-match."""
    replaced: bool
    """... and its result replaced the first fit."""


def good_fit(res: ICPResult, min_fitness: float, max_rmse_m: float) -> bool:
    """Is an ICP match a trustworthy tracking result?"""
    return bool(res.converged and res.fitness >= min_fitness and res.rmse_m <= max_rmse_m
                and np.all(np.isfinite(res.covariance)))


def _better(new: ICPResult, old: ICPResult, min_fitness: float, max_rmse_m: float) -> bool:
    """Does the re-match ``new`` fit better than the first match ``old``?"""
    if not good_fit(new, min_fitness, np.inf):
        return False
    if not good_fit(old, min_fitness, np.inf):  # the first match failed outright
        return True
    if new.rmse_m <= max_rmse_m < old.rmse_m:
        return True
    return new.fitness >= old.fitness and new.rmse_m <= old.rmse_m


def _slid(res: ICPResult, start: Array, correlative: CorrelativeConfig) -> bool:
    """Did ICP end farther from its start than the re-match window reaches? No ICP basin is that wide: it slid
    into another alignment (a corridor turned end for end fits as well)."""
    d = se2.local(start, res.transform)
    return bool(np.hypot(d[0], d[1]) > correlative.window_xy_m or abs(d[2]) > correlative.window_theta_rad)


def track_scan(pts: Array, target: ICPTarget, guess: Array, icp_config: ICPConfig, min_fitness: float,
               rematch_rmse_m: float, correlative: CorrelativeConfig, points: int,
               steady: Array | None = None, prior_weights: Array | None = None) -> TrackResult:
    """Match scan points ``pts`` (N,2) to the local map ``target`` from ``guess`` (3,) (world poses); when the fit
    is poor, re-match from a correlative search over ``correlative``'s window (with at most ``points`` of the scan,
    evenly spread; 0: no re-match). A fit that slid farther from the guess than that window is not trusted: ICP
    starts again from ``steady`` (the last motion repeated), which wins when it fits and stays near its start;
    else the re-match runs as for a poor fit. ``prior_weights`` (3,): the first ICP also pulls towards the guess
    with these weights (:func:`~slam2d.frontend.icp.icp`'s ``prior``; None: off); the recovery fits do not, since
    they run where the guess is in doubt."""
    prior = None if prior_weights is None else (guess, prior_weights)
    res = icp(pts, target, initial=guess, config=icp_config, prior=prior)
    slid = _slid(res, guess, correlative)
    if points <= 0 or (good_fit(res, min_fitness, rematch_rmse_m) and not slid):
        return TrackResult(res, False, False)
    if slid and steady is not None:
        alt = icp(pts, target, initial=steady, config=icp_config)
        if good_fit(alt, min_fitness, rematch_rmse_m) and not _slid(alt, steady, correlative):
            return TrackResult(alt, True, True)
    sel = pts[np.unique(np.linspace(0, len(pts) - 1, min(len(pts), points)).astype(np.int64))]
    near = target.points[np.einsum("ij,ij->i", target.points - guess[:2], target.points - guess[:2])
                         <= (np.max(np.hypot(pts[:, 0], pts[:, 1])) + correlative.window_xy_m) ** 2]
    cm = correlative_match(sel, near, guess, correlative)
    again = icp(pts, target, initial=cm.transform, config=icp_config)
    if _better(again, replace(res, converged=False) if slid else res, min_fitness, rematch_rmse_m):
        return TrackResult(again, True, True)
    return TrackResult(res, True, False)
