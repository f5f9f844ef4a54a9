"""Gauss-Newton and Levenberg-Marquardt on a :class:`FactorGraph`.

Objective: ``F(x) = sum_f rho_f(e_f^T Omega_f e_f)`` (g2o's chi2 when no robust kernel is set; no 1/2).
Linear system per iteration: ``(H + lambda D) dx = -g`` (GN: lambda = 0) with ``H = sum w J^T Omega J``,
``g = sum w J^T Omega e`` (IRLS weights ``w`` of the robust kernels at the current point; ``w = 1`` without kernel).

Levenberg-Marquardt uses Marquardt's scaling ``D = diag(H)`` (default; scale invariant; the default
``lambda_0 = 1e-9`` starts as Gauss-Newton and damps only after a rejected step: measured on the staged datasets,
``lambda_0 = 1e-5`` cost intel 1, manhattan.g2o 4 and cityTrees10000 25 extra iterations) or Levenberg's ``D = I``
with ``lambda_0 = tau * max(diag H)`` (g2o's choice). Gain ratio ``rho = (F(x) - F(x + dx)) / (-g.dx + lambda dx.D dx)``
(the decrease predicted by the linear model of F without the 1/2). A step is accepted when rho > 0; then lambda is
divided by ``lambda_decrease_factor`` (10) if rho > 0.75, doubled if rho < 0.25, else kept. A rejected step
multiplies lambda by nu and doubles nu (Nielsen's rule, Madsen, Nielsen & Tingleff 2004, sec. 3.2; nu resets to 2
on acceptance). Each rejected step costs one factorisation and counts as an iteration. (Nielsen's smooth update
``max(1/3, 1 - (2 rho - 1)^3)`` was tried first: it needed 23 iterations instead of 5 on manhattan.g2o because
lambda can only shrink 3x per step after the first, very nonlinear steps.)

Powell's dog leg ("dogleg"; Madsen, Nielsen & Tingleff 2004, sec. 3.3): one factorisation per linearisation point
gives the Gauss-Newton step; the step is GN, the scaled Cauchy step or the dog-leg blend inside the trust radius
(initially the GN step length). rho as for LM with the undamped model; rho > 0.75: radius = max(radius, 3 |dx|);
rho < 0.25: radius = |dx| / 2; a rejected step sets radius = |dx| / 4 and retries WITHOUT refactorising.

Termination rule (checked after every accepted step; GN accepts every step):
  1. ``F_old - F_new <= absolute_decrease_tol``                         -> "absolute decrease"
  2. ``F_old - F_new <= relative_decrease_tol * F_old``                 -> "relative decrease"
     (for GN also when F increased: it is reported as "cost increased" and the better point is kept)
  3. ``max |dx| <= step_tol``                                            -> "small step"
  4. ``F_new <= absolute_decrease_tol``                                  -> "zero cost"
  5. ``iterations == max_iterations``                                    -> "max iterations"
  6. LM only: ``max_rejections`` consecutive rejected steps or lambda above ``lambda_max`` -> "no progress"
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from slam2d.config import check_nonnegative, check_positive
from slam2d.graph.factors import KINDS
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.linear import SOLVERS, LinearSolver, SolverError, make_solver
from slam2d.graph.problem import Analysis
from slam2d.graph.robust import kernel_code


@dataclass(frozen=True, slots=True, kw_only=True)
class OptimizerConfig:
    """Settings of :func:`optimize`."""

    method: Literal["lm", "gn", "dogleg"] = "lm"
    """"lm" (Levenberg-Marquardt), "gn" (Gauss-Newton, undamped) or "dogleg" (Powell's dog leg)."""
    max_iterations: int = 100
    """maximum number of iterations (accepted + rejected LM steps count; each is one factorisation)."""
    relative_decrease_tol: float = 1e-7
    """stop when an accepted step lowers the cost by less than this fraction of it."""
    absolute_decrease_tol: float = 1e-9
    """stop when an accepted step lowers the cost by less than this (chi2 units)."""
    step_tol: float = 1e-12
    """stop when the largest step component is below this (m / rad)."""
    damping: Literal["marquardt", "levenberg"] = "marquardt"
    """LM: "marquardt" solves (H + lambda diag(H)) dx = -g (scale invariant); "levenberg" uses lambda I."""
    lambda_initial_factor: float = 1e-9
    """LM: initial lambda (marquardt), or this * max(diag H) (levenberg, Nielsen's tau)."""
    lambda_decrease_factor: float = 10.0
    """LM: divide lambda by this after a step whose gain ratio exceeds 0.75."""
    lambda_max: float = 1e16
    """LM: give up when lambda grows beyond this."""
    max_rejections: int = 20
    """LM: give up after this many consecutive rejected steps."""
    linear_solver: str = "auto"
    """"auto" (qdldl, else cholmod, else splu), "qdldl", "cholmod", "splu" or "dense"."""
    robust_kernel: str | None = None
    """override every selected factor's kernel: None (keep per-factor kernels), "none", "huber", "cauchy", "dcs"."""
    robust_param: float = 1.0
    """parameter of ``robust_kernel`` (huber/cauchy delta in sqrt(chi2) units; dcs Phi in chi2 units)."""
    robust_kinds: tuple[str, ...] = ()
    """factor types the override applies to (empty: all types)."""
    gauge: Literal["first_pose", "none"] = "first_pose"
    """hold the lowest-key pose of every component without a pose prior ("none": rely on priors)."""

    def __post_init__(self) -> None:
        if self.method not in ("lm", "gn", "dogleg"):
            raise ValueError(f"OptimizerConfig.method must be 'lm', 'gn' or 'dogleg' (got {self.method!r})")
        for name in ("max_iterations", "max_rejections"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise ValueError(f"OptimizerConfig.{name} must be an integer >= 1 (got {v!r})")
        if not (isinstance(self.lambda_decrease_factor, int | float) and self.lambda_decrease_factor > 1
                and np.isfinite(self.lambda_decrease_factor)):
            raise ValueError("OptimizerConfig.lambda_decrease_factor must be a finite number > 1 (got "
                             f"{self.lambda_decrease_factor!r})")
        if self.linear_solver != "auto" and self.linear_solver not in SOLVERS:
            raise ValueError(f"OptimizerConfig.linear_solver: unknown linear solver {self.linear_solver!r}; choose one "
                             f"of auto, {', '.join(SOLVERS)}")
        unknown = sorted(set(self.robust_kinds) - set(KINDS))
        if unknown:
            raise ValueError(f"OptimizerConfig.robust_kinds: unknown factor type(s) {unknown}; known: {sorted(KINDS)}")
        check_nonnegative(self, "relative_decrease_tol", "absolute_decrease_tol", "step_tol")
        check_positive(self, "lambda_initial_factor", "lambda_max", "robust_param")
        try:
            kernel_code(self.robust_kernel)
        except ValueError as e:
            raise ValueError(f"OptimizerConfig.robust_kernel: {e}") from None
        if self.damping not in ("marquardt", "levenberg"):
            raise ValueError(f"OptimizerConfig.damping must be 'marquardt' or 'levenberg' (got {self.damping!r})")
        if self.gauge not in ("first_pose", "none"):
            raise ValueError(f"OptimizerConfig.gauge must be 'first_pose' or 'none' (got {self.gauge!r})")


@dataclass
class Summary:
    """What happened in one :func:`optimize` call."""

    chi2_initial: float
    chi2_final: float
    cost_initial: float
    cost_final: float
    iterations: int
    linear_solves: int
    rejected_steps: int
    termination: str
    solve_s: float
    analysis_s: float
    linearize_s: float
    factorize_s: float
    linear_solver: str
    method: str
    dimension: int
    hessian_nnz_upper: int
    num_components: int
    gauge_pose_keys: list[int]
    lambda_final: float = 0.0
    cost_history: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


class Optimizer:
    """Reusable optimiser: keeps the symbolic analysis and the linear solver (with its symbolic factorisation)
    between calls while the graph structure and the variable sets are unchanged; a changed structure (factors or
    variables appended) triggers a new analysis automatically.
    """

    def __init__(self, graph: FactorGraph, config: OptimizerConfig | None = None, *,
                 fixed_pose_keys: ArrayLike = ()) -> None:
        self.graph = graph
        self.config = config or OptimizerConfig()
        self.fixed_pose_keys = np.asarray(fixed_pose_keys, np.int64).reshape(-1)
        self.analysis: Analysis | None = None
        self.solver: LinearSolver | None = None
        self.analyses_done = 0
        # the graph the analysis was built on: the caller's, or a private copy carrying the config's kernel override
        self._working: FactorGraph = graph
        self._analysed: FactorGraph = graph
        self._working_key: tuple[object, ...] = ()

    def _working_graph(self) -> FactorGraph:
        """The caller's graph, or (``robust_kernel`` set) a private view of it with the override applied: the
        caller's per-factor kernels are never rewritten."""
        cfg = self.config
        if cfg.robust_kernel is None:
            return self.graph
        key = (self.graph.structure_version, cfg.robust_kernel, cfg.robust_param, cfg.robust_kinds)
        if self._working is self.graph or self._working_key != key:
            self._working = self.graph.with_robust(cfg.robust_kinds, cfg.robust_kernel, cfg.robust_param)
            self._working_key = key
        return self._working

    def _prepare(self, values: Values) -> float:
        t0 = time.perf_counter()
        cfg = self.config
        graph = self._working_graph()
        if self.analysis is None or graph is not self._analysed or not self.analysis.compatible(graph, values):
            self.analysis = Analysis(graph, values, fixed_pose_keys=self.fixed_pose_keys, gauge=cfg.gauge)
            self.solver = make_solver(cfg.linear_solver)
            self.analyses_done += 1
            self._analysed = graph
        return time.perf_counter() - t0

    def optimize(self, values: Values) -> tuple[Values, Summary]:
        """Optimise from ``values`` (not modified); returns new values and a summary."""
        t_start = time.perf_counter()
        t_an = self._prepare(values)
        an, solver, cfg = self.analysis, self.solver, self.config
        assert an is not None and solver is not None
        poses, points = values.poses.copy(), values.points.copy()
        t_lin = t_fac = 0.0

        t0 = time.perf_counter()
        cost, chi2v, data, g = an.linearize(poses, points)
        t_lin += time.perf_counter() - t0
        cost0, chi20 = cost, chi2v
        hmat = an.upper(np.zeros(an.nnz))
        history = [cost]
        if cfg.damping == "levenberg":
            lam = cfg.lambda_initial_factor * float(data[an.diag_pos].max()) if an.n else 0.0
        else:
            lam = cfg.lambda_initial_factor
        nu = 2.0
        radius, fresh = 0.0, True  # dogleg trust radius (0: start with the full Gauss-Newton step)
        h_gn = h_cp = np.zeros(an.n)
        n_gn = n_cp = predicted_dl = 0.0
        it = solves = rejected = consecutive = 0
        termination = "max iterations"
        if an.n == 0:
            termination = "no free variables"
        elif cfg.method != "gn" and cost <= cfg.absolute_decrease_tol:
            termination = "zero cost"  # already optimal: every damped step would be rejected until lambda_max
        while an.n and termination == "max iterations" and it < cfg.max_iterations:
            it += 1
            if cfg.method == "dogleg":
                if fresh:  # new linearisation point: one factorisation gives the GN step for every radius tried
                    np.copyto(hmat.data, data)
                    t0 = time.perf_counter()
                    try:
                        solver.factorize(hmat)
                        h_gn = -solver.solve(g)
                    except SolverError:
                        raise SolverError("dogleg: H is singular (unconstrained variables or missing gauge); "
                                          "try --solver lm or add priors") from None
                    t_fac += time.perf_counter() - t0
                    solves += 1
                    hg = _sym_matvec(hmat, data[an.diag_pos], g)
                    gg, ghg = float(np.einsum("i,i->", g, g)), float(np.einsum("i,i->", g, hg))
                    h_cp = -(gg / ghg) * g if ghg > 0 else -g
                    n_gn, n_cp = float(np.linalg.norm(h_gn)), float(np.linalg.norm(h_cp))
                    if radius <= 0:
                        radius = n_gn
                    fresh = False
                if n_gn <= radius:
                    dx = h_gn
                elif n_cp >= radius:
                    dx = (radius / n_cp) * h_cp
                else:  # |h_cp + beta (h_gn - h_cp)| = radius, beta in (0, 1)
                    d = h_gn - h_cp
                    qa = float(np.einsum("i,i->", d, d))
                    qb = 2.0 * float(np.einsum("i,i->", h_cp, d))
                    qc = n_cp * n_cp - radius * radius
                    beta = (-qb + np.sqrt(max(qb * qb - 4 * qa * qc, 0.0))) / (2 * qa)
                    dx = h_cp + beta * d
                predicted_dl = -(2.0 * float(np.einsum("i,i->", g, dx))
                                 + float(np.einsum("i,i->", dx, _sym_matvec(hmat, data[an.diag_pos], dx))))
            else:
                # refill the values of one CSC matrix (no per-iteration sparse construction / format checks)
                np.copyto(hmat.data, data)
                if cfg.method == "lm":
                    dscale = _damping_diag(data[an.diag_pos], cfg.damping)
                    hmat.data[an.diag_pos] += lam * dscale
                t0 = time.perf_counter()
                try:
                    solver.factorize(hmat)
                    dx = -solver.solve(g)
                except SolverError:
                    if cfg.method == "gn":
                        raise SolverError("Gauss-Newton: H is singular (unconstrained variables or missing gauge); "
                                          "try --solver lm or add priors") from None
                    dx = np.full(an.n, np.nan)
                t_fac += time.perf_counter() - t0
                solves += 1
                if not np.all(np.isfinite(dx)):
                    if cfg.method == "gn":
                        raise SolverError("Gauss-Newton produced a non-finite step (H singular?)")
                    rejected += 1
                    consecutive += 1
                    lam *= nu
                    nu *= 2
                    if consecutive >= cfg.max_rejections or lam > cfg.lambda_max:
                        termination = "no progress"
                        break
                    continue
            p_new, q_new = an.retract(poses, points, dx)
            t0 = time.perf_counter()
            cost_new, chi2_new, data_new, g_new = an.linearize(p_new, q_new)
            t_lin += time.perf_counter() - t0
            decrease = cost - cost_new
            if cfg.method == "dogleg":
                rho = decrease / predicted_dl if predicted_dl > 0 else -1.0
                step_norm = float(np.linalg.norm(dx))
                if not (rho > 0 and np.isfinite(cost_new)):
                    rejected += 1
                    consecutive += 1
                    radius = 0.25 * step_norm
                    if consecutive >= cfg.max_rejections or radius <= cfg.step_tol:
                        termination = "no progress"
                        break
                    continue
                consecutive = 0
                if rho > 0.75:
                    radius = max(radius, 3.0 * step_norm)
                elif rho < 0.25:
                    radius = 0.5 * step_norm
                fresh = True
            elif cfg.method == "lm":
                # einsum, not BLAS: a threaded BLAS dot costs milliseconds on a busy machine
                predicted = float(-np.einsum("i,i->", g, dx) + lam * np.einsum("i,i,i->", dx, dscale, dx))
                rho = decrease / predicted if predicted > 0 else -1.0
                if not (rho > 0 and np.isfinite(cost_new)):
                    rejected += 1
                    consecutive += 1
                    lam *= nu
                    nu *= 2
                    if consecutive >= cfg.max_rejections or lam > cfg.lambda_max:
                        termination = "no progress"
                        break
                    continue
                consecutive = 0
                if rho > 0.75:
                    lam = max(lam / cfg.lambda_decrease_factor, 1e-15)
                elif rho < 0.25:
                    lam *= 2.0
                nu = 2.0
            elif not np.isfinite(cost_new):
                raise SolverError("Gauss-Newton diverged (non-finite cost)")
            if cfg.method == "gn" and decrease < 0 and abs(decrease) <= cfg.relative_decrease_tol * cost:
                termination = "cost increased"
                break  # keep the better, current point
            poses, points, data, g = p_new, q_new, data_new, g_new
            cost_old, cost, chi2v = cost, cost_new, chi2_new
            history.append(cost)
            if 0 <= decrease <= cfg.absolute_decrease_tol:
                termination = "absolute decrease"
                break
            if 0 <= decrease <= cfg.relative_decrease_tol * cost_old:
                termination = "relative decrease"
                break
            if float(np.abs(dx).max()) <= cfg.step_tol:
                termination = "small step"
                break
            if cost <= cfg.absolute_decrease_tol:
                termination = "zero cost"
                break
        out = Values(values.pose_keys, poses, values.point_keys, points)  # Values copies what it is given
        summary = Summary(
            chi2_initial=chi20, chi2_final=chi2v, cost_initial=cost0, cost_final=cost, iterations=it,
            linear_solves=solves, rejected_steps=rejected, termination=termination,
            solve_s=time.perf_counter() - t_start, analysis_s=t_an, linearize_s=t_lin, factorize_s=t_fac,
            linear_solver=getattr(solver, "name", "?"), method=cfg.method, dimension=an.n,
            hessian_nnz_upper=an.nnz, num_components=an.num_components,
            gauge_pose_keys=[int(k) for k in an.gauge_pose_keys], lambda_final=lam, cost_history=history,
        )
        return out, summary


def _sym_matvec(upper: sp.csc_matrix, diag: np.ndarray, x: np.ndarray) -> np.ndarray:
    """H x from the upper triangle of symmetric H. Shapes: (n,) -> (n,)."""
    return np.asarray(upper @ x + upper.T @ x - diag * x)


def _damping_diag(diag: np.ndarray, damping: str) -> np.ndarray:
    """D of the damped system H + lambda D: ones (Levenberg) or diag(H) clamped away from 0 (Marquardt)."""
    if damping == "levenberg":
        return np.ones_like(diag)
    return np.maximum(diag, 1e-9 * max(1.0, float(diag.max())))


def optimize(graph: FactorGraph, values: Values, config: OptimizerConfig | None = None, *,
             fixed_pose_keys: ArrayLike = ()) -> tuple[Values, Summary]:
    """One-shot optimisation (builds the analysis). Use :class:`Optimizer` to re-optimise incrementally."""
    return Optimizer(graph, config, fixed_pose_keys=fixed_pose_keys).optimize(values)
