"""Range-only EKF-SLAM: delayed beacon placement, gated scalar updates, Monte-Carlo consistency, Plaza."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import slam2d
from slam2d.eval.consistency import monte_carlo_consistency, online_pose_nees
from slam2d.filters.range_only_ekf import RangeOnlyEKF, RangeOnlyEKFConfig
from slam2d.geometry.trilateration import refine_point, trilaterate
from slam2d.lab.registry import make_config
from slam2d.log import Log, Observations, Step
from slam2d.models.sensors import SensorConfig
from slam2d.sim.simulator import simulate
from testkit import dataset_path


def test_refine_point_is_exact_without_noise_and_beats_the_linear_fit_with_noise():
    rng = np.random.default_rng(3)
    target = np.array([4.0, -2.0])
    p = rng.uniform(-10, 10, size=(30, 2))
    r = np.hypot(*(p - target).T)
    x, cov = refine_point(p, r, trilaterate(p, r) + 1.0)
    np.testing.assert_allclose(x, target, atol=1e-9)
    assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) > 0)
    lin, ml = [], []
    for _ in range(200):
        rn = r + rng.normal(0, 0.5, r.size)
        start = trilaterate(p, rn)
        lin.append(np.hypot(*(start - target)))
        ml.append(np.hypot(*(refine_point(p, rn, start)[0] - target)))
    assert np.mean(np.square(ml)) < np.mean(np.square(lin))


def _steps(ranges: list[tuple[int, float]], u=(0.0, 0.0, 0.0)) -> Step:
    ids = np.array([b for b, _ in ranges], dtype=np.int64)
    r = np.array([x for _, x in ranges])
    obs = Observations(range_m=r, bearing_rad=np.full(r.size, np.nan), landmark_id=ids)
    return Step(index=0, time_s=0.0, dt_s=0.1, odometry=np.asarray(u, dtype=float), observations=obs)


def test_beacon_is_placed_after_enough_spread_ranges_and_outliers_are_gated():
    cfg = RangeOnlyEKFConfig(sensor=SensorConfig(range_std_m=0.05), init_min_ranges=10, init_min_spread_m=1.0)
    est = RangeOnlyEKF(cfg)
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    beacon = np.array([5.0, 3.0])
    pose = np.zeros(3)
    for k in range(40):  # drive a circle of radius 3 around the origin, ranging the beacon each step
        ang = 2 * np.pi * (k + 1) / 40
        new = np.array([3 * np.sin(ang), 3 - 3 * np.cos(ang), ang])
        u = slam2d.geometry.between(pose, new)
        pose = new
        est.step(_steps([(7, float(np.hypot(*(beacon - pose[:2]))))], u))
    snap = est.estimate()
    assert snap.landmark_ids.tolist() == [7]
    np.testing.assert_allclose(snap.landmarks[0], beacon, atol=0.05)
    # the new beacon is correlated with the robot (it was placed relative to the robot's path)
    mu, P = est._mu, est._P
    assert np.abs(P[:3, 3:]).max() > 0 and mu.shape == (5,)
    before = est.estimate()
    est.step(_steps([(7, 50.0)]))  # 45 m off: a multipath outlier
    after = est.estimate()
    assert after.diagnostics.range_outliers == 1
    np.testing.assert_allclose(after.landmarks, before.landmarks)
    np.testing.assert_allclose(after.pose, before.pose)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="init_min_ranges"):
        RangeOnlyEKFConfig(init_min_ranges=2)
    with pytest.raises(ValueError, match="gate_probability"):
        RangeOnlyEKFConfig(gate_probability=1.0)


def test_range_only_ekf_beats_dead_reckoning_on_a_simulated_loop():
    for seed in range(3):
        log = simulate("loop", seed, landmarks=8, **{"sensor.max_range_m": 60.0})
        _, ro = slam2d.run_named("range-only-ekf", log=log, seed=seed)
        _, dr = slam2d.run_named("dead-reckoning", log=log, seed=seed)
        assert ro["ate_rmse_m"] < 0.65 * dr["ate_rmse_m"], (seed, ro["ate_rmse_m"], dr["ate_rmse_m"])


def _pose_nees(logs: list[Log], motion_scale: float, steps: int) -> np.ndarray:
    """Pose NEES (runs, steps) of the range-only EKF with its motion noise scaled by ``motion_scale`` over the first
    ``steps`` steps of each log (run r seeded with r)."""
    def ekf(log: Log) -> RangeOnlyEKF:
        cfg = make_config("range-only-ekf", None, log.metadata)
        return RangeOnlyEKF(dataclasses.replace(cfg, motion=cfg.motion.scaled(motion_scale)))
    return np.stack([online_pose_nees(ekf(log), log, np.random.default_rng(r), steps) for r, log in enumerate(logs)])


#: the overconfident filter fails over the first 40 steps of the same 30 runs by a wide margin. Measured, 30 runs x
#: 40 steps on seeds 0-29, 30-59 and 60-89: 0 % of steps inside the band, mean NEES 26.9 or more (the check below
#: needs < 50 % and > 10), while the honest filter on those prefixes has 97-100 % inside (mean 2.7-3.0)
#: (regenerate: PYTHONPATH=src python benchmarks/nees_power.py band|overconfident|range-only)
RO_SEEDS, RO_STEPS, RO_POWER_STEPS = 30, 150, 40


@pytest.mark.slow
def test_range_only_ekf_is_consistent_and_an_overconfident_one_is_not():
    """30 runs x 150 steps of the room, ~11 beacons placed per run (measured: 100 % of steps inside the band); the
    overconfident filter (motion noise x0.1) runs on the first RO_POWER_STEPS steps of the same simulated logs."""
    logs = [simulate("room", r, steps=RO_STEPS) for r in range(RO_SEEDS)]
    good = monte_carlo_consistency(_pose_nees(logs, 1.0, RO_STEPS), 3)
    assert good.fraction_inside >= 0.9 and 2.0 < good.overall_mean < 4.0, good.overall_mean
    bad = monte_carlo_consistency(_pose_nees(logs, 0.1, RO_POWER_STEPS), 3)
    assert bad.fraction_inside < 0.5 and bad.overall_mean > 10.0


@pytest.mark.slow
def test_plaza_range_only_ekf_beats_dead_reckoning():
    dataset_path("plaza-range-only")
    from slam2d.io.datasets import load_dataset

    for name in ("plaza1", "plaza2"):
        log = load_dataset(name)
        _, dr = slam2d.run_named("dead-reckoning", log=log)
        _, ro = slam2d.run_named("range-only-ekf", log=log)
        assert ro["ate_rmse_m"] < 0.9 * dr["ate_rmse_m"], (name, ro["ate_rmse_m"], dr["ate_rmse_m"])
        assert ro["landmarks_estimated"] == 4
