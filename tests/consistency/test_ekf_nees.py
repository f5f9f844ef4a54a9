"""Monte-Carlo consistency of EKF-SLAM (known association, short runs): the average robot-pose NEES over seeds
stays inside the two-sided 95% chi-square band, and an overconfident filter (motion noise x 0.1) does not."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from slam2d.filters.ekf_slam import EKFSLAM
from slam2d.geometry.angles import angle_diff
from slam2d.lab.registry import make_config
from slam2d.log import Log
from slam2d.sim.simulator import simulate

SEEDS = 40
STEPS = 60


@pytest.fixture(scope="module")
def logs() -> list[Log]:
    return [simulate("room", seed, steps=STEPS) for seed in range(SEEDS)]


def average_pose_nees(logs: list[Log], motion_noise_scale: float) -> np.ndarray:
    """Average over runs of e^T P^-1 e for the robot pose at steps 1..T (heading error through angle_diff)."""
    nees = np.zeros((len(logs), STEPS))
    for r, log in enumerate(logs):
        est = EKFSLAM(make_config("ekf", {"motion_noise_scale": motion_noise_scale}, log.metadata))
        est.reset(log.initial_pose, rng=np.random.default_rng(r))
        for t, step in enumerate(log):
            est.step(step)
            snap = est.estimate()
            assert snap.pose_cov is not None
            truth = log.true_poses[t + 1]
            e = np.array([*(snap.pose[:2] - truth[:2]), angle_diff(snap.pose[2], truth[2])])
            nees[r, t] = e @ np.linalg.solve(snap.pose_cov, e)
    return nees.mean(axis=0)


def fraction_inside_band(avg: np.ndarray, runs: int, dof: int = 3) -> float:
    lo, hi = stats.chi2.ppf([0.025, 0.975], dof * runs) / runs
    return float(np.mean((avg >= lo) & (avg <= hi)))


@pytest.mark.slow
def test_average_pose_nees_inside_chi2_band(logs):
    avg = average_pose_nees(logs, 1.0)
    frac = fraction_inside_band(avg, SEEDS)
    assert frac >= 0.9, f"only {frac:.0%} of steps inside the band; mean NEES {avg.mean():.2f}"
    assert 2.0 < avg.mean() < 4.0  # dof 3


@pytest.mark.slow
def test_overconfident_filter_fails_the_same_check(logs):
    avg = average_pose_nees(logs, 0.1)
    assert fraction_inside_band(avg, SEEDS) < 0.9
    assert avg.mean() > 6.0
