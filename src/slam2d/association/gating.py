"""What every association method shares: input checks, innovations, chi-square gates, mutual exclusion, and the
NEW / CLUTTER rule for observations left unmatched.

Conventions used by all methods (documented once, here):

* Innovation of observation ``i`` against candidate ``j``: ``nu_ij = [r_i - r_j, angle_diff(b_i, b_j)]``.
* Individual compatibility (IC): ``d2_ij = nu_ij^T S_j^-1 nu_ij <= chi2.ppf(gate_probability, 2)`` and, when
  ``descriptor_max_distance > 0`` and both sides carry descriptors, ``|desc_i - desc_j| <= descriptor_max_distance``.
  A pair failing the descriptor test is *not a candidate at all*: it counts for neither gate below.
* Joint compatibility of a set of n pairs with distinct candidates: the stacked innovation ``nu_H`` and the matching
  sub-matrix ``C_H`` of ``S_joint`` give ``NIS_H = nu_H^T C_H^-1 nu_H <= chi2.ppf(gate_probability, 2n)``.
* An observation left unmatched is ``NEW`` when its d2 to every descriptor-compatible candidate exceeds
  ``chi2.ppf(new_landmark_probability, 2)`` (the wide gate), otherwise ``CLUTTER`` (close enough to something known
  that starting a landmark could duplicate it, but not taken: ambiguous).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from slam2d.association.base import CLUTTER, NEW, AssociationConfig, AssociationResult, Candidates
from slam2d.geometry.angles import angle_diff
from slam2d.geometry.gaussian import chi2_gate
from slam2d.log import Observations

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: relative tolerance for the symmetry check of S and S_joint (round-off of H P H^T + R is ~1e-16 relative)
SYMMETRY_RTOL = 1e-8


@functools.lru_cache(maxsize=4096)
def _chi2(probability: float, dof: int) -> float:
    # scipy's chi2.ppf costs ~0.5 ms a call; the same few quantiles are asked for at every step of a run
    return chi2_gate(probability, dof)


def gate_thresholds(config: AssociationConfig) -> tuple[float, float]:
    """``(individual gate, new-landmark gate)``: chi-square quantiles with 2 dof at the configured probabilities."""
    return _chi2(config.gate_probability, 2), _chi2(config.new_landmark_probability, 2)


def joint_thresholds(probability: float, max_pairs: int) -> Array:
    """``t[n] = chi2.ppf(probability, 2n)`` for n = 0..max_pairs (t[0] = 0: the empty hypothesis has NIS 0).

    Shapes: -> (max_pairs+1,).
    """
    t = np.zeros(max_pairs + 1)
    for n in range(1, max_pairs + 1):
        t[n] = _chi2(probability, 2 * n)
    return t


# ---------------------------------------------------------------------------------------------- input validation
def _check_cov_blocks(s: Array, what: str, ids: IntArray) -> Array:
    """Check (L,2,2) covariances: finite, symmetric, positive definite; return the symmetrised copy."""
    if not np.all(np.isfinite(s)):
        bad = int(np.argwhere(~np.isfinite(s).all(axis=(1, 2)))[0, 0])
        raise ValueError(f"{what}[{bad}] (candidate id {ids[bad]}) has non-finite entries")
    scale = np.maximum(np.abs(s).max(axis=(1, 2)), np.finfo(float).tiny)
    asym = np.abs(s[:, 0, 1] - s[:, 1, 0]) > SYMMETRY_RTOL * scale
    if np.any(asym):
        bad = int(np.flatnonzero(asym)[0])
        raise ValueError(f"{what}[{bad}] (candidate id {ids[bad]}) is not symmetric: {s[bad].tolist()}")
    a, d = s[:, 0, 0], s[:, 1, 1]
    b = 0.5 * (s[:, 0, 1] + s[:, 1, 0])
    # a 2x2 symmetric matrix is positive definite iff a > 0 and det > 0; a relative floor on det catches matrices
    # that are singular up to round-off, whose inverse would turn any innovation into a huge (or tiny) distance
    det = a * d - b * b
    bad_mask = ~((a > 0) & (d > 0) & (det > 1e-12 * a * d))
    if np.any(bad_mask):
        bad = int(np.flatnonzero(bad_mask)[0])
        raise ValueError(f"{what}[{bad}] (candidate id {ids[bad]}) is singular or not positive definite: "
                         f"{s[bad].tolist()}")
    out = s.copy()
    out[:, 0, 1] = out[:, 1, 0] = b
    return out


def validate(observations: Observations, candidates: Candidates) -> tuple[Array, Array | None]:
    """Check shapes and values of both inputs; raise ValueError naming the field. Returns symmetrised (S, S_joint).

    Checked: observation arrays (K,) finite with range >= 0; candidate ids (L,) non-negative and unique (NEW and
    CLUTTER are negative, and mutual exclusion needs one row per landmark); z_pred (L,2) finite; S (L,2,2) finite,
    symmetric, positive definite; S_joint (2L,2L) finite, symmetric, its 2x2 diagonal blocks equal to S; descriptors
    with matching dimension. Positive definiteness of S_joint is checked where it is used (on the sub-matrix of the
    candidates involved), because a full factorisation would cost O(L^3).
    """
    k = len(observations)
    for name in ("range_m", "bearing_rad", "landmark_id"):
        arr = getattr(observations, name)
        if np.shape(arr) != (k,):
            raise ValueError(f"Observations.{name} must have shape ({k},), got {np.shape(arr)}")
    if not (np.all(np.isfinite(observations.range_m)) and np.all(np.isfinite(observations.bearing_rad))):
        raise ValueError("Observations.range_m / bearing_rad contain non-finite values")
    if np.any(observations.range_m < 0):
        raise ValueError("Observations.range_m must be >= 0")
    if observations.descriptor is not None and (np.ndim(observations.descriptor) != 2
                                                or np.shape(observations.descriptor)[0] != k):
        raise ValueError(f"Observations.descriptor must have shape ({k}, D), got {np.shape(observations.descriptor)}")
    ids = np.asarray(candidates.ids)
    n = ids.shape[0] if ids.ndim == 1 else -1
    if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"Candidates.ids must be a 1-D integer array, got shape {ids.shape} dtype {ids.dtype}")
    if np.any(ids < 0):
        raise ValueError(f"Candidates.ids must be >= 0 (negative values mean NEW/CLUTTER), got {ids[ids < 0][:5]}")
    if len(np.unique(ids)) != n:
        uniq, counts = np.unique(ids, return_counts=True)
        raise ValueError(f"Candidates.ids must be unique; repeated: {uniq[counts > 1][:5].tolist()}")
    if np.shape(candidates.z_pred) != (n, 2):
        raise ValueError(f"Candidates.z_pred must have shape ({n}, 2), got {np.shape(candidates.z_pred)}")
    if not np.all(np.isfinite(candidates.z_pred)):
        raise ValueError("Candidates.z_pred contains non-finite values")
    if np.shape(candidates.S) != (n, 2, 2):
        raise ValueError(f"Candidates.S must have shape ({n}, 2, 2), got {np.shape(candidates.S)}")
    s = _check_cov_blocks(np.asarray(candidates.S, dtype=np.float64), "Candidates.S", ids)
    sj = None
    if candidates.S_joint is not None:
        sj = np.asarray(candidates.S_joint, dtype=np.float64)
        if sj.shape != (2 * n, 2 * n):
            raise ValueError(f"Candidates.S_joint must have shape ({2 * n}, {2 * n}), got {sj.shape}")
        if not np.all(np.isfinite(sj)):
            raise ValueError("Candidates.S_joint contains non-finite values")
        scale = max(float(np.abs(sj).max(initial=0.0)), np.finfo(float).tiny)
        if np.any(np.abs(sj - sj.T) > SYMMETRY_RTOL * scale):
            i, j = np.unravel_index(int(np.argmax(np.abs(sj - sj.T))), sj.shape)
            raise ValueError(f"Candidates.S_joint is not symmetric (entry [{i},{j}]={sj[i, j]!r} vs [{j},{i}]="
                             f"{sj[j, i]!r})")
        blocks = sj.reshape(n, 2, n, 2)[np.arange(n), :, np.arange(n), :]
        diff = np.abs(blocks - s).max(axis=(1, 2)) if n else np.zeros(0)
        tol = 1e-6 * np.abs(s).max(axis=(1, 2)) if n else np.zeros(0)
        if np.any(diff > tol):
            bad = int(np.flatnonzero(diff > tol)[0])
            raise ValueError(f"Candidates.S_joint diagonal block {bad} (candidate id {ids[bad]}) differs from "
                             f"Candidates.S[{bad}]; S must be the diagonal blocks of S_joint")
        sj = 0.5 * (sj + sj.T)
    if candidates.descriptors is not None and (np.ndim(candidates.descriptors) != 2
                                               or np.shape(candidates.descriptors)[0] != n):
        raise ValueError(f"Candidates.descriptors must have shape ({n}, D), got {np.shape(candidates.descriptors)}")
    if (candidates.descriptors is not None and observations.descriptor is not None
            and np.shape(candidates.descriptors)[1:] != np.shape(observations.descriptor)[1:]):
        raise ValueError(f"descriptor length differs: observations {np.shape(observations.descriptor)[1:]}, "
                         f"candidates {np.shape(candidates.descriptors)[1:]}")
    return s, sj


# ---------------------------------------------------------------------------------------------- the problem
@dataclass(frozen=True)
class Problem:
    """A validated association problem: the arrays every method works on.

    Shapes (K observations, L candidates): z (K,2); nu (K,L,2) innovations; d2 (K,L) individual squared
    Mahalanobis distances; allowed (K,L) pairs passing the descriptor test; ic (K,L) individually compatible pairs;
    S (L,2,2) symmetrised; S_joint (2L,2L) or None (None: block diagonal of S).
    """

    z: Array
    nu: Array
    d2: Array
    allowed: BoolArray
    ic: BoolArray
    S: Array
    S_joint: Array | None
    gate: float
    new_gate: float
    ids: IntArray

    @property
    def num_obs(self) -> int:
        return int(self.z.shape[0])

    @property
    def num_candidates(self) -> int:
        return int(self.ids.shape[0])

    def joint_block(self, rows: IntArray, cols: IntArray) -> Array:
        """Joint innovation covariance between candidate lists ``rows`` and ``cols``. Shapes: -> (2R, 2C)."""
        if self.S_joint is not None:
            n = self.num_candidates
            two = np.arange(2)
            blk = self.S_joint.reshape(n, 2, n, 2)[np.ix_(rows, two, cols, two)]
            return blk.reshape(2 * len(rows), 2 * len(cols))
        out = np.zeros((len(rows), 2, len(cols), 2))
        same = rows[:, None] == cols[None, :]
        r, c = np.nonzero(same)
        out[r, :, c, :] = self.S[rows[r]]
        return out.reshape(2 * len(rows), 2 * len(cols))


def innovations(z: Array, z_pred: Array) -> Array:
    """``nu[i, j] = z_i - z_pred_j`` with the bearing through ``angle_diff``. Shapes: (K,2),(L,2) -> (K,L,2)."""
    dr = z[:, None, 0] - z_pred[None, :, 0]
    db = angle_diff(z[:, None, 1], z_pred[None, :, 1])
    return np.stack([dr, db], axis=-1)


def mahalanobis_matrix(nu: Array, S: Array) -> Array:
    """``d2[i, j] = nu_ij^T S_j^-1 nu_ij`` for symmetric positive definite 2x2 ``S``. Shapes: (K,L,2),(L,2,2)->(K,L)."""
    a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
    det = a * d - b * b
    x, y = nu[..., 0], nu[..., 1]
    return (d * x * x - 2.0 * b * x * y + a * y * y) / det


def descriptor_distance(a: Array, b: Array) -> Array:
    """Euclidean distance between every row of ``a`` and of ``b``. Shapes: (K,D),(L,D) -> (K,L)."""
    sq = np.sum(a * a, axis=1)[:, None] + np.sum(b * b, axis=1)[None, :] - 2.0 * a @ b.T
    return np.sqrt(np.maximum(sq, 0.0))


def build_problem(observations: Observations, candidates: Candidates, config: AssociationConfig) -> Problem:
    """Validate the inputs and compute innovations, distances and gates (vectorised over all K x L pairs)."""
    s, sj = validate(observations, candidates)
    z = observations.z.reshape(-1, 2).astype(np.float64)
    z_pred = np.asarray(candidates.z_pred, dtype=np.float64).reshape(-1, 2)
    nu = innovations(z, z_pred)
    d2 = mahalanobis_matrix(nu, s)
    allowed = np.ones(d2.shape, dtype=bool)
    if config.descriptor_max_distance > 0 and observations.descriptor is not None \
            and candidates.descriptors is not None and d2.size:
        dist = descriptor_distance(np.asarray(observations.descriptor, dtype=np.float64).reshape(len(z), -1),
                                   np.asarray(candidates.descriptors, dtype=np.float64).reshape(len(z_pred), -1))
        allowed = dist <= config.descriptor_max_distance
    gate, new_gate = gate_thresholds(config)
    ic = allowed & (d2 <= gate)
    return Problem(z, nu, d2, allowed, ic, s, sj, gate, new_gate, np.asarray(candidates.ids, dtype=np.int64))


# ---------------------------------------------------------------------------------------------- shared steps
def max_matching(cost: Array, allowed: BoolArray) -> tuple[IntArray, IntArray]:
    """Mutual exclusion: the matching with the most pairs among ``allowed`` ones, and among those the least total
    cost (one optimal assignment problem solved by ``scipy.optimize.linear_sum_assignment``).

    Each row may also stay unmatched through a dummy column of cost 0; every real pair's cost is lowered by a
    constant larger than any possible total cost, so one more pair always beats any saving in cost.
    Shapes: cost (K,L), allowed (K,L) -> (rows (n,), cols (n,)) sorted by row.
    """
    rows_any = np.flatnonzero(allowed.any(axis=1))
    cols_any = np.flatnonzero(allowed.any(axis=0))
    if len(rows_any) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    sub_ok = allowed[np.ix_(rows_any, cols_any)]
    sub = cost[np.ix_(rows_any, cols_any)]
    big = (len(rows_any) + 1) * (float(np.max(np.abs(sub[sub_ok]))) + 1.0)
    # forbidden pairs cost more than staying unmatched (0), so they are never chosen
    real = np.where(sub_ok, sub - big, big)
    full = np.hstack([real, np.zeros((len(rows_any), len(rows_any)))])
    r, c = linear_sum_assignment(full)
    keep = c < len(cols_any)
    r, c = r[keep], c[keep]
    ok = sub_ok[r, c]
    return rows_any[r[ok]].astype(np.int64), cols_any[c[ok]].astype(np.int64)


def check_joint_positive_definite(problem: Problem, cand: IntArray) -> Array:
    """The joint covariance of candidates ``cand``; ValueError unless it is positive definite. Shapes: -> (2n,2n)."""
    c = problem.joint_block(cand, cand)
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        raise ValueError(f"Candidates.S_joint is not positive definite on the individually compatible candidates "
                         f"{problem.ids[cand].tolist()}") from None
    return c


def joint_nis(problem: Problem, obs: IntArray, cand: IntArray) -> float:
    """Joint NIS of the pairs ``(obs[k], cand[k])``: ``nu^T C^-1 nu`` with C from S_joint (nan if a candidate
    repeats; 0 for no pairs). Raises ValueError when that sub-matrix of S_joint is not positive definite."""
    if len(obs) == 0:
        return 0.0
    return pairs_nis(problem.nu[obs, cand], problem.d2[obs, cand], cand, problem.S_joint, problem.ids)


def pairs_nis(nu: Array, d2: Array, cand: IntArray, S_joint: Array | None, ids: IntArray) -> float:
    """:func:`joint_nis` from the pairs' own innovations ``nu`` (n,2) and distances ``d2`` (n,), for callers that
    never build the whole K x L problem. ``S_joint`` (2L,2L) symmetrised or None (block diagonal)."""
    if len(cand) == 0:
        return 0.0
    if len(np.unique(cand)) != len(cand):
        return float("nan")
    if S_joint is None:  # block diagonal: the sum of the pairs' own NIS (no dense 2K x 2K factorisation)
        return float(np.sum(d2))
    n_c, two = S_joint.shape[0] // 2, np.arange(2)
    c = S_joint.reshape(n_c, 2, n_c, 2)[np.ix_(cand, two, cand, two)].reshape(2 * len(cand), 2 * len(cand))
    try:
        chol = np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        raise ValueError(f"Candidates.S_joint is not positive definite on candidates "
                         f"{ids[cand].tolist()}") from None
    y = np.linalg.solve(chol, nu.reshape(-1))
    return float(y @ y)


def finalize(problem: Problem, obs: IntArray, cand: IntArray, *, nis: float | None = None, nodes: int = 0,
             truncated: bool = False) -> AssociationResult:
    """Turn matched pairs into an :class:`AssociationResult`, applying the NEW / CLUTTER rule to the rest."""
    k = problem.num_obs
    assignment = np.full(k, NEW, dtype=np.int64)
    if problem.num_candidates:
        near = (problem.allowed & (problem.d2 <= problem.new_gate)).any(axis=1)
        assignment[near] = CLUTTER
    assignment[obs] = problem.ids[cand]
    d2 = np.full(k, np.nan)
    d2[obs] = problem.d2[obs, cand]
    value = joint_nis(problem, obs, cand) if nis is None else float(nis)
    return AssociationResult(assignment, d2, value, nodes, truncated)
