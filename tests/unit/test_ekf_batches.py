"""The chunked in-place EKF update (one triangle of P between chunks, dsyrk downdates) against the dense textbook
Joseph form applied chunk by chunk, and against chained calls of the single joint update."""

import numpy as np
import pytest

from slam2d.filters.ekf_slam import (
    CovarianceError,
    ekf_update_range_bearing_batch,
    ekf_update_range_bearing_batches,
)
from slam2d.models.sensors import range_bearing
from testkit import dense_joseph

R = np.diag([0.1**2, 0.02**2])


def _state(rng, n_l):
    n = 3 + 2 * n_l
    a = rng.standard_normal((n, n)) * 0.05
    P = a @ a.T + 0.01 * np.eye(n)
    mu = np.concatenate([[0.5, -0.3, 0.2], rng.uniform(-10, 10, 2 * n_l)])
    return mu, P


def _observations(rng, mu, js):
    lms = mu[3:].reshape(-1, 2)[js]
    return range_bearing(mu[:3], lms).reshape(-1, 2) + rng.normal(0, [0.1, 0.02], (len(js), 2))


@pytest.mark.parametrize(("n_l", "k", "batch"), [(30, 70, 16), (12, 40, 64), (80, 33, 7), (5, 1, 4)])
def test_chunked_update_is_the_dense_joseph_form_chunk_by_chunk(rng, n_l, k, batch):
    mu, P = _state(rng, n_l)
    js = rng.integers(0, n_l, k)  # repeats included: a landmark seen twice in one chunk
    z = _observations(rng, mu, js)
    mu_ref, P_ref = mu.copy(), P.copy()
    for c in range(0, k, batch):
        mu_ref, P_ref = dense_joseph(mu_ref, P_ref, js[c:c + batch], z[c:c + batch], R)
    mu_new, P_new = mu.copy(), P.copy()
    out_mu, out_P = ekf_update_range_bearing_batches(mu_new, P_new, js, z, R, batch=batch)
    assert out_mu is mu_new and out_P is P_new  # in place
    np.testing.assert_allclose(mu_new, mu_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(P_new, P_ref, rtol=0, atol=1e-9)
    assert np.array_equal(P_new, P_new.T)
    # and the single joint update chained over the chunks (the filter's previous path) to round-off
    mu_c, P_c = mu.copy(), P.copy()
    for c in range(0, k, batch):
        mu_c, P_c = ekf_update_range_bearing_batch(mu_c, P_c, js[c:c + batch], z[c:c + batch], R)
    np.testing.assert_allclose(mu_new, mu_c, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P_new, P_c, rtol=0, atol=1e-12)


def test_chunked_update_on_a_fortran_ordered_p_takes_the_plain_path(rng):
    mu, P = _state(rng, 10)
    js = rng.integers(0, 10, 20)
    z = _observations(rng, mu, js)
    a_mu, a_P = ekf_update_range_bearing_batches(mu.copy(), P.copy(), js, z, R, batch=6)
    b_mu, b_P = ekf_update_range_bearing_batches(mu.copy(), np.asfortranarray(P), js, z, R, batch=6)
    np.testing.assert_allclose(a_mu, b_mu, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a_P, b_P, rtol=0, atol=1e-12)


def test_a_failing_chunk_leaves_a_full_symmetric_p_and_says_how_far_it_got(rng):
    mu, P = _state(rng, 8)
    js = np.array([0, 1, 2, 3, 5, 4])
    z = _observations(rng, mu, js)
    P[13, 16] = P[16, 13] = np.nan  # landmark 5 (second chunk of 3) has a non-finite row: refused before it applies
    mu_ref, P_ref = ekf_update_range_bearing_batch(mu, P, js[:3], z[:3], R)
    with pytest.raises(CovarianceError) as err:
        ekf_update_range_bearing_batches(mu, P, js, z, R, batch=3)
    assert err.value.done == 3 and not err.value.applied
    assert np.array_equal(P, P.T, equal_nan=True)  # the lower triangle was mirrored before the error left
    np.testing.assert_allclose(mu, mu_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-12)


def test_chunked_update_rejects_bad_input(rng):
    mu, P = _state(rng, 3)
    with pytest.raises(IndexError):
        ekf_update_range_bearing_batches(mu, P, [0, 3], np.ones((2, 2)), R, batch=2)
    with pytest.raises(ValueError, match="observation 1"):
        ekf_update_range_bearing_batches(mu, P, [0, 1], np.array([[1.0, 0.0], [np.nan, 0.0]]), R, batch=2)
    with pytest.raises(ValueError, match="batch must be >= 1"):
        ekf_update_range_bearing_batches(mu, P, [0], np.ones((1, 2)), R, batch=0)


@pytest.mark.parametrize("guard", ["raise", "repair"])
def test_estimator_guards_the_chunked_update(guard):
    """P indefinite outside the rows the update reads (as in test_ekf_slam's post-check test): the chunked update
    drives a variance negative, the estimator re-raises or repairs P once and carries on."""
    from slam2d.association import AssociationConfig
    from slam2d.filters.ekf_slam import EKFSLAM, EKFConfig
    from slam2d.log import Observations, Step

    mu = np.array([0.0, 0.0, 0.0, 2.0, 0.0, 5.0, 5.0])
    P = np.eye(7) * 0.1
    P[5, 5] = 1e-6
    P[0, 5] = P[5, 0] = 0.05
    est = EKFSLAM(EKFConfig(confirm_after=1, tentative_max_misses=0, batch_from=0, covariance_guard=guard,
                            association=AssociationConfig(method="known", known_outlier_gate=False)))
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    est._mu, est._P, est._ids = mu.copy(), P.copy(), np.array([0, 1])
    est._tracks.append(2, step=0)
    step = Step(index=1, time_s=0.2, dt_s=0.2, odometry=np.zeros(3),
                observations=Observations(np.array([1.5, 1.6]), np.array([0.0, 0.01]), np.array([0, 0])))
    if guard == "raise":
        with pytest.raises(CovarianceError, match="must be finite and >= 0"):
            est.step(step)
        return
    est.step(step)
    mu2, P2, _ = est.state
    assert est.estimate().diagnostics.covariance_repairs == 1
    assert np.array_equal(P2, P2.T) and np.linalg.eigvalsh(P2)[0] > 0 and np.all(np.isfinite(mu2))
