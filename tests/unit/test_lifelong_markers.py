"""Surveyed floor markers in the lifelong lidar mode (issue 17): the fix of one step against an independent
minimiser, the survey lookup, and a few simulated minutes of the challenge warehouse with and without markers."""

import numpy as np
import pytest
from scipy.optimize import minimize

from slam2d.config import with_overrides
from slam2d.geometry import se2
from slam2d.graph.lidar import LidarSLAM, LidarSLAMConfig, LifelongLidarConfig
from slam2d.graph.lidar_lifelong import LifelongMarkers, MarkerSurvey, fuse_marker_fixes
from slam2d.log import MarkerReadings, Observations, Scan, Step
from slam2d.maps.layers import LayersConfig
from slam2d.models.floor_markers import marker_in_robot
from slam2d.sim import ScenarioConfig, Simulator
from slam2d.sim.raycast import simulate_scan_culled


def _objective(x, x0, info, z, m, var):
    d = x - x0
    d[2] = np.arctan2(np.sin(d[2]), np.cos(d[2]))
    r = marker_in_robot(x, m) - z
    return float(d @ info @ d + np.sum(r * r) / var)


def test_fix_matches_an_independent_minimiser_of_the_same_objective() -> None:
    rng = np.random.default_rng(1)
    truth = np.array([12.0, -3.0, 0.7])
    m = truth[:2] + rng.uniform(-0.9, 0.9, (3, 2))
    z = marker_in_robot(truth, m) + rng.normal(0, 0.01, (3, 2))
    x0 = truth + np.array([0.12, -0.08, 0.01])
    cov = np.diag([0.05, 0.04, 0.006]) ** 2
    cov[0, 1] = cov[1, 0] = 0.3 * 0.05 * 0.04
    var = 0.014**2
    x, c = fuse_marker_fixes(x0, cov, z, m, var, iterations=10)
    info = np.linalg.inv(cov)
    ref = minimize(_objective, x0, args=(x0, info, z, m, var), method="BFGS", options={"gtol": 1e-10}).x
    assert np.allclose(x, ref, atol=1e-5)
    assert np.hypot(*(x[:2] - truth[:2])) < 0.03  # the markers pulled a 14 cm error to about their noise
    # the returned covariance is the inverse Hessian of the objective / 2 at the optimum (finite differences)
    eps = 1e-4
    h = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            ei, ej = np.eye(3)[i] * eps, np.eye(3)[j] * eps
            h[i, j] = (_objective(x + ei + ej, x0, info, z, m, var) - _objective(x + ei - ej, x0, info, z, m, var)
                       - _objective(x - ei + ej, x0, info, z, m, var)
                       + _objective(x - ei - ej, x0, info, z, m, var)) / (4 * eps**2)
    assert np.allclose(np.linalg.inv(c), h / 2, rtol=2e-2)


def test_fix_with_a_loose_prior_and_exact_readings_lands_on_the_truth_and_a_stiff_prior_holds() -> None:
    truth = np.array([-4.0, 7.5, -2.9])
    m = truth[:2] + np.array([[0.5, 0.2], [-0.3, 0.6]])
    z = marker_in_robot(truth, m)
    guess = truth + np.array([-0.2, 0.15, 0.03])
    x, _ = fuse_marker_fixes(guess, np.eye(3) * 1e6, z, m, 1e-4, iterations=10)
    assert np.allclose(se2.between(truth, x), 0.0, atol=1e-8)
    x, _ = fuse_marker_fixes(guess, np.eye(3) * 1e-12, z, m, 1e-4)
    assert np.allclose(x, guess, atol=1e-6)


def test_survey_lookup_and_bad_surveys() -> None:
    s = MarkerSurvey(((7, 1.0, 2.0), (3, -1.0, 0.5)))
    xy, known = s.lookup(np.array([3, 4, 7, 100]))
    assert known.tolist() == [True, False, True, False]
    assert np.allclose(xy[[0, 2]], [[-1.0, 0.5], [1.0, 2.0]])
    with pytest.raises(ValueError, match="id 3 is listed twice"):
        MarkerSurvey(((3, 0.0, 0.0), (3, 1.0, 1.0)))
    with pytest.raises(ValueError, match="used by the lifelong mode only"):
        LidarSLAMConfig(surveyed_markers=((0, 0.0, 0.0),))


def test_readings_of_markers_outside_the_survey_change_nothing() -> None:
    est = LidarSLAM(LifelongLidarConfig(surveyed_markers=((5, 1.0, 0.0),)))
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    ang = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    scan = Scan(np.full(90, 5.0), ang, 30.0)
    empty = Observations(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    odo = np.array([0.0, 0.0, 0.0])
    est.step(Step(0, 0.0, 0.0, odo, empty, scan=scan, markers=MarkerReadings(np.array([[0.3, 0.0]]),
                                                                                 np.array([9]))))
    assert est.layer_stats().marker_fixes == 0 and np.allclose(est.estimate().pose, 0.0)
    est.step(Step(1, 0.1, 0.1, odo, empty, scan=scan, markers=MarkerReadings(np.array([[0.95, 0.0]]),
                                                                                 np.array([5]))))
    assert est.layer_stats().marker_fixes == 1
    assert est.estimate().pose[0] > 0.02  # the reading says the robot stands 5 cm ahead of the origin


def test_an_unsurveyed_marker_is_mapped_on_its_first_sighting_and_corrects_later_passes() -> None:
    floor = np.diag([0.05, 0.05, 0.005]) ** 2
    lm = LifelongMarkers(MarkerSurvey(((1, 0.0, 0.0),)), map_unsurveyed=True, camera_var=1e-4, survey_var=1e-4,
                         match_floor=floor)
    cov = np.eye(3) * 1e-6
    first = [np.array([10.0, 2.0, 0.3]), np.array([10.1, 2.0, 0.3])]
    mark = np.array([10.5, 2.4])
    for p in first:  # its first sighting: mapped from the poses, the poses untouched
        out, _ = lm.correct(p, cov, [4], marker_in_robot(p, mark)[None])
        assert np.allclose(out, p) and lm.mapped == 0
    lm.correct(first[-1], cov, np.zeros(0, np.int64), np.zeros((0, 2)))  # out of view: frozen
    assert lm.mapped == 1 and lm.fixes == 0
    truth = np.array([10.2, 2.1, 0.25])
    guess = truth + np.array([0.1, -0.05, 0.0])
    z = marker_in_robot(truth, mark)[None]
    out, _ = lm.correct(guess, cov, [4], z)
    ref, _ = fuse_marker_fixes(guess, cov + floor, z, mark[None], 1e-4 + floor[0, 0])
    assert lm.fixes == 1 and np.allclose(out, ref)
    assert np.hypot(*(out[:2] - truth[:2])) < 0.7 * np.hypot(*(guess[:2] - truth[:2]))
    # without mapping an unsurveyed marker is ignored
    plain = LifelongMarkers(MarkerSurvey(()), map_unsurveyed=False, camera_var=1e-4, survey_var=1e-4,
                            match_floor=floor)
    assert np.allclose(plain.correct(guess, cov, [4], z)[0], guess) and plain.mapped == 0


def _shift_p99(markers: bool, steps: int, seed: int) -> tuple[float, int]:
    """Online (unaligned) position error p99 of a lifelong run in the 100 x 100 m warehouse (20 forklifts), the
    first scan taken at the dock (the map's origin), as benchmarks/warehouse_shift.py does."""
    over = {"dt_s": 0.1, "warehouse.floor_markers": markers}
    sim = Simulator(with_overrides(ScenarioConfig(name="warehouse-challenge"), over), seed=seed, record=False)
    truth = sim.world.floor_markers + np.random.default_rng(seed).normal(0.0, 0.01, sim.world.floor_markers.shape)
    survey = tuple((i, float(x), float(y)) for i, (x, y) in enumerate(truth.tolist()))
    est = LidarSLAM(LidarSLAMConfig(layers=LayersConfig(), loop_closure=False, surveyed_markers=survey))
    est.reset(sim.pose, rng=np.random.default_rng(seed))
    lidar = sim.config.lidar
    ranges = simulate_scan_culled(sim.pose, sim.world.segments_near(0.0, sim.pose[:2], lidar.max_range_m), lidar,
                                  sim.rng["lidar"])
    empty = Observations(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    est.step(Step(0, 0.0, 0.0, np.zeros(3), empty, scan=Scan(ranges, lidar.angles(), lidar.max_range_m)))
    driver = sim.driver()
    err = np.zeros(steps)
    for i in range(steps):
        est.step(sim.step(*driver.command(sim.pose, None)))
        err[i] = np.hypot(*(est.estimate().pose[:2] - sim.pose[:2]))
    return float(np.percentile(err, 99)), est.layer_stats().marker_fixes


@pytest.mark.slow
def test_surveyed_markers_hold_a_few_shift_minutes_within_the_target() -> None:
    # measured at seed 1, 3 simulated minutes (2026-12-05, HEAD 1619d9a): 5.3 cm with surveyed markers, 15.9 cm
    # without (seed 3: 4.3 / 16.8 cm; seed 2 drifts more, 7.3 / 91.4 cm); an earlier estimator gave 4.1 / 12.8 cm
    on, fixes = _shift_p99(True, 1800, seed=1)
    off, none = _shift_p99(False, 1800, seed=1)
    assert fixes > 100 and none == 0
    assert on < 0.07
    assert on < 0.5 * off
