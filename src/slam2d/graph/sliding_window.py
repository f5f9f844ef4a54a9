"""Bounded-work local solves for online graph SLAM: a sliding window with a fixed boundary.

The newest poses (the window) and every landmark they observed are free; every other pose that shares a factor with
them is a boundary pose (it carries the rest of the graph as a boundary condition, as the fixed poses of
:mod:`slam2d.graph.incremental` do for pose graphs), held fixed. The work of one solve depends on the window, the
landmarks in it and their sightings, not on the length of the trajectory.

The window's uncertainty (for association and drawing) is approximated from the window alone
(:meth:`WindowSolve.marginals`): its own factors and priors on the poses they reach outside it, a conservative
stand-in for the rest of the graph (the price of a sliding window without a marginalisation prior; ``finalize``
and loop closures still solve and factorise the whole graph).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.graph.factors import KINDS
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.marginals import marginal_covariances
from slam2d.graph.optimizer import Optimizer, OptimizerConfig
from slam2d.graph.robust import KERNEL_NAMES

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def subgraph(graph: FactorGraph, free_poses: IntArray, free_points: IntArray,
             boundary_sightings: int | None = None) -> FactorGraph:
    """A new graph with the factors of ``graph`` that touch a free pose or point (kernels kept). With
    ``boundary_sightings`` = K, a free point keeps only its K newest sightings from poses that are not free (its
    older ones are left out: they tie it to poses far back, whose number grows with every revisit)."""
    out = FactorGraph()
    for b in graph.blocks():
        vks = KINDS[b.kind].var_kinds
        sel = np.zeros(b.size, dtype=bool)
        for a, vk in enumerate(vks):
            sel |= np.isin(b.keys[a], free_poses if vk == "pose" else free_points)
        if boundary_sightings is not None and vks == ("pose", "point"):
            outside = np.flatnonzero(sel & ~np.isin(b.keys[0], free_poses))
            order = outside[np.lexsort((-b.keys[0][outside], b.keys[1][outside]))]  # by point, newest pose first
            pts = b.keys[1][order]
            first = np.r_[0, np.flatnonzero(pts[1:] != pts[:-1]) + 1]
            rank = np.arange(order.size) - np.repeat(first, np.diff(np.r_[first, order.size]))
            sel[order[rank >= boundary_sightings]] = False
        if not np.any(sel):
            continue
        add = getattr(out, f"add_{b.kind}")
        info = np.zeros_like(b.sqrt_info)
        info[sel] = np.swapaxes(b.sqrt_info[sel], 1, 2) @ b.sqrt_info[sel]  # Omega = L^T L of the selected ones
        # one batch per (kernel, parameter) pair: add_* takes one of each
        groups = np.unique(np.column_stack([b.kernel[sel].astype(np.float64), b.kernel_param[sel]]), axis=0)
        for code, param in groups:
            s = sel & (b.kernel == int(code)) & (b.kernel_param == param)
            name = KERNEL_NAMES[int(code)]
            add(*[k[s] for k in b.keys], b.z[s], info[s], robust=None if name == "none" else name,
                robust_param=float(param))
    return out


@dataclass
class WindowSolve:
    """One local solve: the optimised local values, the local graph, its free poses and boundary poses."""

    values: Values
    graph: FactorGraph
    free_poses: IntArray
    boundary: IntArray

    def marginals(self, pose_keys: IntArray, point_keys: IntArray, pose_covs: Callable[[IntArray], Array]) -> Array:
        """Joint marginal covariance of these window variables (poses first), from the window alone: the factors of
        the window's poses, and a prior with covariance ``pose_covs(keys)`` (K,3,3) on each other pose they reach
        (the pose before the window, the old ends of loop closures), as if those were independent.

        Conservative: older sightings of the window's landmarks are left out (a prior on those landmarks would
        count the pose prior's information a second time: both derive from the same earlier poses)."""
        g = subgraph(self.graph, self.free_poses, np.zeros(0, np.int64))
        vals = self.values
        used, pts = g.pose_keys_used(), g.point_keys_used()
        held = np.setdiff1d(used, self.free_poses)
        if held.size:
            g.add_prior(held, vals.poses[np.searchsorted(vals.pose_keys, held)],
                        np.linalg.inv(np.asarray(pose_covs(held)) + 1e-12 * np.eye(3)))
        sub_vals = Values(used, vals.poses[np.searchsorted(vals.pose_keys, used)], pts,
                          _rows(vals.point_keys, pts, vals.points))
        return marginal_covariances(g, sub_vals, pose_keys, point_keys).joint


def solve_window(graph: FactorGraph, values: Values, free_poses: IntArray, free_points: IntArray, iterations: int,
                 boundary_sightings: int | None = None) -> WindowSolve:
    """Levenberg-Marquardt on the factors touching ``free_poses`` / ``free_points`` (see :func:`subgraph`), every
    other pose they reach held fixed. ``values`` is not modified; the returned values hold the free and boundary
    variables."""
    sub = subgraph(graph, free_poses, free_points, boundary_sightings)
    pose_keys = sub.pose_keys_used()
    point_keys = sub.point_keys_used()
    boundary = np.setdiff1d(pose_keys, free_poses)
    loc = Values(pose_keys, values.poses[np.searchsorted(values.pose_keys, pose_keys)],
                 point_keys, _rows(values.point_keys, point_keys, values.points))
    out, _ = Optimizer(sub, OptimizerConfig(method="lm", max_iterations=iterations),
                       fixed_pose_keys=boundary).optimize(loc)
    return WindowSolve(out, sub, np.intersect1d(free_poses, pose_keys), boundary)


def _rows(keys: IntArray, query: IntArray, table: Array) -> Array:
    order = np.argsort(keys, kind="stable")
    return table[order[np.searchsorted(keys[order], query)]]
