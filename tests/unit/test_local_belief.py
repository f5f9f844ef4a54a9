import numpy as np
import pytest

from slam2d.graph.local_belief import LocalBelief


def _random_cov(rng, n):
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def _dense_h(keys, hp, hl, block_keys):
    """H = [Hp | Hl at each landmark's columns] for a block ordered [pose, block_keys...]."""
    m, n = len(keys), 3 + 2 * len(block_keys)
    H = np.zeros((2 * m, n))
    for i, k in enumerate(keys):
        j = list(block_keys).index(k)
        H[2 * i:2 * i + 2, :3] = hp[i]
        H[2 * i:2 * i + 2, 3 + 2 * j:5 + 2 * j] = hl[i]
    return H


def test_update_is_the_dense_kalman_update():
    rng = np.random.default_rng(0)
    keys = np.array([7, 3, 11, 5])
    P = _random_cov(rng, 3 + 2 * keys.size)
    b = LocalBelief()
    b.set(keys, P)
    obs = np.array([11, 7, 5])
    hp, hl, nu = rng.normal(size=(3, 2, 3)), rng.normal(size=(3, 2, 2)), rng.normal(size=(3, 2))
    R = np.array([[0.3, 0.05], [0.05, 0.1]])
    dx = b.update(obs, hp, hl, nu, R)
    H = _dense_h(obs, hp, hl, keys)
    S = H @ P @ H.T + np.kron(np.eye(3), R)
    K = P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(dx, K @ nu.reshape(-1), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b.cov, P - K @ S @ K.T, rtol=1e-10, atol=1e-12)


def test_predict_augment_select_remove_match_the_dense_linear_maps():
    rng = np.random.default_rng(1)
    b = LocalBelief()
    P = _random_cov(rng, 7)
    b.set([4, 9], P)
    G, Q = rng.normal(size=(3, 3)), _random_cov(rng, 3)
    b.predict(G, Q)
    F = np.eye(7)
    F[:3, :3] = G
    P = F @ P @ F.T
    P[:3, :3] += Q
    np.testing.assert_allclose(b.cov, P, rtol=1e-12)
    gp, gz, R = rng.normal(size=(2, 2, 3)), rng.normal(size=(2, 2, 2)), _random_cov(rng, 2)
    b.augment([1, 2], gp, gz, R)
    A = np.zeros((11, 11))  # [x, l4, l9, l1, l2] = A [x, l4, l9, z1, z2]
    A[:7, :7] = np.eye(7)
    A[7:9, :3], A[9:11, :3] = gp
    A[7:9, 7:9], A[9:11, 9:11] = gz
    Pz = np.zeros((11, 11))
    Pz[:7, :7] = P
    Pz[7:9, 7:9] = Pz[9:11, 9:11] = R
    full = A @ Pz @ A.T
    np.testing.assert_allclose(b.cov, full, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(b.rows([2, 4, 8]), [3, 0, -1])
    idx = np.r_[0:3, 9:11, 3:5]
    np.testing.assert_allclose(b.select([2, 4]), full[np.ix_(idx, idx)])
    np.testing.assert_allclose(b.point_covs([9]), full[None, 5:7, 5:7])
    b.remove([9, 123])
    idx = np.r_[0:5, 7:11]
    np.testing.assert_allclose(b.cov, full[np.ix_(idx, idx)])
    np.testing.assert_array_equal(b.keys, [4, 1, 2])
    with pytest.raises(KeyError):
        b.select([9])
