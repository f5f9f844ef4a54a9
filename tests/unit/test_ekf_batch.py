"""The joint (batched) EKF update against the dense textbook formulas, and the filter with batches vs one update per
observation."""

import numpy as np
import pytest

import slam2d
from slam2d.filters.ekf_slam import (
    CovarianceError,
    EKFConfig,
    ekf_update_range_bearing,
    ekf_update_range_bearing_batch,
)
from slam2d.lab.registry import make_estimator
from slam2d.models.sensors import range_bearing
from testkit import dense_joseph


def _state(rng, n_l):
    n = 3 + 2 * n_l
    a = rng.standard_normal((n, n)) * 0.05
    P = a @ a.T + 0.01 * np.eye(n)
    mu = np.concatenate([[0.5, -0.3, 0.2], rng.uniform(-10, 10, 2 * n_l)])
    return mu, P


@pytest.mark.parametrize("js", [[0, 3, 1, 4], [2, 2, 5], [1]])
def test_batch_update_is_the_dense_joint_kalman_update(rng, js):
    mu, P = _state(rng, 6)
    js = np.array(js)
    lms = mu[3:].reshape(-1, 2)[js]
    z = range_bearing(mu[:3], lms).reshape(-1, 2) + rng.normal(0, [0.1, 0.02], (len(js), 2))
    R = np.diag([0.1**2, 0.02**2])
    mu_ref, P_ref = dense_joseph(mu, P, js, z, R)
    mu_b, P_b = ekf_update_range_bearing_batch(mu, P, js, z, R)
    np.testing.assert_allclose(mu_b, mu_ref, atol=1e-10)
    np.testing.assert_allclose(P_b, P_ref, atol=1e-10)
    assert np.array_equal(P_b, P_b.T)
    if len(js) == 1:  # one observation: the same update as the per-observation kernel
        mu_s, P_s = ekf_update_range_bearing(mu, P, int(js[0]), z[0], R)
        np.testing.assert_allclose(mu_b, mu_s, atol=1e-12)
        np.testing.assert_allclose(P_b, P_s, atol=1e-12)


def test_batch_update_rejects_bad_input(rng):
    mu, P = _state(rng, 3)
    R = np.diag([0.01, 0.0004])
    with pytest.raises(IndexError):
        ekf_update_range_bearing_batch(mu, P, [0, 3], np.ones((2, 2)), R)
    with pytest.raises(ValueError, match="observation 1"):
        ekf_update_range_bearing_batch(mu, P, [0, 1], np.array([[1.0, 0.0], [np.nan, 0.0]]), R)
    with pytest.raises(ValueError, match="one observation per landmark"):
        ekf_update_range_bearing_batch(mu, P, [0, 1], np.ones((3, 2)), R)
    bad = P.copy()
    bad[3:5, 3:5] = -5 * np.eye(2)  # not a covariance: S is not positive definite
    with pytest.raises(CovarianceError):
        ekf_update_range_bearing_batch(mu, bad, [0], np.array([[5.0, 0.1]]), R)
    with pytest.raises(ValueError, match="batch_from"):
        EKFConfig(batch_from=-1)


def test_batched_filter_matches_one_update_per_observation_to_first_order():
    """Same log, joint updates on every step vs one update per observation: the estimates agree far inside their
    uncertainty."""
    log = slam2d.simulate("room", seed=4, steps=150)
    out = {}
    for batch in (10**9, 0):
        est = make_estimator("ekf", {"batch_from": batch}, log.metadata)
        est.reset(log.initial_pose, rng=np.random.default_rng(0))
        for step in log:
            est.step(step)
        out[batch] = est.estimate()
    a, b = out[10**9], out[0]
    sd = np.sqrt(np.diag(a.pose_cov))
    assert np.all(np.abs(a.pose[:2] - b.pose[:2]) < 0.1 * sd[:2])
    np.testing.assert_allclose(a.pose_cov, b.pose_cov, rtol=0.05)
    np.testing.assert_array_equal(a.landmark_ids, b.landmark_ids)
    lm_sd = np.sqrt(np.diagonal(a.landmark_covs, axis1=1, axis2=2))
    ratio = np.abs(a.landmarks - b.landmarks) / lm_sd
    assert ratio.max() < 0.25, ratio.max()
