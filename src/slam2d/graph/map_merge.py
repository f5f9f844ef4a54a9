"""Map merging: the rigid transform between two robots' frames from common evidence, and its verification.

Evidence is a set of point correspondences ``p_a`` (frame A) <-> ``p_b`` (frame B) with covariances: the same
landmark mapped by both (known ids), candidate landmark pairs (unknown ids: every pair, most of them wrong), and
robot-robot sightings (the observed robot's position in its own frame <-> where the observer saw it). The transform
``T_a_b`` (``p_a = T_a_b (.) p_b``) is the closed-form weighted 2D rigid alignment (Umeyama without scale), found
inside RANSAC over 2-correspondence minimal sets, then refitted on the consensus.

A hypothesis is ACCEPTED only if it is verified: at least ``min_pairs`` inlier correspondences spread over at least
``min_spread_m`` (so that the rotation is observable), and the residuals pass the chi-square test at
``probability`` with ``2 n - 3`` degrees of freedom (2 per pair, minus the 3 of the fitted transform) using the
correspondences' own covariances. Ambiguous landmark pairs are made one-to-one (each landmark in at most one pair),
and one whose landmark has a second pair inside the gate is not counted at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry import se2
from slam2d.geometry.gaussian import chi2_gate

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def rigid_align(p_b: ArrayLike, p_a: ArrayLike, weights: ArrayLike | None = None) -> Array:
    """``T_a_b`` = [tx, ty, theta] minimising ``sum w |p_a - T_a_b (.) p_b|^2`` (closed form; Umeyama 1991 in 2D,
    no scale). Shapes: (N,2),(N,2),(N,) -> (3,). Needs N >= 2 points that are not all equal."""
    pb = np.asarray(p_b, dtype=np.float64).reshape(-1, 2)
    pa = np.asarray(p_a, dtype=np.float64).reshape(-1, 2)
    w = np.ones(pb.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    if pb.shape != pa.shape or pb.shape[0] < 2:
        raise ValueError(f"need two equal-length point sets of >= 2 points, got {pb.shape} and {pa.shape}")
    w = w / w.sum()
    mb, ma = w @ pb, w @ pa
    qb, qa = pb - mb, pa - ma
    sxx = float(np.sum(w * (qb[:, 0] * qa[:, 0] + qb[:, 1] * qa[:, 1])))
    sxy = float(np.sum(w * (qb[:, 0] * qa[:, 1] - qb[:, 1] * qa[:, 0])))
    th = float(np.arctan2(sxy, sxx))
    c, s = np.cos(th), np.sin(th)
    t = ma - np.array([c * mb[0] - s * mb[1], s * mb[0] + c * mb[1]])
    return np.array([t[0], t[1], th])


def residual_d2(T_a_b: ArrayLike, p_a: Array, cov_a: Array, p_b: Array, cov_b: Array) -> Array:
    """Squared Mahalanobis distance of each correspondence under ``T_a_b``:
    ``e = p_a - T (.) p_b``, ``S = cov_a + R cov_b R^T``. Shapes: (N,2),(N,2,2),(N,2),(N,2,2) -> (N,)."""
    T = np.asarray(T_a_b, dtype=np.float64)
    R = se2.rotation_matrix(T[2])
    e = p_a - se2.transform_points(T, p_b)
    S = cov_a + R @ cov_b @ R.T
    return np.asarray(np.einsum("ni,nij,nj->n", e, np.linalg.inv(S), e))


@dataclass(frozen=True)
class MergeHypothesis:
    """The verdict on one candidate merge. ``inliers``: indices of the consensus correspondences; ``chi2`` their
    summed squared Mahalanobis residual and ``dof = 2 n - 3``; ``reason`` says why it was rejected ("" if accepted).
    """

    T_a_b: Array
    inliers: IntArray
    chi2: float
    dof: int
    spread_m: float
    accepted: bool
    reason: str


def _one_to_one(d2: Array, ok: NDArray[np.bool_], ia: IntArray, ib: IntArray, ambiguous: NDArray[np.bool_]
                ) -> NDArray[np.bool_]:
    """Keep, among ambiguous pairs sharing a landmark on either side, only the one with the smallest d2."""
    keep = ok.copy()
    amb = np.flatnonzero(ok & ambiguous)
    if amb.size:
        used_a: set[int] = set()
        used_b: set[int] = set()
        for k in amb[np.argsort(d2[amb])]:
            if int(ia[k]) in used_a or int(ib[k]) in used_b:
                keep[k] = False
            else:
                used_a.add(int(ia[k]))
                used_b.add(int(ib[k]))
    return keep


def find_merge(p_a: ArrayLike, cov_a: ArrayLike, p_b: ArrayLike, cov_b: ArrayLike, *, rng: np.random.Generator,
               ambiguous: ArrayLike | None = None, ids_a: ArrayLike | None = None, ids_b: ArrayLike | None = None,
               probability: float = 0.99, min_pairs: int = 3, min_spread_m: float = 1.0,
               iterations: int = 200) -> MergeHypothesis:
    """RANSAC + closed-form alignment + chi-square verification of correspondences (see the module docstring).

    ``ambiguous`` (N,) bool marks candidate pairs that may be wrong AND compete for the same landmark: with
    ``ids_a`` / ``ids_b`` (N,) naming the landmark on each side, the consensus keeps each landmark at most once.
    Shapes: p_a (N,2), cov_a (N,2,2), p_b (N,2), cov_b (N,2,2).
    """
    pa = np.asarray(p_a, dtype=np.float64).reshape(-1, 2)
    pb = np.asarray(p_b, dtype=np.float64).reshape(-1, 2)
    ca = np.asarray(cov_a, dtype=np.float64).reshape(-1, 2, 2)
    cb = np.asarray(cov_b, dtype=np.float64).reshape(-1, 2, 2)
    n = pa.shape[0]
    amb = np.zeros(n, dtype=bool) if ambiguous is None else np.asarray(ambiguous, dtype=bool)
    ia = np.arange(n) if ids_a is None else np.asarray(ids_a, dtype=np.int64)
    ib = np.arange(n) if ids_b is None else np.asarray(ids_b, dtype=np.int64)
    none = MergeHypothesis(np.zeros(3), np.zeros(0, dtype=np.int64), float("nan"), 0, 0.0, False, "")
    if n < max(2, min_pairs):
        return _reject(none, f"{n} correspondences (need {min_pairs})")
    gate = chi2_gate(probability, 2)
    w = 1.0 / np.maximum(np.trace(ca, axis1=1, axis2=2) + np.trace(cb, axis1=1, axis2=2), 1e-12)
    best_keep, best_score = None, (-1, np.inf)
    for _ in range(iterations):
        i, j = rng.choice(n, size=2, replace=False)
        if np.hypot(*(pb[i] - pb[j])) < 1e-6 or np.hypot(*(pa[i] - pa[j])) < 1e-6:
            continue
        T = rigid_align(pb[[i, j]], pa[[i, j]])
        d2 = residual_d2(T, pa, ca, pb, cb)
        keep = _one_to_one(d2, d2 <= gate, ia, ib, amb)
        score = (int(keep.sum()), float(d2[keep].sum()))
        if score[0] > best_score[0] or (score[0] == best_score[0] and score[1] < best_score[1]):
            best_keep, best_score = keep, score
    if best_keep is None or best_score[0] < 2:
        return _reject(none, "no consistent pair of correspondences")
    keep = best_keep
    for _ in range(2):  # refit on the consensus, re-select
        T = rigid_align(pb[keep], pa[keep], w[keep])
        d2 = residual_d2(T, pa, ca, pb, cb)
        keep = _one_to_one(d2, d2 <= gate, ia, ib, amb)
        if keep.sum() < 2:
            return _reject(none, "consensus collapsed on refit")
    # an ambiguous pair is evidence only if neither of its landmarks has another pair inside the gate (a landmark
    # between two candidates could be either; fusing the wrong two would bend both maps)
    ok = d2 <= gate
    if np.any(amb):
        na = np.bincount(np.unique(ia[ok & amb], return_inverse=True)[1]) if np.any(ok & amb) else np.zeros(0)
        nb = np.bincount(np.unique(ib[ok & amb], return_inverse=True)[1]) if np.any(ok & amb) else np.zeros(0)
        ua, ub = np.unique(ia[ok & amb]), np.unique(ib[ok & amb])
        single_a = np.isin(ia, ua[na == 1])
        single_b = np.isin(ib, ub[nb == 1])
        keep &= ~amb | (single_a & single_b)
    inl = np.flatnonzero(keep).astype(np.int64)
    if inl.size < 2:
        return _reject(none, "no unambiguous consensus")
    T = rigid_align(pb[inl], pa[inl], w[inl])
    d2 = residual_d2(T, pa, ca, pb, cb)[inl]
    chi2, dof = float(d2.sum()), 2 * inl.size - 3
    spread = float(np.max(np.hypot(*(pa[inl, None, :] - pa[None, inl, :]).transpose(2, 0, 1))))
    hyp = MergeHypothesis(T, inl, chi2, dof, spread, True, "")
    if inl.size < min_pairs:
        return _reject(hyp, f"{inl.size} consistent correspondences (need {min_pairs})")
    if spread < min_spread_m:
        return _reject(hyp, f"evidence spread {spread:.2f} m (need {min_spread_m} m)")
    if chi2 > chi2_gate(probability, dof):
        return _reject(hyp, f"chi2 {chi2:.1f} above the {probability} quantile for {dof} dof")
    return hyp


def _reject(h: MergeHypothesis, reason: str) -> MergeHypothesis:
    return MergeHypothesis(h.T_a_b, h.inliers, h.chi2, h.dof, h.spread_m, False, reason)
