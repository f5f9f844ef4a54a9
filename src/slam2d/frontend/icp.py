"""Iterative closest point scan matching in SE(2): point-to-point and point-to-line, with a constraint covariance.

Convention (the one every caller relies on): ``icp(source, target)`` returns ``T = T_target_source``, the pose of the
source frame expressed in the target frame, so that ``transform_points(T, source) ~ target``. For two scans taken at
poses ``a`` (target) and ``b`` (source), ``T`` estimates ``between(a, b)`` and ``b = compose(a, T)``.

Each iteration matches the source points, moved by the current estimate, to their nearest target points (one
``cKDTree`` query for all points), rejects pairs farther than ``max_correspondence_m`` and then keeps the
``trim_fraction`` closest (trimmed ICP), or, with ``median_gate``, those within that many times the median
distance. Point-to-point solves the increment in closed form (SVD, with the det(R) = +1 guard against
reflections) and composes it on the LEFT, ``T <- dT (+) T``, because it was estimated between points already
expressed in the target frame. Point-to-line takes Gauss-Newton steps on
``r_i = n_i . (R p_i + t - q_i)`` directly in the pose parameters (additive with wrap, the library's convention).

Covariance: ``sigma^2 (J^T J)^-1`` at the solution, with ``J`` the Jacobian of the final residuals with respect to
``[x, y, theta]`` of ``T`` and ``sigma^2`` the residual variance (sum of squares over dof). It is the usual
Hessian-based estimate: it captures degeneracy (a corridor is unconstrained along its axis) but not wrong matches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from slam2d.config import check_nonnegative, check_positive, check_probability
from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle, wrap_angle_scalar

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class ICPConfig:
    """Scan-matching settings."""

    method: Literal["point-to-point", "point-to-line"] = "point-to-line"
    """error metric: distance to the matched point, or to the line through it (needs target normals)."""
    max_iterations: int = 40
    """iteration cap."""
    max_correspondence_m: float = 1.0
    """matches farther than this are outliers (m)."""
    trim_fraction: float = 0.9
    """after the distance gate keep only this fraction of the closest matches (1.0: no trimming)."""
    median_gate: float = 0.0
    """instead of a fixed fraction, keep the matches within this many times the median match distance (after the
    distance gate, every iteration; 0: ``trim_fraction`` applies). The cut follows the scan: a clean one keeps
    nearly all its matches, one with moved objects drops their far matches."""
    tolerance: float = 1e-6
    """stop when the update is smaller than this (m and rad)."""
    normal_neighbours: int = 5
    """points used to fit each target normal (point-to-line)."""
    min_matches: int = 8
    """fewer accepted matches than this means failure (``converged=False``)."""

    def __post_init__(self) -> None:
        if self.method not in ("point-to-point", "point-to-line"):
            raise ValueError(f"ICPConfig.method must be 'point-to-point' or 'point-to-line' (got {self.method!r})")
        check_positive(self, "max_correspondence_m", "tolerance")
        check_probability(self, "trim_fraction", open_low=True)
        check_nonnegative(self, "median_gate")
        if self.max_iterations < 1:
            raise ValueError(f"ICPConfig.max_iterations must be >= 1 (got {self.max_iterations})")
        if self.normal_neighbours < 2:
            raise ValueError(f"ICPConfig.normal_neighbours must be >= 2 (got {self.normal_neighbours})")
        if self.min_matches < 3:
            raise ValueError(f"ICPConfig.min_matches must be >= 3 (got {self.min_matches})")


@dataclass(frozen=True)
class ICPResult:
    """Outcome of one alignment. Shapes: transform (3,) = T_target_source, covariance (3,3)."""

    transform: Array
    covariance: Array
    converged: bool
    iterations: int
    matches: int
    rmse_m: float
    fitness: float
    """fraction of source points with an accepted match."""


def estimate_normals(points: ArrayLike, k: int = 5, tree: cKDTree | None = None) -> Array:
    """Unit normals by PCA of each point's ``k`` nearest neighbours (all points at once). Shapes: (N,2) -> (N,2)."""
    p = np.asarray(points, dtype=np.float64)
    k = min(k, len(p))
    tree = tree if tree is not None else cKDTree(p)
    _, idx = tree.query(p, k=k)
    nb = p[idx.reshape(len(p), k)]  # (N,k,2)
    x, y = nb[:, :, 0], nb[:, :, 1]
    cx, cy = x - x.mean(axis=1, keepdims=True), y - y.mean(axis=1, keepdims=True)
    xx, xy, yy = cx * cx, cx * cy, cy * cy
    cov = np.empty((len(p), 2, 2))
    # the scatter matrices, summed over the neighbours one column at a time (an einsum over (N,k,2) costs 3x)
    sxx, sxy, syy = xx[:, 0].copy(), xy[:, 0].copy(), yy[:, 0].copy()
    for i in range(1, k):
        sxx += xx[:, i]
        sxy += xy[:, i]
        syy += yy[:, i]
    cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 0], cov[:, 1, 1] = sxx, sxy, sxy, syy
    _, vec = np.linalg.eigh(cov)  # ascending eigenvalues: column 0 is the normal
    return vec[:, :, 0]


def kabsch_2d(p: ArrayLike, q: ArrayLike) -> Array:
    """Least-squares rigid transform ``T`` with ``transform_points(T, p) ~ q`` (never a reflection).

    Shapes: (N,2),(N,2) -> (3,).
    """
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
    pm, qm = p.mean(axis=0), q.mean(axis=0)
    h = (p - pm).T @ (q - qm)
    u, _, vt = np.linalg.svd(h)
    # det guard: a reflection fits mirrored data better than any rotation; flip the weakest axis instead
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, d]) @ u.T
    t = qm - r @ pm
    return np.array([t[0], t[1], float(wrap_angle(np.arctan2(r[1, 0], r[0, 0])))])


def _rotated_derivative(c: float, s: float, x: Array, y: Array) -> tuple[Array, Array]:
    """d(R p)/d theta = R' p for each source point p = (x, y), with ``c, s`` the cosine and sine of R's angle: its
    x and y components, (N,) each."""
    return -s * x - c * y, c * x - s * y


def _jacobian_rows(theta: float, src: Array) -> Array:
    """d(R p + t)/d[x, y, theta] for each source point: (N,2,3)."""
    n = len(src)
    j = np.zeros((n, 2, 3))
    j[:, 0, 0] = 1.0
    j[:, 1, 1] = 1.0
    j[:, 0, 2], j[:, 1, 2] = _rotated_derivative(np.cos(theta), np.sin(theta), src[:, 0], src[:, 1])
    return j


@dataclass(frozen=True)
class ICPTarget:
    """A target prepared once for many alignments (a local map matched by every scan): its finite points (M,2),
    their KD-tree and, for point-to-line, their normals (M,2)."""

    points: Array
    tree: cKDTree
    normals: Array | None

    def moved(self, delta: ArrayLike) -> ICPTarget:
        """The same target moved rigidly by ``delta`` (3,) (points mapped, normals rotated, tree rebuilt): the
        normals' neighbourhood fits are not redone, which is most of :func:`prepare_target`'s cost."""
        d = np.asarray(delta, dtype=np.float64)
        pts = se2.transform_points(d, self.points)
        normals = None if self.normals is None else se2.transform_points(np.array([0.0, 0.0, d[2]]), self.normals)
        return ICPTarget(pts, cKDTree(pts), normals)


def prepare_target(target: ArrayLike, config: ICPConfig | None = None) -> ICPTarget:
    """Build the KD-tree (and normals for point-to-line) of ``target`` (M,2) once."""
    cfg = config or ICPConfig()
    tgt = np.asarray(target, dtype=np.float64).reshape(-1, 2)
    tgt = tgt[np.all(np.isfinite(tgt), axis=1)]
    tree = cKDTree(tgt)
    normals = None
    if cfg.method == "point-to-line" and len(tgt) >= max(cfg.min_matches, cfg.normal_neighbours):
        normals = estimate_normals(tgt, cfg.normal_neighbours, tree)
    return ICPTarget(tgt, tree, normals)


def icp(source: ArrayLike, target: ArrayLike | ICPTarget, initial: ArrayLike | None = None,
        config: ICPConfig | None = None, *, prior: tuple[ArrayLike, ArrayLike] | None = None) -> ICPResult:
    """Align ``source`` points to ``target`` points; returns ``T_target_source`` (see the module docstring).

    Shapes: source (N,2), target (M,2), initial (3,) or None (identity).
    Non-finite points are dropped. Too few points or matches gives ``converged=False`` with the initial guess and
    an infinite covariance, never an exception, so a SLAM loop can fall back to odometry.

    ``prior`` (point-to-line only): ``(mean (3,), weights (3,))`` adds the rows ``weights * (T - mean)`` (angle
    wrapped) to every Gauss-Newton step, beside the matches' residuals (each weighs 1 per metre): a direction the
    scan leaves loose (a corridor's axis) then follows ``mean`` instead of the iterate. The covariance stays the
    matches' alone.
    """
    cfg = config or ICPConfig()
    if prior is not None and cfg.method != "point-to-line":
        raise ValueError("icp: a prior needs the point-to-line method")
    # the prior's rows (mean, weights, Jacobian): the Jacobian is constant, only the residual moves with the iterate
    prior_rows = None if prior is None else (np.asarray(prior[0], dtype=np.float64),
                                             np.asarray(prior[1], dtype=np.float64),
                                             np.diag(np.asarray(prior[1], dtype=np.float64)))
    src = np.asarray(source, dtype=np.float64).reshape(-1, 2)
    prep = target if isinstance(target, ICPTarget) else prepare_target(target, cfg)
    src = src[np.all(np.isfinite(src), axis=1)]
    t = np.zeros(3) if initial is None else np.asarray(initial, dtype=np.float64).copy()
    fail = ICPResult(t, np.full((3, 3), np.inf), False, 0, 0, float("inf"), 0.0)
    if len(src) < cfg.min_matches or len(prep.points) < max(cfg.min_matches, cfg.normal_neighbours):
        return fail
    tgt, tree, normals = prep.points, prep.tree, prep.normals
    if cfg.method == "point-to-point":
        normals = None
    elif normals is None:
        normals = estimate_normals(tgt, cfg.normal_neighbours, tree)

    sx, sy = src[:, 0].copy(), src[:, 1].copy()  # contiguous columns: every iteration reads them
    gate, trim, median_gate, tol = cfg.max_correspondence_m, cfg.trim_fraction, cfg.median_gate, cfg.tolerance
    moved = np.empty_like(src)

    def match(tr: Array) -> tuple[NDArray[np.intp], NDArray[np.intp], float, float]:
        """The accepted matches (source indices, closest first, and their target indices) of the source
        moved by ``tr`` into ``moved``, and the cosine and sine of ``tr``'s angle."""
        # se2.transform_points written into one buffer: the same arithmetic, no temporaries to stack
        c, s = np.cos(tr[2]), np.sin(tr[2])
        moved[:, 0] = tr[0] + c * sx - s * sy
        moved[:, 1] = tr[1] + s * sx + c * sy
        d, j = tree.query(moved, distance_upper_bound=gate)
        if median_gate > 0:
            # unmatched points have d = inf and sort last; a stable sort keeps index order among equal distances.
            # The median and the count under the gate are read off the sorted distances (np.median's value: the
            # middle one, or the mean of the middle two)
            order = np.argsort(d, kind="stable")
            nf = int(np.count_nonzero(d < np.inf))
            keep = 0
            if nf:
                ds = d[order[:nf]]
                h = nf // 2
                median = float(ds[h]) if nf % 2 else float((ds[h - 1] + ds[h]) / 2.0)
                keep = int(np.searchsorted(ds, median_gate * median, side="right"))
            ok = order[:keep]
        elif trim < 1.0:
            found = int(np.count_nonzero(d < np.inf))
            ok = np.argsort(d, kind="stable")[:max(math.ceil(trim * found), 1) if found else 0]
        else:
            ok = np.flatnonzero(np.isfinite(d))
        return ok, j[ok], c, s

    converged = False
    it = 0
    history: list[Array] = []  # the last 4 transforms
    for it in range(1, cfg.max_iterations + 1):
        ok, j, c, s = match(t)
        if len(ok) < cfg.min_matches:
            return ICPResult(t, np.full((3, 3), np.inf), False, it, len(ok), float("inf"), len(ok) / len(src))
        if normals is None:
            dt = kabsch_2d(moved[ok], tgt[j])
            t = se2.compose(dt, t)  # dt maps target-frame points to target-frame points: it goes on the left
            step = np.abs(dt)
        else:
            # the rows [n, n . d(R p)/d theta] and residuals n . (R p + t - q), written column by column
            jac = np.empty((len(ok), 3))
            jac[:, :2] = normals[j]
            n0, n1 = jac[:, 0], jac[:, 1]
            dx, dy = _rotated_derivative(c, s, sx[ok], sy[ok])
            jac[:, 2] = n0 * dx + n1 * dy
            m, q = moved[ok], tgt[j]
            r = n0 * (m[:, 0] - q[:, 0]) + n1 * (m[:, 1] - q[:, 1])
            if prior_rows is not None:
                pm, pw, pj = prior_rows
                e = t - pm
                e[2] = wrap_angle_scalar(float(e[2]))
                jac, r = np.vstack([jac, pj]), np.concatenate([r, pw * e])
            # minimum-norm step: a degenerate direction (corridor axis) is left where the initial guess put it
            delta = -np.linalg.lstsq(jac, r, rcond=1e-8)[0]
            t = t + delta  # se2.retract
            t[2] = wrap_angle_scalar(float(t[2]))
            step = np.abs(delta)
        # trimmed matching can flip between two correspondence sets forever (a limit cycle of ~1 mm): returning
        # to a transform of the last few iterations is convergence as well
        if step.max() < tol:
            converged = True
            break
        # se2.local's x and y are plain differences: only a transform that passes them needs the full check
        if any(abs(t[0] - h[0]) < tol and abs(t[1] - h[1]) < tol for h in history) and \
                (np.abs(se2.local(np.array(history), t)) < tol).all(axis=1).any():
            converged = True
            break
        history = [*history[-3:], t]
    ok, j, _, _ = match(t)
    if len(ok) < cfg.min_matches:
        return ICPResult(t, np.full((3, 3), np.inf), False, it, len(ok), float("inf"), len(ok) / len(src))
    jr = _jacobian_rows(float(t[2]), src[ok])
    if normals is None:
        res = (moved[ok] - tgt[j]).ravel()
        jac = jr.reshape(-1, 3)
        dof = max(res.size - 3, 1)
        rmse = float(np.sqrt(np.mean(np.sum((moved[ok] - tgt[j]) ** 2, axis=1))))
    else:
        n = normals[j]
        res = np.einsum("ni,ni->n", n, moved[ok] - tgt[j])
        jac = np.einsum("ni,nij->nj", n, jr)
        dof = max(res.size - 3, 1)
        rmse = float(np.sqrt(np.mean(res**2)))
    h = jac.T @ jac
    sigma2 = max(float(res @ res) / dof, 1e-12)
    # eigen-inverse with a floor: an unobservable direction gets a huge (not NaN/inf) variance only along itself
    lam, vec = np.linalg.eigh(h)
    lam = np.maximum(lam, 1e-12 * max(float(lam[-1]), 1e-300))
    cov = sigma2 * (vec / lam) @ vec.T
    return ICPResult(t, 0.5 * (cov + cov.T), converged, it, len(ok), rmse,
                     len(ok) / len(src))
