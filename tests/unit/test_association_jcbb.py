"""JCBB against an exhaustive joint-compatibility search.

"Exhaustive" (the definition in ``slam2d.association.jcbb``): enumerate every hypothesis built from individually
compatible pairs with each observation and each candidate used at most once; keep those whose joint NIS (innovations
stacked, covariance from S_joint) is at most chi2.ppf(p, 2n); return the one with the most pairs, ties broken by the
lowest joint NIS, exact ties by the lexicographically smallest assignment (candidate index per observation,
"unmatched" after every candidate). The reference below computes every NIS from scratch with a dense solve and
uses scipy's quantiles directly: it shares no code with the branch and bound except the innovations and the IC mask.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _association_problems import random_problem
from scipy import stats

import slam2d.association.jcbb as jcbb_module
from slam2d.association import CLUTTER, NEW, AssociationConfig, associate
from slam2d.association.gating import build_problem


def exhaustive(prob, probability: float) -> tuple[int, float, tuple[int, ...]]:
    k, n_cand = prob.num_obs, prob.num_candidates
    thr = [0.0] + [stats.chi2.ppf(probability, 2 * n) for n in range(1, k + 1)]
    choices = [[*np.flatnonzero(prob.ic[i]).tolist(), n_cand] for i in range(k)]
    best: tuple[int, float, tuple[int, ...]] = (0, 0.0, tuple([n_cand] * k))

    def rec(i: int, assign: list[int], used: set[int]) -> None:
        nonlocal best
        if i == k:
            obs = [o for o in range(k) if assign[o] < n_cand]
            if not obs:
                return
            cand = np.array([assign[o] for o in obs])
            nu = np.concatenate([prob.nu[o, assign[o]] for o in obs])
            if prob.S_joint is not None:
                idx = (2 * cand[:, None] + np.arange(2)).ravel()
                c = prob.S_joint[np.ix_(idx, idx)]
            else:
                c = np.zeros((2 * len(obs), 2 * len(obs)))
                for t, j in enumerate(cand):
                    c[2 * t:2 * t + 2, 2 * t:2 * t + 2] = prob.S[j]
            nis = float(nu @ np.linalg.solve(c, nu))
            if nis > thr[len(obs)]:
                return
            if (-len(obs), nis, tuple(assign)) < (-best[0], best[1], best[2]):
                best = (len(obs), nis, tuple(assign))
            return
        for j in choices[i]:
            if j < n_cand and j in used:
                continue
            assign.append(j)
            if j < n_cand:
                used.add(j)
            rec(i + 1, assign, used)
            assign.pop()
            used.discard(j)

    rec(0, [], set())
    return best


@pytest.mark.parametrize("seeded", [True, False], ids=["with-incumbent", "search-only"])
def test_jcbb_equals_exhaustive_search_on_random_problems(seeded, monkeypatch):
    if not seeded:  # the branch and bound alone, without the heuristic starting hypothesis, must agree as well
        monkeypatch.setattr(jcbb_module, "_seed_incumbent", lambda st, d2: None)
    rng = np.random.default_rng(20240601 if seeded else 777)
    n_problems, ambiguous, differs_from_ic, multi_pair = 0, 0, 0, 0
    for trial in range(240 if seeded else 200):
        obs, cands = random_problem(rng, max_obs=7, max_cand=10)
        if trial % 6 == 5:  # also without landmark correlations (S_joint None means block diagonal of S)
            cands = dataclasses.replace(cands, S_joint=None)
        p = float(rng.choice([0.9, 0.95, 0.99]))
        cfg = AssociationConfig(method="jcbb", gate_probability=p, new_landmark_probability=max(p, 0.9999))
        prob = build_problem(obs, cands, cfg)
        n_best, nis_best, key = exhaustive(prob, p)
        res = associate(obs, cands, cfg, rng=rng)
        expected = np.array([prob.ids[j] if j < prob.num_candidates else -99 for j in key])
        got = np.where(res.assignment >= 0, res.assignment, -99)
        assert np.array_equal(got, expected), f"trial {trial}: jcbb {res.assignment} vs exhaustive {expected}"
        assert res.joint_nis == pytest.approx(nis_best, rel=1e-9, abs=1e-12)
        assert not res.truncated
        n_problems += 1
        ambiguous += bool((prob.ic.sum(axis=1) > 1).any())
        multi_pair += n_best >= 3
        ic_only = associate(obs, cands, dataclasses.replace(cfg, method="mahalanobis"), rng=rng)
        differs_from_ic += not np.array_equal(ic_only.assignment, res.assignment)
    assert n_problems >= 200
    # the problems are not trivial: many have competing candidates, and joint compatibility changes the answer
    assert ambiguous >= 80 and multi_pair >= 80 and differs_from_ic >= 20, (ambiguous, multi_pair, differs_from_ic)


def test_jcbb_result_is_individually_and_jointly_compatible_and_exclusive():
    rng = np.random.default_rng(7)
    for _ in range(60):
        obs, cands = random_problem(rng, max_obs=12, max_cand=14, spacing_m=0.4)
        cfg = AssociationConfig(method="jcbb")
        prob = build_problem(obs, cands, cfg)
        res = associate(obs, cands, cfg, rng=rng)
        matched = np.flatnonzero(res.assignment >= 0)
        cand = np.array([int(np.flatnonzero(prob.ids == a)[0]) for a in res.assignment[matched]], dtype=int)
        assert len(set(cand.tolist())) == len(cand)
        assert np.all(prob.ic[matched, cand])
        if len(matched):
            assert res.joint_nis <= stats.chi2.ppf(cfg.gate_probability, 2 * len(matched)) + 1e-9
            np.testing.assert_allclose(res.d2[matched], prob.d2[matched, cand])
        assert np.all(np.isnan(res.d2[res.assignment < 0]))


def test_jcbb_node_limit_reports_truncation_and_still_returns_a_valid_hypothesis():
    rng = np.random.default_rng(3)
    for _ in range(20):
        obs, cands = random_problem(rng, max_obs=7, max_cand=10, spacing_m=0.3)
        full = associate(obs, cands, AssociationConfig(method="jcbb"), rng=rng)
        cut = associate(obs, cands, AssociationConfig(method="jcbb", jcbb_max_nodes=2), rng=rng)
        if full.nodes > 2:
            assert cut.truncated and cut.nodes == 3
        assert (cut.assignment >= 0).sum() <= (full.assignment >= 0).sum()
        m = cut.assignment >= 0
        if m.any():
            assert cut.joint_nis <= stats.chi2.ppf(0.99, 2 * int(m.sum())) + 1e-9
        assert set(cut.assignment[~m].tolist()) <= {NEW, CLUTTER}


def test_jcbb_prefers_the_shifted_pattern_that_nearest_neighbour_gets_wrong():
    # three landmarks 0.5 m apart in a row, predicted from a belief whose heading is off; the true sightings fall
    # close to the *neighbouring* predictions, but the joint covariance knows the whole row moves together
    from slam2d.association.predict import candidates_from_belief
    from slam2d.log import Observations
    from slam2d.models.sensors import range_bearing

    lm = np.array([[5.0, -0.5], [5.0, 0.0], [5.0, 0.5], [5.0, 1.0]])
    true_pose = np.array([0.0, 0.0, 0.0])
    belief = np.array([0.0, 0.0, -0.1])  # 0.1 rad heading error: ~0.5 m at 5 m, one landmark spacing
    p = np.diag([0.01**2, 0.01**2, 0.08**2])
    cov = np.zeros((11, 11))
    cov[:3, :3] = p
    cov[3:, 3:] = 0.01**2 * np.eye(8)
    r = np.diag([0.05**2, 0.005**2])
    cands = candidates_from_belief(belief, lm, np.array([10, 11, 12, 13]), cov, r)
    z = range_bearing(true_pose, lm[:3])
    obs = Observations(z[:, 0], z[:, 1], np.array([10, 11, 12]))
    res = associate(obs, cands, AssociationConfig(method="jcbb"), rng=np.random.default_rng(0))
    np.testing.assert_array_equal(res.assignment, [10, 11, 12])
    nn = associate(obs, cands, AssociationConfig(method="nn"), rng=np.random.default_rng(0))
    assert not np.array_equal(nn.assignment, [10, 11, 12])


def test_jcbb_time_budget_returns_its_best_so_far_flagged_truncated():
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(20):
        obs, cands = random_problem(rng, max_obs=7, max_cand=10, spacing_m=0.3)
        full = associate(obs, cands, AssociationConfig(method="jcbb"), rng=rng)
        # a budget that is already spent when the search starts: the root node sees the deadline passed
        cut = associate(obs, cands, AssociationConfig(method="jcbb", jcbb_time_budget_s=0.0), rng=rng)
        roomy = associate(obs, cands, AssociationConfig(method="jcbb", jcbb_time_budget_s=3600.0), rng=rng)
        np.testing.assert_array_equal(roomy.assignment, full.assignment)  # a budget never reached changes nothing
        assert not roomy.truncated
        if full.nodes > 1:
            checked += 1
            assert cut.truncated and cut.nodes == 1
        m = cut.assignment >= 0
        assert m.sum() <= (full.assignment >= 0).sum()
        if m.any():
            assert cut.joint_nis <= stats.chi2.ppf(0.99, 2 * int(m.sum())) + 1e-9
    assert checked >= 5
    with pytest.raises(ValueError, match="jcbb_time_budget_s"):
        AssociationConfig(method="jcbb", jcbb_time_budget_s=-1.0)
