"""``associate``: the one call every back end makes, whatever the method."""

from __future__ import annotations

import time

import numpy as np

from slam2d.association.base import CLUTTER, AssociationConfig, AssociationResult, Candidates, associate_known
from slam2d.association.gating import Problem, build_problem, finalize, joint_nis
from slam2d.association.individual import individual_compatibility
from slam2d.association.jcbb import jcbb
from slam2d.association.nn import nearest_neighbour
from slam2d.association.ransac import ransac
from slam2d.log import Observations


def _known(problem: Problem, observations: Observations, candidates: Candidates,
           outlier_gate: bool) -> AssociationResult:
    base = associate_known(observations, candidates)
    assignment = base.assignment.copy()
    obs = np.flatnonzero(assignment >= 0).astype(np.int64)
    index = {int(c): k for k, c in enumerate(problem.ids)}
    cand = np.array([index[int(c)] for c in assignment[obs]], dtype=np.int64)
    d2 = np.full(len(assignment), np.nan)
    d2[obs] = problem.d2[obs, cand]
    if outlier_gate and obs.size:
        # an id the source reports can still be wrong (a misread barcode): outside the wide gate it is clutter
        bad = d2[obs] > problem.new_gate
        assignment[obs[bad]] = CLUTTER
        obs, cand = obs[~bad], cand[~bad]
    return AssociationResult(assignment, d2, joint_nis(problem, obs, cand))


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
    problem = build_problem(observations, candidates, config)
    if config.method == "known":
        return _known(problem, observations, candidates, config.known_outlier_gate)
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
