"""A drone's keyframe edge: the scan match across the track and in heading, the wheel odometry for everything
(fleet.drone.keyframe_edge), checked against a direct least-squares solve of the two measurements."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.fleet.drone import SCAN_SIGMA_ACROSS_M, SCAN_SIGMA_THETA_RAD, keyframe_edge
from slam2d.models.motion import MotionNoise, odometry_covariance


def _rot_end(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("heading", [0.0, 0.7, -2.5])
def test_along_track_comes_from_odometry_alone(heading: float) -> None:
    """The scan match is 50 cm short along the track (a forklift ahead dragged it): the fused edge keeps the
    odometry's along-track position to the numerical precision and the scan's heading almost fully."""
    track = np.array([np.cos(heading), np.sin(heading)])
    z_odo = np.array([*(1.0 * track), 0.02])
    z_scan = np.array([*(0.5 * track), 0.0])
    cov = odometry_covariance(z_odo, MotionNoise())
    z, info = keyframe_edge(z_scan, z_odo, cov)
    along = float(z[:2] @ track) - 1.0  # odometry: 1 m
    # the scan pulls along the track only through the odometry's correlation with heading and across
    assert abs(along) < 0.02
    assert abs(z[2]) < abs(z_odo[2]) * 0.2
    assert np.all(np.linalg.eigvalsh(info) > 0)


def test_equals_least_squares_of_both_measurements() -> None:
    """Fused z and information against an independent solve: stack the two linear measurements of the relative
    pose vector (scan: across + heading rows; odometry: full, whitened by its covariance) and solve."""
    rng = np.random.default_rng(3)
    noise = MotionNoise()
    for _ in range(20):
        z_odo = np.array([rng.uniform(0.5, 1.5), rng.normal(0, 0.1), rng.normal(0, 0.3)])
        z_scan = z_odo + rng.normal(0, [0.3, 0.05, 0.01])
        cov = odometry_covariance(z_odo, noise) + np.diag([1e-6, 1e-6, 1e-8])
        a = np.arctan2(z_odo[1], z_odo[0])
        rows_scan = np.array([[-np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]) / np.array(
            [[SCAN_SIGMA_ACROSS_M], [SCAN_SIGMA_THETA_RAD]])
        w_odo = np.linalg.cholesky(np.linalg.inv(cov)).T
        big_a = np.vstack([rows_scan, w_odo])
        big_b = np.concatenate([rows_scan @ z_scan, w_odo @ z_odo])
        x, *_ = np.linalg.lstsq(big_a, big_b, rcond=None)
        z, info = keyframe_edge(z_scan, z_odo, cov)
        assert np.allclose(z, x, atol=1e-9)
        # information of the vector, rotated into the between factor's end frame
        cov_vec = np.linalg.inv(big_a.T @ big_a)
        r = _rot_end(z[2])
        assert np.allclose(np.linalg.inv(info), r @ cov_vec @ r.T, rtol=1e-6, atol=1e-12)
