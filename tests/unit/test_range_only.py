import numpy as np
import pytest

import slam2d
from slam2d.graph.range_only import RangeOnlyConfig, range_only_slam, trilaterate
from testkit import dataset_path


def test_trilateration_is_exact_without_noise():
    rng = np.random.default_rng(0)
    target = np.array([3.0, -4.0])
    p = rng.uniform(-20, 20, size=(6, 2))
    np.testing.assert_allclose(trilaterate(p, np.hypot(*(p - target).T)), target, atol=1e-9)
    with pytest.raises(ValueError, match=">= 3"):
        trilaterate(p[:2], np.ones(2))


def test_range_only_slam_beats_dead_reckoning_on_a_simulated_loop():
    log = slam2d.simulate("loop", seed=2, landmarks=8, **{"sensor.max_range_m": 60.0})
    res = range_only_slam(log, RangeOnlyConfig(motion=slam2d.ScenarioConfig().motion, range_std_m=0.1))
    dr = slam2d.ate(res.dead_reckoning, log.true_poses).rmse_m
    ro = slam2d.ate(res.trajectory, log.true_poses).rmse_m
    assert ro < 0.3 * dr, (ro, dr)


@pytest.mark.slow
def test_plaza_range_only_graph_beats_dead_reckoning():
    dataset_path("plaza-range-only")
    for name in ("plaza1", "plaza2"):
        _, dr = slam2d.run_named("dead-reckoning", log=_load(name))
        _, ro = slam2d.run_named("range-only-graph", log=_load(name))
        assert ro["ate_rmse_m"] < 0.9 * dr["ate_rmse_m"], (name, ro["ate_rmse_m"], dr["ate_rmse_m"])


def _load(name):
    from slam2d.io.datasets import load_dataset

    return load_dataset(name)


def test_beacons_with_too_few_ranges_are_left_out():
    log = slam2d.simulate("grid", seed=0, steps=3, landmarks=20)
    res = range_only_slam(log, RangeOnlyConfig(range_std_m=0.1))
    counts = np.bincount(log.obs_id[log.obs_id >= 0])
    assert set(res.beacon_ids.tolist()) == set(np.flatnonzero(counts >= 3).tolist())


def test_standstill_steps_do_not_break_the_solve():
    """A standstill's odometry covariance is zero (MRCLAM logs many; the solve raised "Singular matrix"): its factor
    gets a floor. Here three readings say "no motion" (zeroed), and the solve still beats dead reckoning."""
    import dataclasses

    log = slam2d.simulate("loop", seed=2, landmarks=8, steps=120, **{"sensor.max_range_m": 60.0})
    odo = log.odometry.copy()
    odo[[30, 31, 80]] = 0.0
    res = range_only_slam(dataclasses.replace(log, odometry=odo),
                          RangeOnlyConfig(motion=slam2d.ScenarioConfig().motion, range_std_m=0.1))
    assert np.all(np.isfinite(res.trajectory))
    ro, dr = (slam2d.ate(t, log.true_poses).rmse_m for t in (res.trajectory, res.dead_reckoning))
    assert ro < 0.5 * dr, (ro, dr)
