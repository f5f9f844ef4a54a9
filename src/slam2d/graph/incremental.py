"""Incremental pose-graph optimisation: one pose and its edges per step, bounded work per step.

On a step that brings a loop closure, only a local problem is solved: the newest ``window`` poses plus a small
neighbourhood around each old loop endpoint are free, every other pose touched by their edges is held fixed (it
carries the rest of the graph's information as a boundary condition). Every ``full_every`` steps the whole graph is
re-linearised and solved once, which spreads the accumulated corrections along the entire trajectory; ``finalize``
runs the whole-graph optimisation to convergence. The local solves keep the online estimate close to the optimum
without paying for a whole-graph factorisation on every step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.geometry import se2
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.marginals import factored_block
from slam2d.graph.optimizer import Optimizer, OptimizerConfig, Summary

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class IncrementalConfig:
    """Incremental pose-graph settings."""

    window: int = 30
    """newest poses freed in a local solve."""
    loop_neighbourhood: int = 3
    """poses on each side of an old loop endpoint freed in a local solve."""
    iterations: int = 2
    """Gauss-Newton iterations per local solve."""
    full_every: int = 500
    """steps between whole-graph solves (one Gauss-Newton iteration each)."""
    loop_kernel: str | None = None
    """robust kernel on loop edges (edges between non-consecutive poses), e.g. "cauchy"; None: plain least
    squares. A wrong loop that slipped through verification then bends the graph less."""
    loop_kernel_scale: float = 3.0
    """scale of ``loop_kernel`` in standard deviations (sqrt(chi2))."""

    def __post_init__(self) -> None:
        for n in ("window", "iterations", "full_every"):
            if getattr(self, n) < 1:
                raise ValueError(f"IncrementalConfig.{n} must be >= 1 (got {getattr(self, n)})")
        if self.loop_kernel_scale <= 0:
            raise ValueError(f"IncrementalConfig.loop_kernel_scale must be > 0 (got {self.loop_kernel_scale})")
        if self.loop_neighbourhood < 0:
            raise ValueError(f"IncrementalConfig.loop_neighbourhood must be >= 0 (got {self.loop_neighbourhood})")


class IncrementalPoseGraph:
    """Poses keyed 0..t in order; ``add_step(t, i, j, z, information)`` adds pose t and the edges that end at it."""

    def __init__(self, initial_pose: Array, config: IncrementalConfig | None = None) -> None:
        self.config = config or IncrementalConfig()
        self._poses = np.zeros((1024, 3))
        self._poses[0] = initial_pose
        self.num_poses = 1
        self._ei = np.zeros(1024, np.int64)
        self._ej = np.zeros(1024, np.int64)
        self._z = np.zeros((1024, 3))
        self._info = np.zeros((1024, 3, 3))
        self.num_edges = 0
        self._adj: list[list[int]] = [[]]
        self.local_solves = 0
        self.full_solves = 0
        # the whole-graph optimiser of the last full solve, kept while no pose or edge is added: the solves that
        # follow a loop, one per scan, then reuse its symbolic analysis and factorisation ordering
        self._full: tuple[tuple[int, int, OptimizerConfig], Optimizer] | None = None
        # the optimiser whose solver holds the factorisation of the whole graph as it is now (a Gauss-Newton full
        # solve since which nothing was added): :meth:`newest_covariance` reads it
        self._factored: Optimizer | None = None

    @property
    def poses(self) -> Array:
        return self._poses[: self.num_poses]

    def _grow(self) -> None:
        if self.num_poses >= len(self._poses):
            self._poses = np.vstack([self._poses, np.zeros_like(self._poses)])
        need = self.num_edges
        if need >= len(self._ei) - 64:
            self._ei = np.concatenate([self._ei, np.zeros_like(self._ei)])
            self._ej = np.concatenate([self._ej, np.zeros_like(self._ej)])
            self._z = np.vstack([self._z, np.zeros_like(self._z)])
            self._info = np.concatenate([self._info, np.zeros_like(self._info)])

    def add_step(self, t: int, i: NDArray[np.int64], j: NDArray[np.int64], z: Array, information: Array) -> None:
        """Add pose ``t`` (= the number of poses so far) and edges (i, j) with j == t or i == t, the other end older."""
        if t != self.num_poses:
            raise ValueError(f"poses must arrive in order: expected {self.num_poses}, got {t}")
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        if np.any(np.maximum(i, j) != t) or np.any(np.minimum(i, j) >= t) or np.any(np.minimum(i, j) < 0):
            raise ValueError(f"step {t}: every edge must join pose {t} to an existing older pose")
        self._grow()
        self._factored = None
        odo = np.flatnonzero((i == t - 1) & (j == t))
        prev = self._poses[t - 1]
        self._poses[t] = se2.compose(prev, z[odo[0]]) if odo.size else prev
        self.num_poses += 1
        self._adj.append([])
        for k in range(len(i)):
            e = self.num_edges
            self._ei[e], self._ej[e], self._z[e], self._info[e] = i[k], j[k], z[k], information[k]
            self._adj[i[k]].append(e)
            self._adj[j[k]].append(e)
            self.num_edges += 1
        old = np.minimum(i, j)
        loops = old[old < t - 1]
        if t % self.config.full_every == 0:
            self._solve_full(1)
        elif loops.size:
            self._solve_local(t, loops)

    def add_loop(self, i: int, j: int, z: Array, information: Array) -> None:
        """An extra edge between two existing poses (an on-demand loop closure), followed by a local solve."""
        t = self.num_poses - 1
        if not (0 <= i < j <= t):
            raise ValueError(f"add_loop: need 0 <= i < j <= {t} (got {i}, {j})")
        self._grow()
        self._factored = None
        e = self.num_edges
        self._ei[e], self._ej[e], self._z[e], self._info[e] = i, j, z, information
        self._adj[i].append(e)
        self._adj[j].append(e)
        self.num_edges += 1
        self._solve_local(t, np.array([i], dtype=np.int64))

    def _graph(self, edges: NDArray[np.int64]) -> FactorGraph:
        g = FactorGraph()
        c = self.config
        loop = np.abs(self._ej[edges] - self._ei[edges]) > 1 if c.loop_kernel else np.zeros(len(edges), bool)
        for sel, kernel in ((edges[~loop], None), (edges[loop], c.loop_kernel)):
            if len(sel):
                g.add_between(self._ei[sel], self._ej[sel], self._z[sel], self._info[sel], robust=kernel,
                              robust_param=c.loop_kernel_scale)
        return g

    def _local_region(self, t: int, loops: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The poses a local solve frees (the newest ``window`` and a neighbourhood of each old loop end) and the
        edges touching them."""
        c = self.config
        free = set(range(max(0, t - c.window), t + 1))
        for a in loops:
            free.update(range(max(0, int(a) - c.loop_neighbourhood), min(t, int(a) + c.loop_neighbourhood) + 1))
        free_arr = np.array(sorted(free), dtype=np.int64)
        return free_arr, np.unique(np.concatenate([np.asarray(self._adj[p], np.int64) for p in free_arr]))

    def _solve_local(self, t: int, loops: NDArray[np.int64]) -> None:
        c = self.config
        free_arr, edges = self._local_region(t, loops)
        touched = np.unique(np.concatenate([self._ei[edges], self._ej[edges]]))
        fixed = np.setdiff1d(touched, free_arr)
        if fixed.size == 0:
            fixed = touched[:1]  # nothing outside: hold the oldest pose for the gauge
        vals = Values(touched, self._poses[touched])
        out, _ = Optimizer(self._graph(edges), OptimizerConfig(method="gn", max_iterations=c.iterations),
                           fixed_pose_keys=fixed).optimize(vals)
        self._poses[out.pose_keys] = out.poses
        self.local_solves += 1

    def _solve_full(self, iterations: int, method: str = "gn") -> Summary:
        n = self.num_poses
        cfg = OptimizerConfig(method="lm" if method == "lm" else "gn", max_iterations=iterations)
        key = (n, self.num_edges, cfg)
        if self._full is None or self._full[0] != key:  # edges are never changed once added: the count says it all
            self._full = (key, Optimizer(self._graph(np.arange(self.num_edges)), cfg))
        out, summary = self._full[1].optimize(Values(np.arange(n), self.poses))
        self._poses[:n] = out.poses
        self.full_solves += 1
        self._factored = self._full[1] if cfg.method == "gn" else None  # LM's factor holds its damping
        return summary

    def newest_covariance(self) -> Array | None:
        """Marginal covariance (3,3) of the newest pose, the first one held (the optimiser's gauge), from the
        factorisation of the last whole-graph Gauss-Newton solve while nothing was added since (else None): the
        Hessian at that solve's last linearisation point, three triangular solve pairs and no factorisation."""
        opt = self._factored
        if opt is None or opt.analysis is None or opt.solver is None:
            return None
        cols, _ = opt.analysis.variable_slices([self.num_poses - 1])
        if np.any(cols < 0):  # the newest pose is the held one
            return np.zeros((3, 3))
        return factored_block(opt.solver, opt.analysis.n, cols)

    def solve_full(self, iterations: int) -> Summary:
        """Gauss-Newton on the whole graph (``iterations`` at most), from the current estimate."""
        return self._solve_full(iterations)

    def finalize(self) -> Summary:
        """Optimise the whole graph to convergence (Levenberg-Marquardt)."""
        return self._solve_full(100, "lm")

    def graph(self) -> FactorGraph:
        """The whole graph so far (a new object)."""
        return self._graph(np.arange(self.num_edges))
