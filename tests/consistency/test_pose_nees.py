"""Monte-Carlo consistency of the robot-pose covariance each back end reports (known association, short runs).

For every back end and scenario: over SEEDS independent simulations, the average pose NEES ``e^T P^-1 e`` per step
must lie inside the two-sided 95% chi-square band (3 dof) on at least 90% of the steps -- and the same back end
with its assumed motion noise shrunk x0.1 (an overconfident filter) must FAIL that check, so the test has power.

What "P" is: EKF-SLAM's pose block; online graph SLAM's ``pose_cov`` (the newest pose's marginal from the last
factorisation, propagated through the odometry since); FastSLAM 2.0's weighted particle covariance before
resampling.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from slam2d.eval.consistency import ConsistencySummary, monte_carlo_consistency, pose_error
from slam2d.lab.registry import make_estimator
from slam2d.log import Log
from slam2d.sim.simulator import simulate

SEEDS = 30
STEPS = 200
POWER_STEPS = 100  # the shrunk-noise runs fail by a wide margin; half the steps keep CI short

#: the config change that shrinks each back end's assumed motion noise x0.1 (graph SLAM: odometry information x10)
OVERCONFIDENT: dict[str, dict[str, Any]] = {
    "ekf": {"motion_noise_scale": 0.1},
    "graph": {"odometry_info_scale": 10.0},
    "fastslam2": {"motion_noise_scale": 0.1},
}


@pytest.fixture(scope="module", params=["room", "loop"])
def logs(request: pytest.FixtureRequest) -> list[Log]:
    return [simulate(request.param, seed, steps=STEPS) for seed in range(SEEDS)]


def pose_nees(name: str, logs: list[Log], overrides: dict[str, Any], steps: int = STEPS) -> ConsistencySummary:
    """Monte-Carlo pose NEES of estimator ``name`` over ``logs`` (first ``steps`` steps of each)."""
    values = np.full((len(logs), steps), np.nan)
    for r, log in enumerate(logs):
        est = make_estimator(name, overrides, log.metadata)
        est.reset(log.initial_pose, rng=np.random.default_rng(1000 + r))
        for t, step in enumerate(log.head(steps)):
            est.step(step)
            snap = est.estimate()
            assert snap.pose_cov is not None
            e = pose_error(snap.pose, log.true_poses[t + 1])
            values[r, t] = e @ np.linalg.solve(snap.pose_cov, e)
    return monte_carlo_consistency(values, dof=3)


def _describe(s: ConsistencySummary) -> str:
    return (f"{s.fraction_inside:.0%} of steps inside [{s.band.low:.2f}, {s.band.high:.2f}], "
            f"mean NEES {s.overall_mean:.2f}")


#: FastSLAM 2.0 (100 particles) is overconfident: its particle cloud is the whole of its pose belief, and
#: resampling makes the particles' paths, hence their maps, coalesce onto a few ancestors, so the spread of the cloud
#: stops growing with the map's drift while the error does (Bailey, Nieto & Nebot, "Consistency of the FastSLAM
#: algorithm", ICRA 2006). Measured here: mean NEES 145 (room) and 577 (loop), 6% / 4% of steps inside the band;
#: the final particles of a room run have 43 distinct ancestors 5 steps back, 8 at 20 and 1.4 at 80 (5 seeds);
#: more particles only delay it (room, 10 seeds, 120 steps: 100 particles mean NEES 232, 1000 particles 48, in the
#: band for the first 30 steps only). Not the cause (checked): the proposal and the weight (with H_x P H_x^T) match
#: a brute-force posterior (tests/unit/test_fastslam.py); over the first 15 steps (30 seeds) 1000 particles give mean
#: NEES 2.96 room / 3.06 loop, as the EKF (2.89 / 3.11), 100 particles 3.44 / 3.87; the Rao-Blackwellised mixture
#: covariance sum_i w_i (P_i + d_i d_i^T) of the proposals before the draw changes little (10 seeds x 100 steps: mean
#: NEES 10.2 against 10.7 room, 22.3 against 23.0 loop); nor does the resampling threshold (same runs, room / loop:
#: resampling every step 17.4 / 10.5, never 2816 / 1296). strict: a fix shows up as a failure of this marker.
FASTSLAM_DEGENERATES = pytest.mark.xfail(strict=True, reason="FastSLAM's particle paths coalesce (see comment)")


#: the known failure is confirmed on part of the shared logs (10 seeds x 100 steps: 15 % / 7 % of steps inside, mean
#: NEES 10.7 / 23.0), which saves CI time; a fix still shows as XPASS(strict) -- then drop the marker and this cut
DEGENERATE_SEEDS, DEGENERATE_STEPS = 10, 100


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ekf", "graph", pytest.param("fastslam2", marks=FASTSLAM_DEGENERATES)])
def test_pose_nees_inside_the_chi2_band(name, logs):
    if name == "fastslam2":
        s = pose_nees(name, logs[:DEGENERATE_SEEDS], {}, steps=DEGENERATE_STEPS)
    else:
        s = pose_nees(name, logs, {})
    print(f"{name} {logs[0].metadata.get('scenario', '')}: {_describe(s)}")
    assert s.fraction_inside >= 0.9, f"{name}: {_describe(s)}"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ekf", "graph", "fastslam2"])
def test_overconfident_noise_fails_the_same_check(name, logs):
    s = pose_nees(name, logs, OVERCONFIDENT[name], steps=POWER_STEPS)
    print(f"{name} {logs[0].metadata.get('scenario', '')} overconfident: {_describe(s)}")
    assert s.fraction_inside < 0.9, f"{name}: {_describe(s)}"
    assert s.overall_mean > s.band.high
