"""The association interface: gates, NEW / CLUTTER rule, mutual exclusion, nn, mahalanobis, ransac, descriptors,
candidate prediction, and bad input."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from _association_problems import R, random_problem

from slam2d.association import (
    CLUTTER,
    METHODS,
    NEW,
    AssociationConfig,
    Candidates,
    associate,
    candidates_from_belief,
    gate_thresholds,
    joint_thresholds,
)
from slam2d.association.gating import build_problem, max_matching
from slam2d.log import Observations
from slam2d.models.sensors import range_bearing
from slam2d.testing import numerical_jacobian

RNG = np.random.default_rng(0)


def obs_of(z, ids=None, desc=None) -> Observations:
    z = np.asarray(z, dtype=float).reshape(-1, 2)
    ids = np.full(len(z), -1) if ids is None else np.asarray(ids)
    return Observations(z[:, 0].copy(), z[:, 1].copy(), ids.astype(np.int64), desc)


def cands_of(z_pred, s, ids=None, s_joint=None, desc=None) -> Candidates:
    z_pred = np.asarray(z_pred, dtype=float).reshape(-1, 2)
    n = len(z_pred)
    s = np.broadcast_to(np.asarray(s, dtype=float), (n, 2, 2)).copy()
    ids = np.arange(n) if ids is None else np.asarray(ids)
    return Candidates(ids.astype(np.int64), z_pred, s, s_joint, desc)


# ------------------------------------------------------------------------------------------------ gates
def chi2_cdf_even_dof(x: float, dof: int) -> float:
    """Closed form for even dof = 2n: 1 - exp(-x/2) sum_{k<n} (x/2)^k / k! (independent of scipy)."""
    n = dof // 2
    h = x / 2
    return 1.0 - math.exp(-h) * sum(h**k / math.factorial(k) for k in range(n))


@pytest.mark.parametrize("p", [0.5, 0.9, 0.95, 0.99, 0.9999])
def test_gates_are_chi_square_quantiles_at_the_configured_probability(p):
    new_p = max(p, 0.99999)
    gate, new_gate = gate_thresholds(AssociationConfig(gate_probability=p, new_landmark_probability=new_p))
    # 2 dof: the quantile has the closed form -2 ln(1 - p)
    assert gate == pytest.approx(-2 * math.log(1 - p), rel=1e-10)
    assert new_gate == pytest.approx(-2 * math.log(1 - new_p), rel=1e-10)
    thr = joint_thresholds(p, 6)
    assert thr[0] == 0.0
    for n in range(1, 7):
        assert chi2_cdf_even_dof(thr[n], 2 * n) == pytest.approx(p, abs=1e-10)


@pytest.mark.parametrize("method", ["mahalanobis", "jcbb", "ransac"])
def test_gate_boundary_and_new_vs_clutter_rule(method):
    cfg = AssociationConfig(method=method, gate_probability=0.95, new_landmark_probability=0.999)
    gate, new_gate = gate_thresholds(cfg)
    s = np.diag([0.2**2, 0.05**2])
    cands = cands_of([[5.0, 0.0]], s, ids=[7])
    # place observations along the range axis at chosen squared distances d2 = (dr / 0.2)^2
    for d2, expected in [(0.999 * gate, 7), (1.001 * gate, CLUTTER), (0.999 * new_gate, CLUTTER),
                         (1.001 * new_gate, NEW)]:
        z = [[5.0 + 0.2 * math.sqrt(d2), 0.0]]
        res = associate(obs_of(z), cands, cfg, rng=np.random.default_rng(1))
        assert res.assignment.tolist() == [expected], (d2, gate, new_gate)
        if expected == 7:
            assert res.d2[0] == pytest.approx(d2)
            assert res.joint_nis == pytest.approx(d2)
        else:
            assert np.isnan(res.d2[0]) and res.joint_nis == 0.0


def test_bearing_residual_wraps_around_pi():
    cands = cands_of([[4.0, np.pi - 0.01]], np.diag([0.1**2, 0.02**2]), ids=[3])
    obs = obs_of([[4.0, -np.pi + 0.01]])
    for method in ("nn", "mahalanobis", "jcbb", "ransac"):
        res = associate(obs, cands, AssociationConfig(method=method), rng=np.random.default_rng(0))
        assert res.assignment.tolist() == [3], method
        if method != "nn":
            assert res.d2[0] == pytest.approx((0.02 / 0.02) ** 2)


# ------------------------------------------------------------------------------------------------ exclusion
@pytest.mark.parametrize("method", ["mahalanobis", "jcbb", "ransac"])
def test_two_observations_never_take_one_landmark(method):
    s = np.diag([0.1**2, 0.02**2])
    cands = cands_of([[5.0, 0.0], [9.0, 1.0]], s, ids=[0, 1])
    obs = obs_of([[5.02, 0.0], [4.97, 0.005]])  # both inside landmark 0's gate; landmark 1 far away
    res = associate(obs, cands, AssociationConfig(method=method), rng=np.random.default_rng(0))
    assert sorted(res.assignment.tolist()) == [CLUTTER, 0]
    # the closer one wins (lower d2): observation 0 has d2 = 0.04, observation 1 has 0.09 + 0.0625
    assert res.assignment[0] == 0


def test_nn_has_no_mutual_exclusion_and_reports_nan_joint_nis():
    s = np.diag([0.1**2, 0.02**2])
    cands = cands_of([[5.0, 0.0], [9.0, 1.0]], s, ids=[0, 1])
    obs = obs_of([[5.02, 0.0], [4.97, 0.005]])
    res = associate(obs, cands, AssociationConfig(method="nn"), rng=np.random.default_rng(0))
    assert res.assignment.tolist() == [0, 0]
    assert math.isnan(res.joint_nis)


def brute_force_max_matching(cost, allowed):
    k, n = cost.shape
    best = (0, 0.0, None)
    options = [[*np.flatnonzero(allowed[i]).tolist(), None] for i in range(k)]
    for combo in itertools.product(*options):
        used = [c for c in combo if c is not None]
        if len(set(used)) != len(used):
            continue
        total = sum(cost[i, c] for i, c in enumerate(combo) if c is not None)
        if len(used) > best[0] or (len(used) == best[0] and total < best[1] - 1e-12):
            best = (len(used), total, combo)
    return best


def test_mutual_exclusion_assignment_is_max_cardinality_then_min_cost():
    rng = np.random.default_rng(11)
    for _ in range(150):
        k, n = rng.integers(1, 6), rng.integers(1, 6)
        cost = rng.uniform(0, 9, size=(k, n))
        allowed = rng.random((k, n)) < 0.5
        r, c = max_matching(cost, allowed)
        n_best, total_best, _ = brute_force_max_matching(cost, allowed)
        assert len(r) == n_best
        assert cost[r, c].sum() == pytest.approx(total_best, abs=1e-9)
        assert len(set(c.tolist())) == len(c) and np.all(allowed[r, c])


def test_mahalanobis_method_matches_brute_force_on_random_problems():
    rng = np.random.default_rng(5)
    for _ in range(60):
        obs, cands = random_problem(rng, max_obs=5, max_cand=6)
        cfg = AssociationConfig(method="mahalanobis")
        prob = build_problem(obs, cands, cfg)
        res = associate(obs, cands, cfg, rng=rng)
        n_best, total_best, _ = brute_force_max_matching(prob.d2, prob.ic)
        m = res.assignment >= 0
        assert m.sum() == n_best
        assert np.nansum(res.d2) == pytest.approx(total_best, abs=1e-9)


def test_nn_takes_the_euclidean_nearest_within_the_distance():
    rng = np.random.default_rng(9)
    for _ in range(40):
        obs, cands = random_problem(rng, max_obs=6, max_cand=8)
        cfg = AssociationConfig(method="nn", nn_max_distance=0.5)
        res = associate(obs, cands, cfg, rng=rng)
        for i in range(len(obs)):
            if len(cands) == 0:
                assert res.assignment[i] == NEW
                continue
            db = np.angle(np.exp(1j * (obs.bearing_rad[i] - cands.z_pred[:, 1])))
            dist = np.hypot(obs.range_m[i] - cands.z_pred[:, 0], db)
            j = int(np.argmin(dist))
            if dist[j] <= 0.5:
                assert res.assignment[i] == cands.ids[j]
            else:
                assert res.assignment[i] in (NEW, CLUTTER)


# ------------------------------------------------------------------------------------------------ descriptors
def test_descriptor_gate_decides_between_equally_close_landmarks():
    s = np.diag([0.2**2, 0.05**2])
    desc_l = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    cands = cands_of([[5.0, 0.02], [5.0, -0.02]], s, ids=[4, 5], desc=desc_l)
    # geometrically the observation is a little closer to landmark 4, but it carries landmark 5's signature
    obs = obs_of([[5.0, 0.01]], desc=np.array([[0.02, 0.97, 0.01]]))
    for method in ("nn", "mahalanobis", "jcbb", "ransac"):
        with_desc = AssociationConfig(method=method, descriptor_max_distance=0.2)
        without = AssociationConfig(method=method)
        assert associate(obs, cands, with_desc, rng=np.random.default_rng(0)).assignment.tolist() == [5], method
        assert associate(obs, cands, without, rng=np.random.default_rng(0)).assignment.tolist() == [4], method
    # a signature unlike every landmark: not a candidate at all, so it is NEW even though it is geometrically close
    odd = obs_of([[5.0, 0.01]], desc=np.array([[0.0, 0.0, 1.0]]))
    res = associate(odd, cands, AssociationConfig(method="jcbb", descriptor_max_distance=0.2), rng=RNG)
    assert res.assignment.tolist() == [NEW]


# ------------------------------------------------------------------------------------------------ ransac, known
def test_ransac_is_deterministic_per_rng_and_returns_a_compatible_exclusive_set():
    from scipy import stats

    rng = np.random.default_rng(21)
    for _ in range(30):
        obs, cands = random_problem(rng, max_obs=12, max_cand=14, spacing_m=0.4)
        cfg = AssociationConfig(method="ransac", ransac_iterations=40)
        a = associate(obs, cands, cfg, rng=np.random.default_rng(5))
        b = associate(obs, cands, cfg, rng=np.random.default_rng(5))
        np.testing.assert_array_equal(a.assignment, b.assignment)
        prob = build_problem(obs, cands, cfg)
        m = np.flatnonzero(a.assignment >= 0)
        cand = np.array([int(np.flatnonzero(prob.ids == x)[0]) for x in a.assignment[m]], dtype=int)
        assert len(set(cand.tolist())) == len(cand) and np.all(prob.ic[m, cand])
        if len(m):
            assert a.joint_nis <= stats.chi2.ppf(0.99, 2 * len(m)) + 1e-9


def test_ransac_recovers_a_pattern_shifted_by_the_pose_error():
    # a 3 x 3 lattice of landmarks 0.6 m apart; the belief is 0.5 m off sideways, so every sighting lands on a
    # neighbour's prediction. Minimal sets of correct pairs explain all the others.
    xs, ys = np.meshgrid([4.0, 4.6, 5.2], [-0.6, 0.0, 0.6])
    lm = np.column_stack([xs.ravel(), ys.ravel()])
    pose = np.zeros(3)
    belief = np.array([0.0, 0.55, 0.0])
    p = np.diag([0.3**2, 0.3**2, 0.005**2])
    cov = np.zeros((3 + 18, 3 + 18))
    cov[:3, :3] = p
    cov[3:, 3:] = 0.005**2 * np.eye(18)
    r = np.diag([0.02**2, 0.002**2])
    cands = candidates_from_belief(belief, lm, np.arange(9), cov, r)
    z = range_bearing(pose, lm)
    obs = obs_of(z, ids=np.arange(9))
    res = associate(obs, cands, AssociationConfig(method="ransac"), rng=np.random.default_rng(0))
    np.testing.assert_array_equal(res.assignment, np.arange(9))
    assert res.nodes == 100


def test_known_method_uses_source_ids_and_reports_statistics():
    s = np.diag([0.1**2, 0.02**2])
    cands = cands_of([[5.0, 0.0], [3.0, 1.0]], s, ids=[10, 20])
    obs = obs_of([[5.1, 0.0], [3.0, 1.02], [2.0, 2.0], [6.0, -1.0]], ids=[10, 20, 99, -1])
    res = associate(obs, cands, AssociationConfig(method="known"), rng=RNG)
    assert res.assignment.tolist() == [10, 20, NEW, CLUTTER]
    np.testing.assert_allclose(res.d2[:2], [1.0, 1.0])
    assert res.joint_nis == pytest.approx(2.0)


# ------------------------------------------------------------------------------------------------ prediction
def test_candidates_from_belief_equals_dense_h_p_ht_plus_r():
    rng = np.random.default_rng(4)
    n = 4
    pose = np.array([1.0, -2.0, 0.7])
    lm = rng.uniform(-5, 5, size=(n, 2))
    a = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    cov = 0.01 * a @ a.T + 1e-3 * np.eye(3 + 2 * n)
    cands = candidates_from_belief(pose, lm, np.arange(n), cov, R)

    def h(x):
        return range_bearing(x[:3], x[3:].reshape(n, 2)).ravel()

    x0 = np.concatenate([pose, lm.ravel()])
    jac = numerical_jacobian(h, x0, input_angles=[2], output_angles=list(range(1, 2 * n, 2)))
    expected = jac @ cov @ jac.T + np.kron(np.eye(n), R)
    np.testing.assert_allclose(cands.S_joint, expected, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(cands.z_pred, range_bearing(pose, lm))
    for i in range(n):
        np.testing.assert_allclose(cands.S[i], expected[2 * i:2 * i + 2, 2 * i:2 * i + 2], rtol=1e-6)


# ------------------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("method", METHODS)
def test_empty_observations_and_no_candidates_give_defined_results(method):
    cfg = AssociationConfig(method=method)
    s = np.diag([0.1**2, 0.02**2])
    res = associate(obs_of(np.zeros((0, 2))), cands_of([[5.0, 0.0]], s), cfg, rng=RNG)
    assert res.assignment.shape == (0,) and res.d2.shape == (0,) and res.joint_nis == 0.0
    res = associate(obs_of([[5.0, 0.0], [2.0, 1.0]], ids=[3, -1]), Candidates.empty(), cfg, rng=RNG)
    expected = [NEW, CLUTTER] if method == "known" else [NEW, NEW]
    assert res.assignment.tolist() == expected and np.all(np.isnan(res.d2))
    res = associate(obs_of(np.zeros((0, 2))), Candidates.empty(), cfg, rng=RNG)
    assert res.assignment.shape == (0,)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda c: dataclasses.replace(c, S=c.S * np.array([[1, 1], [0.5, 1]])), "not symmetric"),
        (lambda c: dataclasses.replace(c, S=np.broadcast_to([[1e-2, 1e-2], [1e-2, 1e-2]], c.S.shape).copy()),
         "singular"),
        (lambda c: dataclasses.replace(c, S=-c.S), "not positive definite"),
        (lambda c: dataclasses.replace(c, S=np.where(np.arange(4).reshape(2, 2) == 0, np.nan, c.S)), "non-finite"),
        (lambda c: dataclasses.replace(c, ids=np.array([1, 1, 2])), "unique"),
        (lambda c: dataclasses.replace(c, ids=np.array([-1, 0, 2])), ">= 0"),
        (lambda c: dataclasses.replace(c, z_pred=c.z_pred[:2]), "z_pred"),
        (lambda c: dataclasses.replace(c, S_joint=np.eye(4)), "S_joint must have shape"),
        (lambda c: dataclasses.replace(c, S_joint=np.triu(np.ones((6, 6))) + np.eye(6)), "S_joint is not symmetric"),
        (lambda c: dataclasses.replace(c, S_joint=2 * c.S_joint), "differs from"),
    ],
)
def test_bad_candidates_raise_a_clear_value_error(method, mutate, message):
    obs = obs_of([[5.0, 0.0], [5.1, 0.3]])
    s = np.array([[0.1**2, 1e-4], [1e-4, 0.02**2]])
    good = cands_of([[5.0, 0.0], [5.1, 0.3], [2.0, -1.0]], s, s_joint=np.kron(np.eye(3), s))
    with pytest.raises(ValueError, match=message):
        associate(obs, mutate(good), AssociationConfig(method=method), rng=RNG)


@pytest.mark.parametrize("method", ["jcbb", "ransac"])
def test_indefinite_joint_covariance_is_refused_where_it_is_used(method):
    s = np.diag([0.1**2, 0.02**2])
    s_joint = np.kron(np.eye(2), s)
    s_joint[0:2, 2:4] = s_joint[2:4, 0:2] = 2 * s  # blocks fine, whole matrix indefinite
    cands = cands_of([[5.0, 0.0], [5.1, 0.05]], s, s_joint=s_joint)
    obs = obs_of([[5.0, 0.0], [5.1, 0.05]])
    with pytest.raises(ValueError, match="S_joint is not positive definite"):
        associate(obs, cands, AssociationConfig(method=method), rng=RNG)


def test_bad_observations_and_config_raise():
    s = np.diag([0.1**2, 0.02**2])
    cands = cands_of([[5.0, 0.0]], s)
    with pytest.raises(ValueError, match="non-finite"):
        associate(obs_of([[np.nan, 0.0]]), cands, AssociationConfig(), rng=RNG)
    with pytest.raises(ValueError, match="range_m must be >= 0"):
        associate(obs_of([[-1.0, 0.0]]), cands, AssociationConfig(), rng=RNG)
    with pytest.raises(ValueError, match=r"Observations.descriptor must have shape \(1, D\)"):
        associate(obs_of([[5.0, 0.0]], desc=np.ones((2, 3))), cands, AssociationConfig(), rng=RNG)
    with pytest.raises(ValueError, match="descriptor length"):
        associate(obs_of([[5.0, 0.0]], desc=np.ones((1, 3))), cands_of([[5.0, 0.0]], s, desc=np.ones((1, 4))),
                  AssociationConfig(descriptor_max_distance=1.0), rng=RNG)
    for field, value in [("ransac_min_pairs", 0), ("jcbb_max_nodes", 0), ("ransac_iterations", 0),
                         ("gate_probability", 1.0), ("nn_max_distance", -1.0), ("method", "magic")]:
        with pytest.raises(ValueError, match=field):
            AssociationConfig(**{field: value})


def test_candidates_from_pose_belief_is_the_linearised_prediction_covariance() -> None:
    from slam2d.association import candidates_from_pose_belief
    from slam2d.models.sensors import range_bearing

    rng = np.random.default_rng(7)
    pose = np.array([1.0, 2.0, 0.4])
    lm = rng.uniform(-3, 6, size=(4, 2))
    pcov = np.diag([0.2, 0.1, 0.05]) ** 2
    r = np.diag([0.1, 0.02]) ** 2
    c = candidates_from_pose_belief(pose, pcov, lm, np.arange(4) + 7, r)
    # Jacobian of the stacked predictions w.r.t. the pose by central differences (independent of the library's)
    eps = 1e-6
    jac = np.column_stack([(range_bearing(pose + eps * d, lm) - range_bearing(pose - eps * d, lm)).ravel() / (2 * eps)
                           for d in np.eye(3)])
    expected = jac @ pcov @ jac.T + np.kron(np.eye(4), r)
    assert c.S_joint is not None
    np.testing.assert_allclose(c.S_joint, expected, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(c.S, [expected[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(4)], atol=1e-10)
    np.testing.assert_array_equal(c.ids, np.arange(4) + 7)
