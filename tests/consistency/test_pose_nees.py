"""Monte-Carlo consistency of the robot-pose covariance each back end reports (known association, short runs).

For every back end and scenario: over RUNS[name] independent simulations, the average pose NEES ``e^T P^-1 e`` per step
must lie inside the two-sided 95% chi-square band (3 dof) on at least 90% of the steps -- and the same back end
with its assumed motion noise shrunk x0.1 (an overconfident filter) must FAIL that check, so the test has power.

What "P" is: EKF-SLAM's pose block; online graph SLAM's ``pose_cov`` (the newest pose's marginal from the last
factorisation, propagated through the odometry since); FastSLAM 2.0's ``pose_cov="linearised"`` covariance (the
EKF-SLAM covariance recursion linearised at FastSLAM's own estimate, plus the part of it the particle cloud no longer
spans) -- its default, the weighted particle covariance, is overconfident (the fast test below shows both).

`make test` runs graph SLAM on the loop scenario and the fast FastSLAM 2.0 test (EKF-SLAM's pose NEES and its
overconfident twin are in ``test_ekf_nees.py``); the room scenario, EKF-SLAM and FastSLAM 2.0's 30-run checks here
(about 360 s of the 450 s this file takes on the CI machine) run with SLAM2D_LONG_TESTS=1 (``testkit.LONG``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from slam2d.eval.consistency import ConsistencySummary, monte_carlo_consistency, online_pose_nees
from slam2d.lab.registry import make_estimator
from slam2d.log import Log
from slam2d.sim.simulator import simulate
from testkit import LONG

SEEDS = 30
STEPS = 200
#: Monte-Carlo runs per back end (the first RUNS[name] of the SEEDS logs). EKF-SLAM and graph SLAM keep their power
#: with 20. Measured, 60 runs x 200 steps in three disjoint 20-run sets, both scenarios: the honest filters have
#: 96-100 % of steps inside the 20-run band, while a mildly overconfident one (motion variances x0.5 / odometry
#: information x2, five times milder than OVERCONFIDENT) has 18-66 % inside (the test needs 90 %). FastSLAM 2.0 keeps
#: 30: with 20 that mild variant passed on one set of three (loop, 93 % inside; 84 % and 52 % in the two 30-run sets)
#: and the honest filter failed on one (room, 84 %).
#: (regenerate: PYTHONPATH=src python benchmarks/nees_power.py band|overconfident|range-only)
RUNS = {"ekf": 20, "graph": 20, "fastslam2": SEEDS}
#: the shrunk-noise runs fail the same check (same runs, same band) by a wide margin on their first 40 steps.
#: Measured, 40 steps on seeds 0-89, each back end and scenario: 0 % of steps inside the band and a mean NEES of 14.1
#: or more (3.6 x the band's top or more) in each 30-run set, 16.0 or more (3.9 x) for EKF and graph SLAM in each
#: 20-run set; the honest back ends' means over those prefixes (seeds 30-89) are 2.4-3.3, under the top, so they never
#: satisfy this test's two assertions
POWER_STEPS = 40

#: FastSLAM's particle spread is overconfident once the particles' paths coalesce (Bailey, Nieto & Nebot, "Consistency
#: of the FastSLAM algorithm", ICRA 2006: measured here, 30 seeds x 200 steps, mean NEES 69 room / 449 loop, 6 % / 4 %
#: of steps inside); what is tested is the covariance it reports with pose_cov="linearised" (EKF-SLAM's covariance
#: recursion at FastSLAM's own estimate plus what the particle cloud misses, slam2d.filters.fastslam_marginal)
REPORTED: dict[str, dict[str, Any]] = {"fastslam2": {"pose_cov": "linearised"}}
SHORT_SEEDS, SHORT_STEPS = 10, 100

#: the config change that shrinks each back end's assumed motion noise x0.1 (graph SLAM: odometry information x10)
OVERCONFIDENT: dict[str, dict[str, Any]] = {
    "ekf": {"motion_noise_scale": 0.1},
    "graph": {"odometry_info_scale": 10.0},
    "fastslam2": {"motion_noise_scale": 0.1},
}


@pytest.fixture(scope="module", params=[pytest.param("room", marks=LONG), "loop"])
def logs(request: pytest.FixtureRequest) -> list[Log]:
    return [simulate(request.param, seed, steps=STEPS) for seed in range(SEEDS)]


def pose_nees(name: str, logs: list[Log], overrides: dict[str, Any], steps: int = STEPS) -> ConsistencySummary:
    """Monte-Carlo pose NEES of estimator ``name`` over ``logs`` (first ``steps`` steps of each)."""
    values = np.stack([online_pose_nees(make_estimator(name, overrides, log.metadata), log,
                                        np.random.default_rng(1000 + r), steps) for r, log in enumerate(logs)])
    return monte_carlo_consistency(values, dof=3)


def _describe(s: ConsistencySummary) -> str:
    return (f"{s.fraction_inside:.0%} of steps inside [{s.band.low:.2f}, {s.band.high:.2f}], "
            f"mean NEES {s.overall_mean:.2f}")


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param("ekf", marks=LONG), "graph", pytest.param("fastslam2", marks=LONG)])
def test_pose_nees_inside_the_chi2_band(name, logs):
    s = pose_nees(name, logs[:RUNS[name]], REPORTED.get(name, {}))
    print(f"{name} {logs[0].metadata.get('scenario', '')}: {_describe(s)}")
    assert s.fraction_inside >= 0.9, f"{name}: {_describe(s)}"


def test_fastslam2_particle_covariance_is_overconfident_and_the_linearised_one_is_not():
    """Fast version (10 seeds x 100 steps, loop): the particle spread fails the band, the linearised covariance
    passes it (the 10-seed band is wider than the 30-seed one)."""
    short = [simulate("loop", seed, steps=SHORT_STEPS) for seed in range(SHORT_SEEDS)]
    cloud = pose_nees("fastslam2", short, {}, steps=SHORT_STEPS)
    honest = pose_nees("fastslam2", short, REPORTED["fastslam2"], steps=SHORT_STEPS)
    print(f"fastslam2 loop, particles: {_describe(cloud)}; linearised: {_describe(honest)}")
    assert cloud.fraction_inside < 0.5 and cloud.overall_mean > 2 * cloud.band.high, _describe(cloud)
    assert honest.fraction_inside >= 0.9, _describe(honest)


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param("ekf", marks=LONG), "graph", pytest.param("fastslam2", marks=LONG)])
def test_overconfident_noise_fails_the_same_check(name, logs):
    s = pose_nees(name, logs[:RUNS[name]], {**REPORTED.get(name, {}), **OVERCONFIDENT[name]}, steps=POWER_STEPS)
    print(f"{name} {logs[0].metadata.get('scenario', '')} overconfident: {_describe(s)}")
    assert s.fraction_inside < 0.9, f"{name}: {_describe(s)}"
    assert s.overall_mean > s.band.high
