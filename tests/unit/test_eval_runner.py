import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import slam2d
from slam2d.eval import align_se2, ate, rpe
from slam2d.geometry import compose


def test_ate_is_zero_after_aligning_a_moved_copy(rng):
    traj = np.cumsum(rng.normal(size=(100, 3)), axis=0)
    moved = compose(np.array([3.0, -7.0, 2.1]), traj)
    res = ate(moved, traj)
    assert res.rmse_m < 1e-9
    np.testing.assert_allclose(compose(res.alignment, np.array([0.0, 0.0, 0.0]))[:2],
                               align_se2(moved, traj)[:2])
    assert ate(moved, traj, align=False).rmse_m > 1.0


def test_rpe_of_identical_trajectories_is_zero_and_detects_a_kink(rng):
    traj = np.cumsum(rng.normal(size=(50, 3)), axis=0)
    r = rpe(traj, traj)
    assert r.trans_rmse_m == 0 and r.rot_rmse_rad == 0
    bent = traj.copy()
    bent[30, 2] += 0.2  # one heading off by 0.2 rad: two relative poses see it
    r = rpe(bent, traj)
    assert np.count_nonzero(r.rot_errors_rad > 1e-12) == 2
    assert r.rot_errors_rad.max() == pytest.approx(0.2)


def test_dead_reckoning_drift_grows_with_motion_noise():
    ates = []
    for scale in [0.25, 1.0, 4.0]:
        vals = []
        for seed in range(4):
            _, rec = slam2d.run_named("dead-reckoning", "loop", seed=seed, overrides={
                "motion.alpha_rot_rot": 0.0025 * scale, "motion.alpha_rot_trans": 0.0004 * scale,
                "motion.alpha_trans_trans": 0.0025 * scale})
            vals.append(rec["ate_rmse_m"])
        ates.append(np.mean(vals))
    assert ates[0] < ates[1] < ates[2], ates


def test_runner_records_history_and_metrics():
    log = slam2d.simulate("room", seed=0, steps=30)
    est = slam2d.make_estimator("dead-reckoning", log_metadata=log.metadata)
    res = slam2d.run(est, log, rng=np.random.default_rng(0), keep_snapshots=True)
    assert res.poses.shape == (31, 3) and res.pose_covs.shape == (31, 3, 3)
    assert len(res.snapshots) == 30
    for k in ["ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_rad", "steps", "step_ms_mean", "landmarks_estimated"]:
        assert k in res.metrics
    # position uncertainty grows monotonically while only odometry is used
    tr = np.trace(res.pose_covs[:, :2, :2], axis1=1, axis2=2)
    assert np.all(np.diff(tr) >= -1e-15)


def test_dead_reckoning_covariance_is_consistent():
    """Average NEES of the dead-reckoning pose over Monte-Carlo seeds stays in the chi-square band."""
    from scipy import stats

    n_runs, steps = 40, 60
    nees = np.zeros(steps)
    for seed in range(n_runs):
        log = slam2d.simulate("room", seed=seed, steps=steps)
        est = slam2d.make_estimator("dead-reckoning", log_metadata=log.metadata)
        res = slam2d.run(est, log, rng=np.random.default_rng(seed))
        err = res.poses[1:] - log.true_poses[1:]
        err[:, 2] = slam2d.geometry.angle_diff(res.poses[1:, 2], log.true_poses[1:, 2])
        nees += np.einsum("ti,tij,tj->t", err, np.linalg.inv(res.pose_covs[1:]), err)
    nees /= n_runs
    lo, hi = stats.chi2.ppf([0.025, 0.975], 3 * n_runs) / n_runs
    frac = np.mean((nees > lo) & (nees < hi))
    assert frac > 0.85, (frac, nees.mean())


def test_unknown_names_list_the_valid_ones():
    with pytest.raises(ValueError, match="valid estimators.*dead-reckoning"):
        slam2d.run_named("nope")


def test_run_association_scores_exact_case():
    from slam2d.eval.association import run_association_scores

    # estimator ids 7 and 9 stand for true landmarks 0 and 1; step 2 swaps one match
    assign = [np.array([-1, -1]), np.array([7, 9]), np.array([9, 9, -2])]
    truth = [np.array([0, 1]), np.array([0, 1]), np.array([0, 1, -1])]
    s = run_association_scores(assign, truth)
    assert s["assoc_precision"] == pytest.approx(3 / 4)  # 4 matches, the (9 for true 0) one is wrong
    assert s["assoc_recall"] == pytest.approx(3 / 4)  # 4 matchable observations (steps 1, 2), 3 correct


def test_run_cli_association_option_reaches_the_estimator(tmp_path):
    import json

    from slam2d.cli.main import main

    out = tmp_path / "r.json"
    assert main(["run", "--scenario", "room", "--estimator", "ekf", "--association", "mahalanobis",
                 "--set", "steps=60", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["estimator_config"]["association"]["method"] == "mahalanobis"
    assert 0.9 < rec["assoc_precision"] <= 1.0 and 0.9 < rec["assoc_recall"] <= 1.0
@settings(max_examples=25)
@given(tx=st.floats(-100, 100), ty=st.floats(-100, 100), th=st.floats(-np.pi, np.pi), seed=st.integers(0, 2**31))
def test_ate_and_rpe_are_blind_to_any_rigid_motion_of_the_estimate(tx, ty, th, seed):
    traj = np.cumsum(np.random.default_rng(seed).normal(size=(40, 3)), axis=0)
    moved = compose(np.array([tx, ty, th]), traj)
    assert ate(moved, traj).rmse_m < 1e-8
    # the recovered alignment is the inverse of the applied motion
    np.testing.assert_allclose(compose(ate(moved, traj).alignment, np.array([tx, ty, th])), [0, 0, 0], atol=1e-8)
    r = rpe(moved, traj, delta=3)
    assert r.trans_rmse_m < 1e-8 and r.rot_rmse_rad < 1e-8


def test_a_log_without_the_back_ends_input_is_refused_not_dead_reckoned() -> None:
    import dataclasses

    from slam2d.lab.runner import run_named
    from slam2d.sim import ScenarioConfig, simulate

    with pytest.raises(ValueError, match="'lidar' needs lidar scans; grid has none"):
        run_named("lidar", "grid", overrides={"steps": 20})
    log = simulate(ScenarioConfig(name="room", steps=30), 0)
    assert log.scan_step is not None and len(log.scan_step)
    ranges_only = dataclasses.replace(log, obs_bearing_rad=np.full_like(log.obs_bearing_rad, np.nan))
    for name in ("ekf", "fastslam", "graph"):
        with pytest.raises(ValueError, match=f"'{name}' needs landmark bearings; room's observations are ranges only"):
            run_named(name, log=ranges_only)
    # a lidar log without any landmark observation (a CARMEN log): every landmark back end is refused
    scans_only = dataclasses.replace(log, obs_step=log.obs_step[:0], obs_range_m=log.obs_range_m[:0],
                                     obs_bearing_rad=log.obs_bearing_rad[:0], obs_id=log.obs_id[:0])
    for name in ("ekf", "graph", "range-only-ekf", "range-only-graph"):
        with pytest.raises(ValueError, match=f"'{name}' needs landmark observations; room is a lidar log without"):
            run_named(name, log=scans_only)
    # the same logs serve the back ends that measure with what they have
    assert run_named("range-only-ekf", log=ranges_only)[1]["steps"] == 30
    assert run_named("lidar", log=log)[1]["steps"] == 30
    assert run_named("dead-reckoning", log=scans_only)[1]["steps"] == 30
