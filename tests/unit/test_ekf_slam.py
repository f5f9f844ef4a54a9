"""EKF-SLAM: kernels against dense references and finite differences, the class against the kernels, the linear-
Gaussian equivalence with batch least squares, GPS through correlations, landmark management and bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from slam2d import _jacobians
from slam2d.association import CLUTTER, NEW, AssociationConfig, Candidates
from slam2d.estimator import Estimator
from slam2d.filters.ekf_slam import (
    EKFSLAM,
    CovarianceError,
    EKFConfig,
    augment_linearized,
    augment_state,
    augment_state_batch,
    ekf_predict,
    ekf_predict_linearized,
    ekf_update,
    ekf_update_position,
    ekf_update_range_bearing,
    odometry_covariance_scalar,
    odometry_scalar,
    predict_landmarks,
    range_bearing_scalar,
    remove_landmarks,
    repair_covariance,
    run_association,
)
from slam2d.geometry.angles import angle_diff, wrap_angle
from slam2d.lab.registry import estimator_names, make_config, make_estimator
from slam2d.lab.runner import run, run_named
from slam2d.log import Observations, Step
from slam2d.models.motion import MotionNoise, odometry_covariance, odometry_predict, odometry_predict_jacobians
from slam2d.models.sensors import SensorConfig, range_bearing, range_bearing_inverse, range_bearing_jacobians
from slam2d.sim.simulator import simulate
from slam2d.testing import numerical_jacobian

R_RB = np.diag([0.1**2, 0.02**2])


def random_state(rng: np.random.Generator, n_lm: int, spread: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """A random pose + landmarks with a random SPD covariance (correlated everywhere)."""
    n = 3 + 2 * n_lm
    mu = np.concatenate([[rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-np.pi, np.pi)],
                         rng.uniform(-spread, spread, 2 * n_lm)])
    x = rng.standard_normal((n, n + 2)) * 0.1
    return mu, x @ x.T + 0.01 * np.eye(n)


def dense_joseph(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference: gain and Joseph-form posterior covariance with a full-width Jacobian (O(n^3))."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    ikh = np.eye(P.shape[0]) - K @ H
    return K, ikh @ P @ ikh.T + K @ R @ K.T


# ------------------------------------------------------------------------------------------ augment_state
def test_augment_state_lesson_case():
    mu = np.array([5.0, 3.0, np.pi / 4, 1.0, 2.0])
    rng = np.random.default_rng(0)
    x = rng.standard_normal((5, 5))
    P = x @ x.T * 0.01 + 0.01 * np.eye(5)
    R = np.diag([0.1**2, 0.05**2])
    mu2, P2 = augment_state(mu, P, 2.0, 0.0, R)
    assert mu2.shape == (7,) and P2.shape == (7, 7)
    np.testing.assert_allclose(mu2[5:], [5 + np.sqrt(2), 3 + np.sqrt(2)], atol=1e-12)
    np.testing.assert_allclose(mu2[5:], [6.414, 4.414], atol=5e-4)
    # Jacobians of l = [x + r cos(th + b), y + r sin(th + b)] at th + b = pi/4, r = 2, written out by hand
    c = s = np.sqrt(0.5)
    g_r = np.array([[1.0, 0.0, -2 * s], [0.0, 1.0, 2 * c]])
    g_z = np.array([[c, -2 * s], [s, 2 * c]])
    np.testing.assert_array_equal(P2[:5, :5], P)
    np.testing.assert_allclose(P2[5:, :5], g_r @ P[:3, :], atol=1e-15)
    np.testing.assert_allclose(P2[:5, 5:], (g_r @ P[:3, :]).T, atol=1e-15)
    np.testing.assert_allclose(P2[5:, 5:], g_r @ P[:3, :3] @ g_r.T + g_z @ R @ g_z.T, atol=1e-15)
    assert np.array_equal(P2, P2.T)
    assert np.linalg.eigvalsh(P2)[0] > 0
    # the inputs are untouched (pure function)
    np.testing.assert_array_equal(mu, [5.0, 3.0, np.pi / 4, 1.0, 2.0])


def test_augment_batch_equals_sequential_augmentation():
    rng = np.random.default_rng(1)
    mu, P = random_state(rng, 3)
    z = np.array([[2.0, 0.3], [4.0, -2.0], [1.5, 3.0]])
    mb, pb = augment_state_batch(mu, P, z, R_RB)
    ms, ps = mu, P
    for zi in z:
        ms, ps = augment_state(ms, ps, zi[0], zi[1], R_RB)
    np.testing.assert_allclose(mb, ms, atol=1e-12)
    np.testing.assert_allclose(pb, ps, atol=1e-12)


def test_augment_state_rejects_bad_input():
    mu, P = np.zeros(3), np.eye(3) * 0.1
    with pytest.raises(ValueError, match="range_m"):
        augment_state(mu, P, -1.0, 0.0, R_RB)
    with pytest.raises(ValueError, match="finite"):
        augment_state(mu, P, np.nan, 0.0, R_RB)
    with pytest.raises(ValueError, match="R_obs"):
        augment_state(mu, P, 1.0, 0.0, -R_RB)
    with pytest.raises(ValueError, match="mu must have shape"):
        augment_state(np.zeros(4), np.eye(4), 1.0, 0.0, R_RB)


# ------------------------------------------------------------------------------------------ Jacobians (FD)
def test_registry_holds_every_jacobian_the_filter_uses():
    import slam2d.filters.ekf_slam  # noqa: F401  (registers the scalar range-bearing twin)

    names = {p.name.rsplit(".", 1)[-1] for p in _jacobians.REGISTRY}
    for n in ("odometry_predict", "range_bearing", "range_bearing_inverse", "absolute_position",
              "range_bearing_scalar", "odometry_scalar"):
        assert n in names  # each is FD-checked by tests/unit/test_geometry.py


def test_scalar_twins_equal_the_batched_models():
    rng = np.random.default_rng(21)
    noise = MotionNoise()
    for k in range(50):
        pose = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
        u = np.array([*rng.uniform(-1, 1, 2), rng.uniform(-3, 3)]) if k % 5 else np.array([0.0, 0.0, 0.3])
        new, G, V = odometry_scalar(pose, u)
        g_ref, v_ref = odometry_predict_jacobians(pose, u)
        np.testing.assert_allclose(new, odometry_predict(pose, u), atol=1e-14)
        np.testing.assert_allclose(G, g_ref, atol=1e-14)
        np.testing.assert_allclose(V, v_ref, atol=1e-14)
        np.testing.assert_allclose(odometry_covariance_scalar(u, noise), odometry_covariance(u, noise), atol=1e-15)
        lm = rng.uniform(-8, 8, 2)
        z, H = range_bearing_scalar(pose, lm)
        hp, hl = range_bearing_jacobians(pose, lm)
        np.testing.assert_allclose(z, range_bearing(pose, lm), atol=1e-14)
        np.testing.assert_allclose(H, np.hstack([hp, hl]), atol=1e-14)


@pytest.mark.parametrize("seed", range(4))
def test_predict_matches_full_state_finite_difference_linearisation(seed):
    rng = np.random.default_rng(seed)
    mu, P = random_state(rng, 4)
    u = np.array([0.3, 0.05, 0.2])
    noise = MotionNoise()

    def f_state(x):
        return np.concatenate([odometry_predict(x[:3], u), x[3:]])

    def f_u(uu):
        return np.concatenate([odometry_predict(mu[:3], uu), mu[3:]])

    F = numerical_jacobian(f_state, mu, input_angles=(2,), output_angles=(2,))
    Fu = numerical_jacobian(f_u, u, input_angles=(2,), output_angles=(2,))
    ref = F @ P @ F.T + Fu @ odometry_covariance(u, noise) @ Fu.T
    mu2, P2 = ekf_predict(mu, P, u, noise)
    np.testing.assert_allclose(mu2, f_state(mu), atol=1e-12)
    np.testing.assert_allclose(P2, ref, atol=1e-8)
    # landmark block bit-for-bit untouched; P symmetric
    np.testing.assert_array_equal(P2[3:, 3:], P[3:, 3:])
    assert np.array_equal(P2, P2.T)


@pytest.mark.parametrize("seed", range(4))
def test_range_bearing_update_matches_dense_joseph_with_fd_jacobian(seed):
    rng = np.random.default_rng(seed)
    mu, P = random_state(rng, 5)
    j = 2
    z = range_bearing(mu[:3], mu[3 + 2 * j:5 + 2 * j]) + np.array([0.05, -0.01])

    def h(x):
        return range_bearing(x[:3], x[3 + 2 * j:5 + 2 * j])

    H = numerical_jacobian(h, mu, input_angles=(2,), output_angles=(1,))
    assert np.count_nonzero(np.abs(H) > 1e-12) <= 2 * 5 - 1  # the sparse 2x5 block (dr/dtheta = 0)
    K, P_ref = dense_joseph(P, H, R_RB)
    nu = z - h(mu)
    nu[1] = angle_diff(z[1], h(mu)[1])
    mu_ref = mu + K @ nu
    mu_ref[2] = wrap_angle(mu_ref[2])
    mu2, P2 = ekf_update_range_bearing(mu, P, j, z, R_RB)
    np.testing.assert_allclose(mu2, mu_ref, atol=1e-8)
    np.testing.assert_allclose(P2, P_ref, atol=1e-8)
    assert np.array_equal(P2, P2.T)


def test_low_rank_update_equals_dense_joseph_exactly():
    """With the exact same H (no FD error) the O(n^2) symmetric form equals the dense Joseph form to rounding."""
    rng = np.random.default_rng(5)
    mu, P = random_state(rng, 6)
    idx = np.array([0, 1, 2, 9, 10])
    Hs = rng.standard_normal((2, 5))
    H = np.zeros((2, mu.size))
    H[:, idx] = Hs
    nu = np.array([0.1, -0.2])
    K, P_ref = dense_joseph(P, H, R_RB)
    mu2, P2 = ekf_update(mu, P, idx, Hs, nu, R_RB)
    mu_ref = mu + K @ nu
    mu_ref[2] = wrap_angle(mu_ref[2])
    np.testing.assert_allclose(mu2, mu_ref, atol=1e-12)
    np.testing.assert_allclose(P2, P_ref, atol=1e-12)


def test_augment_matches_full_state_finite_difference_linearisation():
    rng = np.random.default_rng(3)
    mu, P = random_state(rng, 2)
    z = np.array([3.0, 2.5])

    def g(x):
        return np.concatenate([x, range_bearing_inverse(x[:3], z)])

    def g_z(zz):
        return np.concatenate([mu, range_bearing_inverse(mu[:3], zz)])

    Gx = numerical_jacobian(g, mu, input_angles=(2,), output_angles=(2,))
    Gz = numerical_jacobian(g_z, z, input_angles=(1,), output_angles=(2,))
    mu2, P2 = augment_state(mu, P, z[0], z[1], R_RB)
    np.testing.assert_allclose(mu2, g(mu), atol=1e-12)
    np.testing.assert_allclose(P2, Gx @ P @ Gx.T + Gz @ R_RB @ Gz.T, atol=1e-8)


def test_gps_update_matches_dense_joseph_with_fd_jacobian():
    rng = np.random.default_rng(4)
    mu, P = random_state(rng, 3)
    z = mu[:2] + np.array([0.3, -0.2])
    H = numerical_jacobian(lambda x: x[:2], mu, input_angles=(2,))
    R = np.eye(2) * 0.25
    K, P_ref = dense_joseph(P, H, R)
    mu2, P2 = ekf_update_position(mu, P, z, R)
    np.testing.assert_allclose(mu2, mu + K @ (z - mu[:2]), atol=1e-10)
    np.testing.assert_allclose(P2, P_ref, atol=1e-10)


def test_predict_landmarks_matches_dense_joint_innovation_covariance():
    rng = np.random.default_rng(6)
    mu, P = random_state(rng, 6)
    js = np.array([4, 1, 3])

    def h(x):
        return np.concatenate([range_bearing(x[:3], x[3 + 2 * j:5 + 2 * j]) for j in js])

    angles = tuple(range(1, 2 * len(js), 2))
    J = numerical_jacobian(h, mu, input_angles=(2,), output_angles=angles)
    S_ref = J @ P @ J.T + np.kron(np.eye(len(js)), R_RB)
    z_pred, S, S_joint = predict_landmarks(mu, P, js, R_RB, joint=True)
    assert S_joint is not None
    np.testing.assert_allclose(z_pred.reshape(-1), h(mu), atol=1e-12)
    np.testing.assert_allclose(S_joint, S_ref, atol=1e-8)
    for i in range(len(js)):
        np.testing.assert_allclose(S[i], S_ref[2 * i:2 * i + 2, 2 * i:2 * i + 2], atol=1e-8)


# ------------------------------------------------------------------------------------------ linear-Gaussian
def test_linear_gaussian_filter_equals_batch_least_squares():
    """Linear motion x' = x + u and linear observations z = l - p_xy: the filter's final mean and covariance of
    (x_T, landmarks) equal the batch least-squares posterior (information form over the whole trajectory)."""
    rng = np.random.default_rng(11)
    T, M = 25, 5
    Q = np.diag([0.02, 0.03, 0.001])
    Q[0, 1] = Q[1, 0] = 0.005
    R = np.array([[0.04, 0.01], [0.01, 0.05]])
    P0 = np.diag([0.1, 0.2, 0.01])
    m0 = np.array([0.5, -0.3, 0.05])
    true_l = rng.uniform(-5, 5, (M, 2))
    us = rng.normal(0, [0.3, 0.3, 0.01], (T, 3))
    xs = np.cumsum(np.vstack([m0, us]), axis=0) + rng.normal(0, 0.1, (T + 1, 3))
    obs = []  # (t, landmark, z)
    for t in range(1, T + 1):
        for j in rng.choice(M, size=rng.integers(1, 4), replace=False):
            obs.append((t, int(j), true_l[j] - xs[t, :2] + rng.normal(0, 0.2, 2)))
    # --- the filter, through the same kernels the estimator uses, with linear models
    h_block = np.array([[-1.0, 0, 0, 1, 0], [0, -1, 0, 0, 1]])
    mu, P = m0.copy(), P0.copy()
    order: list[int] = []
    for t in range(1, T + 1):
        mu, P = ekf_predict_linearized(mu, P, mu[:3] + us[t - 1], np.eye(3), Q)
        for tt, j, z in obs:
            if tt != t:
                continue
            if j in order:
                a = 3 + 2 * order.index(j)
                nu = z - (mu[a:a + 2] - mu[:2])
                mu, P = ekf_update(mu, P, [0, 1, 2, a, a + 1], h_block, nu, R)
            else:
                g_r = np.array([[[1.0, 0, 0], [0, 1, 0]]])
                mu, P = augment_linearized(mu, P, (mu[:2] + z)[None], g_r, np.eye(2)[None], R)
                order.append(j)
    # --- batch least squares: unknowns [x_0..x_T, l_(order)]
    nx = 3 * (T + 1)
    nv = nx + 2 * len(order)
    info = np.zeros((nv, nv))
    vec = np.zeros(nv)

    def add(rows_j: np.ndarray, cols: list[int], target: np.ndarray, cov: np.ndarray) -> None:
        # residual rows_j @ X[cols] - target ~ N(0, cov)
        w = np.linalg.inv(cov)
        info[np.ix_(cols, cols)] += rows_j.T @ w @ rows_j
        vec[cols] += rows_j.T @ w @ target

    add(np.eye(3), [0, 1, 2], m0, P0)
    for t in range(1, T + 1):
        add(np.hstack([-np.eye(3), np.eye(3)]), list(range(3 * t - 3, 3 * t + 3)), us[t - 1], Q)
    for t, j, z in obs:
        k = nx + 2 * order.index(j)
        add(np.array([[-1.0, 0, 1, 0], [0, -1, 0, 1]]), [3 * t, 3 * t + 1, k, k + 1], z, R)
    x_batch = np.linalg.solve(info, vec)
    cov_batch = np.linalg.inv(info)
    keep = list(range(3 * T, 3 * T + 3)) + list(range(nx, nv))
    np.testing.assert_allclose(mu, x_batch[keep], atol=1e-8)
    np.testing.assert_allclose(P, cov_batch[np.ix_(keep, keep)], atol=1e-8)


# ------------------------------------------------------------------------------------------ GPS through correlations
def test_precise_gps_fix_moves_unobserved_landmarks_by_the_conditional_gaussian():
    """With a near-perfect fix, a landmark that is not observed moves by P_lr P_rr^-1 (z - x): the correlation."""
    rng = np.random.default_rng(8)
    mu, P = random_state(rng, 3)
    z = mu[:2] + np.array([0.4, -0.3])
    R = np.eye(2) * 1e-10
    mu2, P2 = ekf_update_position(mu, P, z, R)
    shift = P[3:, :2] @ np.linalg.solve(P[:2, :2], z - mu[:2])
    np.testing.assert_allclose(mu2[3:] - mu[3:], shift, rtol=1e-6, atol=1e-8)
    assert np.all(np.hypot(*(mu2[3:] - mu[3:]).reshape(-1, 2).T) > 1e-2)  # every landmark moved, none was observed
    np.testing.assert_allclose(mu2[:2], z, atol=1e-8)


def test_gps_fix_after_drift_corrects_landmarks_out_of_view():
    """Drive the loop with a short-range sensor (drift builds up), then one precise GPS fix: landmarks behind the
    robot, not observed at that step, get closer to the truth and more certain."""
    log = simulate("loop", 3, steps=120, **{"sensor.max_range_m": 3.0})
    est = EKFSLAM(make_config("ekf", {"confirm_after": 1}, log.metadata))
    est.reset(log.initial_pose, rng=np.random.default_rng(0))
    for step in log:
        est.step(step)
    mu, P, ids = est.state
    truth = log.true_landmarks[ids]
    lm = mu[3:].reshape(-1, 2)
    out_of_view = np.hypot(*(truth - log.true_poses[-1, :2]).T) > 6.0
    assert out_of_view.sum() >= 10
    # the estimator applies GPS fixes with exactly this kernel (see EKFSLAM.step)
    mu2, P2 = ekf_update_position(mu, P, log.true_poses[-1, :2], np.eye(2) * 1e-6)
    lm2 = mu2[3:].reshape(-1, 2)
    err_before = np.hypot(*(lm - truth)[out_of_view].T)
    err_after = np.hypot(*(lm2 - truth)[out_of_view].T)
    assert np.all(np.abs(lm2 - lm)[out_of_view].max(axis=1) > 1e-3)
    assert np.sqrt(np.mean(err_after**2)) < 0.8 * np.sqrt(np.mean(err_before**2))
    var_before = np.diagonal(P)[3:].reshape(-1, 2)[out_of_view].sum()
    var_after = np.diagonal(P2)[3:].reshape(-1, 2)[out_of_view].sum()
    assert var_after < var_before


# ------------------------------------------------------------------------------------------ class vs kernels
def test_class_agrees_with_the_pure_kernels():
    log = simulate("room", 2, steps=60)
    cfg = make_config("ekf", {"confirm_after": 1, "tentative_max_misses": 0}, log.metadata)
    est = EKFSLAM(cfg)
    est.reset(log.initial_pose, rng=np.random.default_rng(0))
    R = cfg.sensor.covariance
    mu, P = log.initial_pose.copy(), np.zeros((3, 3))
    ids: list[int] = []
    for step in log:
        est.step(step)
        mu, P = ekf_predict(mu, P, step.odometry, cfg.motion)
        obs = step.observations
        new = []
        for o in range(len(obs)):
            i = int(obs.landmark_id[o])
            if i in ids:
                mu, P = ekf_update_range_bearing(mu, P, ids.index(i), obs.z[o], R)
            elif i >= 0 and i not in [int(obs.landmark_id[n]) for n in new]:
                new.append(o)
        if new:
            mu, P = augment_state_batch(mu, P, obs.z[new], R)
            ids += [int(obs.landmark_id[n]) for n in new]
    mu_c, P_c, ids_c = est.state
    assert ids_c.tolist() == ids
    np.testing.assert_allclose(mu_c, mu, atol=1e-12, rtol=0)
    np.testing.assert_allclose(P_c, P, atol=1e-12, rtol=0)
    snap = est.estimate()
    assert snap.state_dim == 3 + 2 * len(ids)
    np.testing.assert_allclose(snap.landmark_covs[0], P[3:5, 3:5], atol=0)


# ------------------------------------------------------------------------------------------ estimator behaviour
def test_registered_and_filled_from_log_metadata():
    assert "ekf" in estimator_names()
    log = simulate("room", 0, steps=5, **{"sensor.range_std_m": 0.3})
    cfg = make_config("ekf", None, log.metadata)
    assert isinstance(cfg, EKFConfig)
    assert cfg.sensor.range_std_m == 0.3
    assert cfg.association.method == "auto"  # resolved by the runner from the log, or at the first step
    assert make_config("ekf", None, log.metadata, has_ids=True).association.method == "known"
    est = make_estimator("ekf", {"snapshot_full_cov": True}, log.metadata)
    res = run(est, log, rng=np.random.default_rng(0))
    snap = res.final
    n_l = len(snap.landmarks)
    assert n_l > 0 and snap.landmark_covs is not None and snap.landmark_covs.shape == (n_l, 2, 2)
    assert snap.full_cov.shape == (snap.state_dim,) * 2
    assert snap.association.shape == (len(log.observations_at(5)),)
    est0 = make_estimator("ekf", None, log.metadata)
    est0.reset(log.initial_pose, rng=np.random.default_rng(0))
    assert est0.estimate().full_cov is None


def test_ekf_beats_dead_reckoning_on_room():
    _, ekf = run_named("ekf", "room", seed=1, overrides={"steps": 200})
    _, dr = run_named("dead-reckoning", "room", seed=1, overrides={"steps": 200})
    assert ekf["ate_rmse_m"] < 0.5 * dr["ate_rmse_m"]
    assert ekf["landmarks_estimated"] >= 20


@pytest.mark.parametrize("method", ["mahalanobis", "jcbb"])
def test_unknown_association_builds_the_same_map(method):
    log = simulate("room", 4, steps=150)
    est = EKFSLAM(make_config("ekf", {"association.method": method}, log.metadata))
    res = run(est, log, rng=np.random.default_rng(0))
    snap = res.final
    # every confirmed landmark sits near a distinct true landmark (optimal one-to-one matching; two true landmarks
    # of this world are only 0.3 m apart, so nearest-neighbour would not do)
    d = np.hypot(*(snap.landmarks[:, None, :] - log.true_landmarks[None]).transpose(2, 0, 1))
    rows, cols = linear_sum_assignment(d)
    assert len(rows) == len(snap.landmarks) >= 20
    assert np.all(d[rows, cols] < 0.3)
    assert res.metrics["ate_rmse_m"] < 0.2


def test_run_association_gates_and_excludes():
    cands = Candidates(np.array([10, 11]), np.array([[3.0, 0.0], [3.0, 0.5]]), np.stack([R_RB, R_RB]))
    obs = Observations(np.array([3.02, 3.0, 6.0, 3.01]), np.array([0.49, 0.005, 2.0, 0.01]),
                       np.full(4, -1, dtype=np.int64))
    res = run_association(obs, cands, AssociationConfig(method="mahalanobis"), np.random.default_rng(0))
    assert res.assignment[0] == 11
    assert res.assignment[2] == NEW
    # observations 1 and 3 both fit landmark 10: one gets it, the other is not matched twice
    assert sorted(res.assignment[[1, 3]].tolist()) in ([10, CLUTTER], [CLUTTER, 10], [NEW, 10], [10, NEW])


def test_clutter_landmarks_are_removed_and_state_shrinks_consistently():
    log = simulate("room", 5, steps=120, clutter_rate=2.0)
    est = EKFSLAM(make_config("ekf", {"association.method": "mahalanobis"}, log.metadata))
    est.reset(log.initial_pose, rng=np.random.default_rng(0))
    removed_seen = False
    for step in log:
        mu_before, P_before, ids_before = est.state
        est.step(step)
        mu, P, ids = est.state
        assert mu.shape == (3 + 2 * len(ids),) and P.shape == (mu.size, mu.size)
        assert np.array_equal(P, P.T)
        snap = est.estimate()
        assert snap.state_dim == mu.size
        assert len(snap.landmarks) + len(snap.tentative_ids) == len(ids)
        if snap.diagnostics.landmarks_removed and not removed_seen:
            removed_seen = True
    assert removed_seen
    assert est.estimate().diagnostics.landmarks_removed >= 5
    assert est.estimate().diagnostics.covariance_repairs == 0
    # most surviving confirmed landmarks are real
    snap = est.estimate()
    d = np.hypot(*(snap.landmarks[:, None, :] - log.true_landmarks[None]).transpose(2, 0, 1)).min(axis=1)
    assert np.mean(d < 0.5) >= 0.8


def test_remove_landmarks_is_exact_marginalisation():
    rng = np.random.default_rng(9)
    mu, P = random_state(rng, 5)
    mu2, P2 = remove_landmarks(mu, P, [1, 3])
    keep = [0, 1, 2, 3, 4, 7, 8, 11, 12]
    np.testing.assert_array_equal(mu2, mu[keep])
    np.testing.assert_array_equal(P2, P[np.ix_(keep, keep)])
    assert P2.flags.c_contiguous


# ------------------------------------------------------------------------------------------ bad input
def _step_with(r: list[float], b: list[float], ids: list[int]) -> Step:
    obs = Observations(np.array(r, dtype=float), np.array(b, dtype=float), np.array(ids, dtype=np.int64))
    return Step(index=7, time_s=1.0, dt_s=0.2, odometry=np.array([0.1, 0.0, 0.0]), observations=obs)


@pytest.mark.parametrize("r,b", [(np.nan, 0.1), (2.0, np.inf), (-0.5, 0.1)])
def test_bad_observations_raise_naming_the_step(r, b):
    est = EKFSLAM()
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"step 7: observation 1"):
        est.step(_step_with([2.0, r], [0.0, b], [0, 1]))


def test_bad_observations_dropped_and_counted_in_drop_mode():
    est = EKFSLAM(EKFConfig(bad_observation="drop"))
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    est.step(_step_with([2.0, np.nan, -1.0, 3.0], [0.0, 0.1, 0.2, 1.0], [0, 1, 2, 3]))
    mu, P, ids = est.state
    assert ids.tolist() == [0, 3]
    assert np.all(np.isfinite(mu)) and np.all(np.isfinite(P))
    assert est.estimate().diagnostics.dropped_observations == 2
    assert est.estimate().association.tolist() == [NEW, CLUTTER, CLUTTER, NEW]


def test_follows_the_estimator_protocol():
    assert isinstance(EKFSLAM(), Estimator)


def test_bad_odometry_and_gps_raise():
    est = EKFSLAM()
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    step = _step_with([], [], [])
    with pytest.raises(ValueError, match="odometry"):
        est.step(dataclasses.replace(step, odometry=np.array([np.nan, 0, 0])))
    with pytest.raises(ValueError, match="gps"):
        est.step(dataclasses.replace(step, gps=np.array([np.nan, 0.0])))
    with pytest.raises(ValueError, match="initial_pose"):
        est.reset(np.array([0.0, np.inf, 0.0]), rng=np.random.default_rng(0))


def test_kernel_rejects_asymmetric_or_indefinite_covariance():
    rng = np.random.default_rng(10)
    mu, P = random_state(rng, 3)
    z = range_bearing(mu[:3], mu[5:7])
    asym = P.copy()
    asym[0, 6] += 0.5
    with pytest.raises(CovarianceError, match="not symmetric"):
        ekf_update_range_bearing(mu, asym, 1, z, R_RB)
    indef = P.copy()
    indef[5, 5] = -1.0
    with pytest.raises(CovarianceError, match="positive semi-definite"):
        ekf_update_range_bearing(mu, indef, 1, z, R_RB)
    with pytest.raises(CovarianceError, match="not finite"):
        bad = P.copy()
        bad[1, 1] = np.nan
        ekf_update_range_bearing(mu, bad, 1, z, R_RB)


def test_repair_rule_restores_a_symmetric_positive_definite_covariance():
    rng = np.random.default_rng(12)
    _, P = random_state(rng, 4)
    bad = P.copy()
    bad[0, 7] += 0.3
    w, v = np.linalg.eigh(P)
    bad2 = (v * np.where(np.arange(w.size) == 0, -1e-3, w)) @ v.T  # one negative eigenvalue
    for b in (bad, bad2):
        fixed = repair_covariance(b)
        assert np.array_equal(fixed, fixed.T)
        assert np.linalg.eigvalsh(fixed)[0] > 0
    # a valid covariance is left (numerically) unchanged
    np.testing.assert_allclose(repair_covariance(P), P, atol=1e-12)
    with pytest.raises(CovarianceError):
        repair_covariance(np.full((3, 3), np.nan))


@pytest.mark.parametrize("guard", ["raise", "repair"])
def test_estimator_covariance_guard(guard):
    log = simulate("room", 0, steps=20)
    est = EKFSLAM(make_config("ekf", {"covariance_guard": guard}, log.metadata))
    est.reset(log.initial_pose, rng=np.random.default_rng(0))
    steps = list(log)
    for s in steps[:10]:
        est.step(s)
    est._P[1, 4] += 0.7  # corrupt: break symmetry between pose and the first landmark
    if guard == "raise":
        with pytest.raises(CovarianceError):
            for s in steps[10:]:
                est.step(s)
        return
    for s in steps[10:]:
        est.step(s)
    mu, P, _ = est.state
    assert est.estimate().diagnostics.covariance_repairs == 1
    assert np.array_equal(P, P.T) and np.linalg.eigvalsh(P)[0] > 0 and np.all(np.isfinite(mu))


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="motion_noise_scale"):
        EKFConfig(motion_noise_scale=0.0)
    with pytest.raises(ValueError, match="confirm_after"):
        EKFConfig(confirm_after=0)
    with pytest.raises(ValueError, match="gps_std_m"):
        EKFConfig(gps_std_m=-1.0)
    with pytest.raises(ValueError, match="covariance_guard"):
        EKFConfig(covariance_guard="ignore")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="sensor"):
        make_config("ekf", {"sensor.range_std_m": -1})


def test_sensor_config_is_used_for_candidates():
    cfg = EKFConfig(sensor=SensorConfig(max_range_m=5.0), association=AssociationConfig(method="mahalanobis"))
    est = EKFSLAM(cfg)
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    est.step(_step_with([2.0, 4.0], [0.0, 1.0], [-1, -1]))
    _, _, ids = est.state
    assert ids.tolist() == [0, 1]
    # drive 30 m away: no candidate in reach, a new observation starts a new landmark instead of matching
    far = Step(index=8, time_s=1.2, dt_s=0.2, odometry=np.array([30.0, 0, 0]),
               observations=Observations(np.array([2.0]), np.array([0.0]), np.array([-1])))
    est.step(far)
    assert est.state[2].tolist() == [0, 1, 2]


def test_kernels_reject_bad_measurements():
    rng = np.random.default_rng(13)
    mu, P = random_state(rng, 2)
    for z in ([np.nan, 0.1], [1.0, np.inf], [-1.0, 0.0]):
        with pytest.raises(ValueError, match="range_m"):
            ekf_update_range_bearing(mu, P, 0, np.array(z), R_RB)
    with pytest.raises(ValueError, match="GPS"):
        ekf_update_position(mu, P, np.array([np.nan, 1.0]), np.eye(2))
    with pytest.raises(ValueError, match="odometry"):
        ekf_predict(mu, P, np.array([0.1, np.nan, 0.0]), MotionNoise())
    with pytest.raises(IndexError):
        ekf_update_range_bearing(mu, P, 2, np.array([1.0, 0.0]), R_RB)


def test_post_update_check_flags_a_negative_variance_and_the_estimator_repairs_it():
    """P indefinite outside the rows an update reads: the pre-checks pass, the update drives a variance negative,
    the post-check raises (applied=True); the estimator's repair rule then restores a valid covariance."""
    mu = np.array([0.0, 0.0, 0.0, 2.0, 0.0, 5.0, 5.0])
    P = np.eye(7) * 0.1
    P[5, 5] = 1e-6
    P[0, 5] = P[5, 0] = 0.05  # |corr| >> 1: P is indefinite, the touched block (pose + landmark 0) is not
    z = np.array([1.5, 0.0])
    with pytest.raises(CovarianceError, match="must be finite and >= 0") as info:
        ekf_update_range_bearing(mu, P, 0, z, R_RB)
    assert info.value.applied
    est = EKFSLAM(EKFConfig(confirm_after=1, tentative_max_misses=0))
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    est._mu, est._P, est._ids = mu.copy(), P.copy(), np.array([0, 1])
    est._tracks.append(2, step=0)  # two landmarks sighted once (the tracks replace the private hit/miss arrays)
    est.step(Step(index=1, time_s=0.2, dt_s=0.2, odometry=np.zeros(3),
                  observations=Observations(np.array([1.5]), np.array([0.0]), np.array([0]))))
    mu2, P2, _ = est.state
    assert est.estimate().diagnostics.covariance_repairs == 1
    assert np.array_equal(P2, P2.T) and np.linalg.eigvalsh(P2)[0] > 0


@pytest.mark.parametrize("limit", [0, 3, 5])
def test_confirmed_landmark_missed_in_view_is_removed_after_the_limit(limit):
    est = EKFSLAM(EKFConfig(association=AssociationConfig(method="mahalanobis"), confirm_after=2,
                            confirmed_max_misses=limit))
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    seen = Observations(np.array([2.0, 6.0]), np.array([0.0, 1.0]), np.array([-1, -1]))
    for i in (1, 2):
        est.step(Step(index=i, time_s=0.2 * i, dt_s=0.2, odometry=np.zeros(3), observations=seen))
    assert len(est.estimate().landmarks) == 2
    # keep seeing the second landmark only; the first one is in view (2 m ahead) but never matched again
    only_second = seen.subset(np.array([False, True]))
    for k in range(1, 8):
        est.step(Step(index=2 + k, time_s=0.2 * (2 + k), dt_s=0.2, odometry=np.zeros(3), observations=only_second))
        mu, P, ids = est.state
        expect = [1] if limit and k >= limit else [0, 1]
        assert ids.tolist() == expect, (k, ids)
        assert mu.shape == (3 + 2 * len(expect),) and P.shape == (mu.size, mu.size)
