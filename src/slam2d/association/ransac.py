"""RANSAC over minimal sets of pairs, with the hypothesis expressed through the joint innovation covariance.

A hypothesis is a minimal set of ``ransac_min_pairs`` individually compatible pairs (distinct observations and
candidates) that is itself jointly compatible. Instead of solving for the pose correction explicitly (the back end's
Jacobians are not part of :class:`Candidates`), the hypothesis conditions the joint Gaussian of all predicted
measurements on the minimal set's innovations, which is exactly what an EKF update on those pairs would do to the
predictions (the idea of 1-point RANSAC, Civera et al., J. Field Robotics 2010):

    shift_j = C_jH C_H^-1 nu_H,    S_j|H = S_j - C_jH C_H^-1 C_Hj.

Score: the number of further observations with a candidate inside the conditional gate (ties: lower total
conditional d2). All hypotheses are scored in one batch. Refinement of the winner: repeatedly condition on all pairs
accepted so far and add the pairs that pass the conditional gate (optimal assignment, so mutual exclusion holds);
then drop, one at a time, the pair whose leave-one-out conditional d2 is largest while it fails the gate or while
the whole set fails the joint chi-square test. Every returned pair is individually compatible and the returned set
is jointly compatible.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam2d.association.gating import Problem, check_joint_positive_definite, joint_thresholds, max_matching

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def _inv2(s: Array) -> Array:
    """Batched inverse of symmetric 2x2 matrices. Shapes: (...,2,2) -> (...,2,2)."""
    a, b, d = s[..., 0, 0], s[..., 0, 1], s[..., 1, 1]
    det = a * d - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.stack([np.stack([d, -b], -1), np.stack([-b, a], -1)], -2) / det[..., None, None]
    return out


def _conditional_d2(problem: Problem, h_obs: IntArray, h_cand: IntArray, act: IntArray) -> Array:
    """Conditional d2 of every observation against the candidates ``act`` given batched hypotheses.

    Shapes: h_obs, h_cand (N, m) -> (N, K, A); pairs not individually compatible, or touching the hypothesis's
    observations or candidates, are +inf.
    """
    nh, m = h_obs.shape
    k, a = problem.num_obs, len(act)
    nu_h = problem.nu[h_obs, h_cand].reshape(nh, 2 * m)  # (N, 2m)
    c_hh = np.stack([problem.joint_block(c, c) for c in h_cand])  # (N, 2m, 2m)
    c_ah = np.stack([problem.joint_block(act, c) for c in h_cand])  # (N, 2A, 2m)
    g = np.linalg.solve(c_hh, np.concatenate([nu_h[..., None], c_ah.transpose(0, 2, 1)], axis=-1))
    shift = np.einsum("nij,nj->ni", c_ah, g[..., 0]).reshape(nh, a, 2)
    # only the 2x2 diagonal blocks of C_aH C_H^-1 C_Ha are needed: O(N A m) instead of O(N A^2 m)
    red = np.einsum("nazp,npaw->nazw", c_ah.reshape(nh, a, 2, 2 * m), g[..., 1:].reshape(nh, 2 * m, a, 2))
    s_cond = problem.S[act][None] - red  # (N, A, 2, 2)
    r = problem.nu[:, act][None] - shift[:, None]  # (N, K, A, 2)
    si = _inv2(s_cond)  # (N, A, 2, 2)
    d2 = np.einsum("nkai,naij,nkaj->nka", r, si, r)
    ok = problem.ic[:, act][None] & np.isfinite(d2) & (d2 >= 0)
    ok &= ~(h_obs[:, :, None] == np.arange(k)[None, None, :]).any(axis=1)[:, :, None]
    ok &= ~(h_cand[:, :, None] == act[None, None, :]).any(axis=1)[:, None, :]
    return np.where(ok, d2, np.inf)


def _loo(problem: Problem, obs: IntArray, cand: IntArray) -> tuple[Array, float]:
    """Leave-one-out conditional d2 of each pair given the others, and the joint NIS of the set. Shapes: (n,)."""
    n = len(obs)
    nu = problem.nu[obs, cand].reshape(-1)
    ci = np.linalg.inv(problem.joint_block(cand, cand))
    ci = 0.5 * (ci + ci.T)
    v = (ci @ nu).reshape(n, 2)
    blocks = ci.reshape(n, 2, n, 2)[np.arange(n), :, np.arange(n), :]  # (n, 2, 2)
    # for a Gaussian, the conditional residual of block k given the rest is (C^-1)_kk^-1 (C^-1 nu)_k
    loo = np.einsum("ni,nij,nj->n", v, _inv2(blocks), v)
    return loo, float(nu @ ci @ nu)


def _sample(problem: Problem, obs_ic: IntArray, m: int, iterations: int, gate: float,
            rng: np.random.Generator) -> tuple[IntArray, IntArray, Array]:
    """Draw ``iterations`` minimal sets at once: m distinct observations, a random compatible candidate for each.
    Keeps those with distinct candidates that are jointly compatible. Shapes: -> (N, m), (N, m), (N,)."""
    h_obs = obs_ic[np.argsort(rng.random((iterations, len(obs_ic))), axis=1)[:, :m]]
    keys = np.where(problem.ic[h_obs], rng.random((iterations, m, problem.num_candidates)), -1.0)
    h_cand = np.argmax(keys, axis=-1)
    srt = np.sort(h_cand, axis=1)
    valid = ~(srt[:, 1:] == srt[:, :-1]).any(axis=1)
    h_obs, h_cand = h_obs[valid], h_cand[valid]
    if len(h_obs) == 0:
        return h_obs, h_cand, np.zeros(0)
    nu_h = problem.nu[h_obs, h_cand].reshape(len(h_obs), 2 * m)
    c_hh = np.stack([problem.joint_block(c, c) for c in h_cand])
    nis_h = np.einsum("ni,ni->n", nu_h, np.linalg.solve(c_hh, nu_h[..., None])[..., 0])
    jc = nis_h <= gate
    return h_obs[jc], h_cand[jc], nis_h[jc]


def ransac(problem: Problem, iterations: int, min_pairs: int, probability: float,
           rng: np.random.Generator) -> tuple[IntArray, IntArray, int]:
    """Returns (obs (n,), cand (n,), hypotheses scored) with pairs sorted by observation."""
    empty = np.zeros(0, dtype=np.int64)
    obs_ic = np.flatnonzero(problem.ic.any(axis=1))
    act = np.flatnonzero(problem.ic.any(axis=0))
    if len(obs_ic) == 0:
        return empty, empty, 0
    check_joint_positive_definite(problem, act)  # conditioning relies on it
    thr = joint_thresholds(probability, problem.num_obs)
    # minimal sets of m pairs; when no valid set of that size turns up (e.g. every observation competes for the same
    # landmark), fall back to smaller sets rather than to no answer
    for m in range(min(min_pairs, len(obs_ic)), 0, -1):
        h_obs, h_cand, nis_h = _sample(problem, obs_ic, m, iterations, thr[m], rng)
        if len(h_obs):
            break
    else:
        return empty, empty, iterations
    # ---- score all hypotheses by consensus in one batch (chunks bound the memory of the (N, K, A) arrays)
    scores, costs = [], []
    chunk = max(1, 2_000_000 // max(1, problem.num_obs * len(act) * 8))
    for s in range(0, len(h_obs), chunk):
        d2c = _conditional_d2(problem, h_obs[s:s + chunk], h_cand[s:s + chunk], act)
        best = d2c.min(axis=2)
        inl = best <= problem.gate
        scores.append(inl.sum(axis=1))
        costs.append(np.where(inl, best, 0.0).sum(axis=1) + nis_h[s:s + chunk])
    score, cost = np.concatenate(scores), np.concatenate(costs)
    win = int(np.lexsort((cost, -score))[0])
    obs, cand = h_obs[win].copy(), h_cand[win].copy()
    # ---- refine: grow the consensus set by conditioning on everything accepted so far
    for _ in range(problem.num_obs):
        d2c = _conditional_d2(problem, obs[None], cand[None], act)[0]
        r, c = max_matching(d2c, d2c <= problem.gate)
        if len(r) == 0:
            break
        obs, cand = np.concatenate([obs, r]), np.concatenate([cand, act[c]])
    # ---- prune: leave-one-out outliers, then the joint test
    while len(obs):
        loo, nis = _loo(problem, obs, cand)
        worst = int(np.argmax(loo))
        if loo[worst] <= problem.gate and nis <= thr[len(obs)]:
            break
        obs, cand = np.delete(obs, worst), np.delete(cand, worst)
    srt_o = np.argsort(obs)
    return obs[srt_o].astype(np.int64), cand[srt_o].astype(np.int64), iterations
