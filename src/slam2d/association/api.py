"""``associate``: the one call every back end makes, whatever the method."""

from __future__ import annotations

import time

import numpy as np

from slam2d.association.base import CLUTTER, AssociationConfig, AssociationResult, Candidates, associate_known
from slam2d.association.gating import (
    build_problem,
    finalize,
    gate_thresholds,
    mahalanobis_matrix,
    pairs_nis,
    validate,
)
from slam2d.association.individual import individual_compatibility
from slam2d.association.jcbb import jcbb
from slam2d.association.nn import nearest_neighbour
from slam2d.association.ransac import ransac
from slam2d.geometry.angles import angle_diff
from slam2d.log import Observations


def _known(observations: Observations, candidates: Candidates, config: AssociationConfig) -> AssociationResult:
    """The source's ids, with d2 and the joint NIS of the matched pairs only (never the K x L problem: with
    hundreds of landmarks in view that was most of the association's time)."""
    s, sj = validate(observations, candidates)
    assignment = associate_known(observations, candidates).assignment.copy()
    obs = np.flatnonzero(assignment >= 0).astype(np.int64)
    ids = np.asarray(candidates.ids, dtype=np.int64)
    order = np.argsort(ids, kind="stable")
    cand = order[np.searchsorted(ids, assignment[obs], sorter=order)].astype(np.int64)
    z = observations.z.reshape(-1, 2).astype(np.float64)[obs]
    z_pred = np.asarray(candidates.z_pred, dtype=np.float64).reshape(-1, 2)[cand]
    nu = np.stack([z[:, 0] - z_pred[:, 0], angle_diff(z[:, 1], z_pred[:, 1])], axis=-1)  # as gating.innovations
    pair_d2 = mahalanobis_matrix(nu[None], s[cand])[0] if obs.size else np.zeros(0)
    d2 = np.full(len(assignment), np.nan)
    d2[obs] = pair_d2
    if config.known_outlier_gate and obs.size:
        # an id the source reports can still be wrong (a misread barcode): outside the wide gate it is clutter
        bad = pair_d2 > gate_thresholds(config)[1]
        assignment[obs[bad]] = CLUTTER
        cand, nu, pair_d2 = cand[~bad], nu[~bad], pair_d2[~bad]
    return AssociationResult(assignment, d2, pairs_nis(nu, pair_d2, cand, sj, ids))


def associate(observations: Observations, candidates: Candidates, config: AssociationConfig, *,
              rng: np.random.Generator) -> AssociationResult:
    """Assign each observation to a candidate id, ``NEW`` or ``CLUTTER`` with ``config.method``.

    Inputs are validated first (a ValueError names the bad field: non-finite values, duplicate or negative ids,
    non-symmetric or singular S, S_joint inconsistent with S, descriptor length mismatch). Empty observations give an
    empty result; no candidates make every observation ``NEW``. ``rng`` is used by ``ransac`` only (it is required
    for every method so that callers never depend on which method is configured).

    Shapes: observations K, candidates L -> assignment (K,), d2 (K,).
    """
    if config.method == "auto":
        raise ValueError("AssociationConfig.method 'auto' must be resolved first (resolve_method: known ids or "
                         "not) by the back end or the runner")
    if config.method == "known":
        return _known(observations, candidates, config)
    problem = build_problem(observations, candidates, config)
    if problem.num_obs == 0 or problem.num_candidates == 0:
        return finalize(problem, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if config.method == "nn":
        obs, cand = nearest_neighbour(problem, config.nn_max_distance)
        return finalize(problem, obs, cand)
    if config.method == "mahalanobis":
        obs, cand = individual_compatibility(problem)
        return finalize(problem, obs, cand)
    if config.method == "jcbb":
        budget = config.jcbb_time_budget_s
        deadline = None if budget is None else time.monotonic() + budget
        obs, cand, nis, nodes, truncated = jcbb(problem, config.gate_probability, config.jcbb_max_nodes, deadline)
        return finalize(problem, obs, cand, nis=nis, nodes=nodes, truncated=truncated)
    if config.method == "ransac":
        obs, cand, hyps = ransac(problem, config.ransac_iterations, config.ransac_min_pairs,
                                 config.gate_probability, rng)
        return finalize(problem, obs, cand, nodes=hyps)
    raise ValueError(f"AssociationConfig.method {config.method!r} is not one of known, nn, mahalanobis, jcbb, ransac")
