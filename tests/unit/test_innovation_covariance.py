"""The one builder of innovation covariances against the textbook formula with H formed explicitly."""

import numpy as np
import pytest

from slam2d.association.predict import innovation_covariance, joint_innovation_covariance


def _dense_reference(hp, hl, cov, rows, r):
    n_l, m = hp.shape[:2]
    H = np.zeros((n_l * m, cov.shape[0]))
    for i in range(n_l):
        H[i * m:(i + 1) * m, :3] = hp[i]
        if rows is not None:
            H[i * m:(i + 1) * m, rows[i]] = hl[i]
    return H @ cov @ H.T + np.kron(np.eye(n_l), r)


@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("known_map", [False, True])
def test_matches_dense_h_p_ht(m, known_map):
    rng = np.random.default_rng(4)
    n_state, n_l = 3 + 2 * 9, 4
    a = rng.standard_normal((n_state, n_state))
    cov = a @ a.T + 0.1 * np.eye(n_state)
    # four of the nine landmarks, in scrambled order: the builder must read only their rows
    rows = None if known_map else 3 + 2 * np.array([7, 2, 5, 0])[:, None] + np.arange(2)
    hp, hl = rng.standard_normal((n_l, m, 3)), rng.standard_normal((n_l, m, 2))
    b = rng.standard_normal((m, m))
    r = b @ b.T + 0.01 * np.eye(m)
    ref = _dense_reference(hp, hl, cov, rows, r)
    s, sj = joint_innovation_covariance(hp, hl, cov, rows, r)
    np.testing.assert_allclose(sj, ref, rtol=1e-10, atol=1e-10)
    blocks = np.stack([ref[i * m:(i + 1) * m, i * m:(i + 1) * m] for i in range(n_l)])
    np.testing.assert_allclose(s, blocks, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(innovation_covariance(hp, hl, cov, rows, r), blocks, rtol=1e-10, atol=1e-10)


def test_no_candidates():
    s, sj = joint_innovation_covariance(np.zeros((0, 2, 3)), np.zeros((0, 2, 2)), np.eye(3), np.zeros((0, 2)),
                                        np.eye(2))
    assert s.shape == (0, 2, 2) and sj.shape == (0, 0)
