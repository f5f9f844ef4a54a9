"""The odometry factor's information must be the inverse covariance of the between-factor ERROR (g2o EdgeSE2),
which expresses the translation residual in the frame at the end of the motion. Checked by Monte Carlo through the
motion model and the graph's own error function."""

import numpy as np
import pytest

from slam2d.graph.factors import eval_between
from slam2d.models.motion import MotionNoise, odometry_covariance, odometry_factor, sample_odometry


def _whitened_sample_cov(u: np.ndarray, cov: np.ndarray, n: int = 50_000) -> np.ndarray:
    """Sample covariance of the between error of noisy odometry about the true motion, whitened by ``cov``."""
    rng = np.random.default_rng(11)
    measured = sample_odometry(np.broadcast_to(u, (n, 3)), MotionNoise(), rng)
    truth = np.broadcast_to(u, (n, 3)).T.copy()
    e, _ = eval_between(np.zeros((3, n)), truth, measured.T.copy())  # error of the true relative pose
    li = np.linalg.inv(np.linalg.cholesky(cov))
    return li @ np.cov(e) @ li.T


@pytest.mark.parametrize("u", [[1.0, 0.3, 1.2], [0.6, -0.2, -1.0], [0.5, 0.0, 0.1]])
def test_information_matches_monte_carlo_between_error(u):
    u = np.array(u)
    z, info = odometry_factor(u, MotionNoise())
    np.testing.assert_array_equal(z, u)
    w = _whitened_sample_cov(u, np.linalg.inv(info))
    # 50k samples: each whitened entry has a standard error below 0.007; 0.05 leaves room for the linearisation
    np.testing.assert_allclose(w, np.eye(3), atol=0.05)


@pytest.mark.parametrize("u", [[1.0, 0.3, 1.2], [0.6, -0.2, -1.0]])
def test_unrotated_covariance_fails_the_same_check(u):
    """The [dx, dy, dtheta] covariance used as the error covariance is visibly wrong after a turn."""
    w = _whitened_sample_cov(np.array(u), odometry_covariance(u, MotionNoise()))
    assert np.abs(w - np.eye(3)).max() > 0.3


def test_batched_and_floor():
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, size=(4, 5, 3))
    z, info = odometry_factor(u, MotionNoise())
    assert z.shape == (4, 5, 3) and info.shape == (4, 5, 3, 3)
    _, one = odometry_factor(u[2, 3], MotionNoise())
    np.testing.assert_allclose(info[2, 3], one, rtol=1e-12)
    np.testing.assert_allclose(info, np.swapaxes(info, -1, -2), rtol=1e-9)
    # a noise model without a floor: standing still needs floor_var to stay invertible
    still = np.zeros(3)
    silent = MotionNoise(min_trans_std_m=0.0, min_rot_std_rad=0.0)
    _, info0 = odometry_factor(still, silent, floor_var=1e-8)
    np.testing.assert_allclose(info0, np.eye(3) * 1e8, rtol=1e-9)
