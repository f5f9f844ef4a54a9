"""Known association computes d2 and the joint NIS of the matched pairs only; it must give what the full K x L
problem gives (the previous path: build_problem, then the pairs read from it)."""

import dataclasses

import numpy as np
import pytest
from _association_problems import random_problem

from slam2d.association import CLUTTER, AssociationConfig, associate
from slam2d.association.gating import build_problem, gate_thresholds, joint_nis


def _reference(obs, cands, config):
    """The full-problem computation: every K x L innovation, then the matched pairs' entries."""
    problem = build_problem(obs, cands, config)
    ids = obs.landmark_id
    assignment = np.where(np.isin(ids, cands.ids), ids, np.where(ids >= 0, -1, CLUTTER)).astype(np.int64)
    o = np.flatnonzero(assignment >= 0)
    index = {int(c): k for k, c in enumerate(problem.ids)}
    c = np.array([index[int(a)] for a in assignment[o]], dtype=np.int64)
    d2 = np.full(len(assignment), np.nan)
    d2[o] = problem.d2[o, c]
    if config.known_outlier_gate and o.size:
        bad = d2[o] > gate_thresholds(config)[1]
        assignment[o[bad]] = CLUTTER
        o, c = o[~bad], c[~bad]
    return assignment, d2, joint_nis(problem, o, c)


@pytest.mark.parametrize("joint", [True, False])
@pytest.mark.parametrize("gate", [True, False])
def test_known_pairs_equal_the_full_problem(joint, gate):
    rng = np.random.default_rng(7)
    config = AssociationConfig(method="known", known_outlier_gate=gate)
    checked_nis = 0
    for _ in range(60):
        obs, cands = random_problem(rng, max_obs=12, max_cand=12)
        if rng.random() < 0.3 and len(obs):  # a repeated id (two sightings of one landmark in a scan)
            ids = obs.landmark_id.copy()
            ids[-1] = ids[0]
            obs = dataclasses.replace(obs, landmark_id=ids)
        if not joint:
            cands = dataclasses.replace(cands, S_joint=None)
        res = associate(obs, cands, config, rng=np.random.default_rng(0))
        a, d2, nis = _reference(obs, cands, config)
        np.testing.assert_array_equal(res.assignment, a)
        np.testing.assert_array_equal(res.d2, d2)  # the same arithmetic, pair by pair
        np.testing.assert_allclose(res.joint_nis, nis, rtol=1e-12, equal_nan=True)
        checked_nis += int(np.isfinite(nis) and nis > 0)
    assert checked_nis > 20
