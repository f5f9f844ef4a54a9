"""Bad input through the Python API: a clear ValueError naming the field, never a silent wrong answer or a NaN."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.eval.association import run_association_scores
from slam2d.eval.mapping import map_error
from slam2d.eval.trajectory import align_se2, ate, rpe
from slam2d.geometry import se2
from slam2d.geometry.gaussian import chi2_gate
from slam2d.geometry.trilateration import trilaterate
from slam2d.graph import FactorGraph, OptimizerConfig, Values, optimize
from slam2d.graph.graph import GraphError
from slam2d.log import Log


def _log_arrays(**changes: object) -> dict[str, object]:
    base: dict[str, object] = dict(stamps_s=np.arange(4.0), odometry=np.zeros((3, 3)), obs_step=np.array([1, 2]),
                                   obs_range_m=np.ones(2), obs_bearing_rad=np.zeros(2), obs_id=np.array([0, 1]))
    base.update(changes)
    return base


@pytest.mark.parametrize(("changes", "message"), [
    ({"stamps_s": np.array([0.0, 2.0, 1.0, 3.0])}, r"stamps_s must be non-decreasing \(stamps_s\[2\]"),
    ({"stamps_s": np.array([0.0, np.nan, 1.0, 3.0])}, "stamps_s has non-finite values"),
    ({"obs_step": np.array([1.5, 2.0])}, "obs_step must be an integer array"),
    ({"obs_id": np.array([0.5, 1.0])}, "obs_id must be an integer array"),
    ({"initial_pose": np.zeros(2)}, "initial_pose"),
    ({"initial_pose": np.array([0.0, 0.0, np.nan])}, "initial_pose has non-finite values"),
    ({"true_poses": np.full((4, 3), np.nan)}, "true_poses has non-finite values"),
    ({"gps_step": np.array([1, 2]), "gps_xy": np.zeros((3, 2))}, "gps_xy"),
    ({"gps_step": np.array([1, 9]), "gps_xy": np.zeros((2, 2))}, "gps_step"),
    ({"gps_step": np.array([1, 1]), "gps_xy": np.zeros((2, 2))}, "gps_step has repeated steps"),
    ({"gps_step": np.array([1, 2])}, "gps_step/gps_xy"),
    ({"scan_step": np.array([1]), "scan_ranges_m": np.ones((1, 5))}, "scan_ranges_m"),
    ({"obs_descriptor": np.zeros((5, 3))}, "obs_descriptor"),
    ({"true_landmarks": np.zeros((3, 3))}, "true_landmarks"),
    ({"true_landmarks": np.zeros((3, 2)), "true_landmark_ids": np.arange(2)}, "true_landmark_ids"),
    ({"marker_step": np.array([1, 9]), "marker_xy_m": np.zeros((2, 2)), "marker_id": np.array([0, 1])},
     "marker_step"),
    ({"scan_max_range_m": -1.0}, "scan_max_range_m"),
])
def test_a_hand_built_log_with_bad_arrays_is_refused_naming_the_field(changes, message):
    with pytest.raises(ValueError, match=message):
        Log(**_log_arrays(**changes))  # type: ignore[arg-type]


def test_a_hand_built_log_takes_lists_and_int_arrays_as_float64_and_keeps_nan_odometry_for_the_runner():
    log = Log(**_log_arrays(odometry=[[1, 0, 0]] * 3, stamps_s=[0, 1, 2, 3]))  # type: ignore[arg-type]
    assert log.odometry.dtype == np.float64 and log.stamps_s.dtype == np.float64
    assert [s.dt_s for s in log] == [1.0, 1.0, 1.0]
    nan_odo = np.zeros((3, 3))
    nan_odo[1, 0] = np.nan  # the runner names the step where it makes the pose non-finite (test_divergence)
    assert np.isnan(Log(**_log_arrays(odometry=nan_odo)).odometry[1, 0])  # type: ignore[arg-type]


def test_trajectory_metrics_refuse_non_finite_poses_and_wrong_shapes():
    rng = np.random.default_rng(0)
    traj = np.cumsum(rng.normal(size=(10, 3)), axis=0)
    bad = traj.copy()
    bad[3, 1] = np.nan
    for f in (lambda: ate(bad, traj), lambda: ate(bad, traj, align=False), lambda: align_se2(bad, traj),
              lambda: rpe(bad, traj)):
        with pytest.raises(ValueError, match="estimate has a non-finite value in row 3"):
            f()
    with pytest.raises(ValueError, match="reference has a non-finite value in row 3"):
        ate(traj, bad)
    with pytest.raises(ValueError, match=r"estimate must have shape \(N, 2\) or \(N, 3\)"):
        ate(np.zeros((5, 4)), np.zeros((5, 4)))
    with pytest.raises(ValueError, match=r"estimate must have shape \(N, 3\)"):
        rpe(traj[:, :2], traj[:, :2])
    with pytest.raises(ValueError, match="delta must be an integer >= 1"):
        rpe(traj, traj, delta=1.5)  # type: ignore[arg-type]
    assert ate(traj[:, :2], traj).rmse_m < 1e-12  # positions alone are fine for ATE


def test_map_error_refuses_wrong_shapes_and_non_finite_positions():
    truth = np.zeros((3, 2))
    with pytest.raises(ValueError, match=r"estimated must have shape \(L, 2\)"):
        map_error(np.zeros((4, 3)), truth)  # was read as 6 landmarks
    with pytest.raises(ValueError, match="estimated landmark 0 has a non-finite position"):
        map_error(np.array([[np.nan, 0.0]]), truth)  # was one spurious landmark
    with pytest.raises(ValueError, match="alignment must be a finite pose"):
        map_error(np.zeros((2, 2)), truth, alignment=[np.nan, 0.0, 0.0])
    assert map_error(np.zeros(0), truth).missed == 3


def test_run_association_scores_refuses_steps_of_different_lengths():
    with pytest.raises(ValueError, match="step 0: 2 assignments for 1 true ids"):
        run_association_scores([np.array([1, 2])], [np.array([1])])
    with pytest.raises(ValueError, match="one array per step"):
        run_association_scores([np.array([1, 2])], [])


def test_se2_refuses_a_transposed_batch_instead_of_reading_garbage():
    poses = np.arange(15.0).reshape(5, 3)
    for f in (se2.compose, se2.between, se2.local):
        with pytest.raises(ValueError, match=r"must have shape \(\.\.\., 3\).*got \(3, 5\)"):
            f(np.zeros(3), poses.T)
    with pytest.raises(ValueError, match=r"got \(3, 5\)"):
        se2.log(poses.T)
    with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., 2\).*got \(2, 4\)"):
        se2.transform_points(np.zeros(3), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="increments"):
        se2.compose_chain(np.zeros(3), np.zeros((3, 4)))
    np.testing.assert_allclose(se2.compose(np.zeros(3), poses)[:, :2], poses[:, :2])  # the right way round


def test_trilaterate_and_chi2_gate_refuse_inconsistent_arguments():
    with pytest.raises(ValueError, match=r"ranges \(K,\)"):
        trilaterate(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), np.ones(2))  # was a silent wrong point
    with pytest.raises(ValueError, match="dof must be an integer"):
        chi2_gate(0.95, 1.5)  # type: ignore[arg-type]


def _chain() -> FactorGraph:
    g = FactorGraph()
    g.add_between([0, 1], [1, 2], np.array([[1.0, 0, 0], [1.0, 0, 0]]), np.eye(3))
    return g


def test_factor_information_batches_must_match_the_measurements():
    with pytest.raises(GraphError, match=r"add_between: information must be \(3, 3\) or \(2, 3, 3\)"):
        _chain().add_between([0, 1], [1, 2], np.zeros((2, 3)), np.stack([np.eye(3)] * 3))
    with pytest.raises(GraphError, match="add_between: information must be"):
        _chain().add_between([0], [1], np.zeros((1, 3)), np.eye(2))
    g = _chain()  # a single (1, 3, 3) matrix is broadcast, so a later batch still lines up
    g.add_between([0, 1], [2, 0], np.zeros((2, 3)), 2.0 * np.eye(3)[None])
    g.add_between([1], [0], np.zeros((1, 3)), 5.0 * np.eye(3))
    assert g.block("between").sqrt_info.shape == (5, 3, 3)


def test_values_refuse_a_transposed_array_rather_than_reshape_it():
    with pytest.raises(GraphError, match=r"Values.poses: values must have shape \(N, 3\), got \(3, 2\)"):
        Values(np.arange(2), np.arange(6.0).reshape(3, 2))
    with pytest.raises(GraphError, match=r"Values.points: values must have shape \(N, 2\), got \(2, 3\)"):
        Values(np.arange(1), np.zeros((1, 3)), np.arange(3), np.arange(6.0).reshape(2, 3))
    v = Values(np.arange(1), np.zeros(3), np.zeros(0, np.int64), np.zeros(0))  # one pose, no points
    assert v.poses.shape == (1, 3) and v.points.shape == (0, 2)
    with pytest.raises(GraphError, match="add_poses"):
        v.add_poses([1, 2], np.zeros((3, 2)))


def test_optimizer_config_refuses_unknown_factor_types_solvers_and_non_integers():
    with pytest.raises(ValueError, match=r"robust_kinds: unknown factor type\(s\) \['betwen'\]"):
        OptimizerConfig(robust_kernel="huber", robust_kinds=("betwen",))  # was silently no kernel at all
    with pytest.raises(GraphError, match="with_robust: unknown factor type"):
        _chain().with_robust(("betwen",), "huber")
    with pytest.raises(ValueError, match="linear_solver: unknown linear solver 'foo'"):
        OptimizerConfig(linear_solver="foo")
    with pytest.raises(ValueError, match="max_iterations must be an integer"):
        OptimizerConfig(max_iterations=2.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="lambda_decrease_factor must be a finite number > 1"):
        OptimizerConfig(lambda_decrease_factor=0.5)


def test_an_empty_graph_says_so():
    with pytest.raises(GraphError, match="the graph has no factors"):
        optimize(FactorGraph(), Values(np.arange(3), np.zeros((3, 3))))


def test_run_and_make_estimator_refuse_a_missing_rng_and_non_mapping_arguments():
    import slam2d

    log = slam2d.simulate("room", seed=0, steps=3)
    est = slam2d.make_estimator("fastslam", log_metadata=log.metadata)
    with pytest.raises(TypeError, match="rng must be a numpy.random.Generator"):
        slam2d.run(est, log, rng=None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="overrides must be a mapping"):
        slam2d.make_estimator("ekf", [("sensor.range_std_m", 1.0)])  # type: ignore[arg-type]


def test_run_refuses_a_registered_back_end_on_a_log_without_its_input() -> None:
    """``slam2d.run`` from Python, like ``run_named`` and the CLI: the lidar back end on the grid (no walls, no scans)
    would only dead-reckon under its name. The registry finds the back end by the estimator's class."""
    from slam2d.lab.registry import make_estimator
    from slam2d.lab.runner import run
    from slam2d.sim.scenarios import ScenarioConfig
    from slam2d.sim.simulator import simulate

    log = simulate(ScenarioConfig(name="grid", steps=10), 0)
    for name in ("lidar", "lidar-lifelong"):
        with pytest.raises(ValueError, match="estimator 'lidar' or 'lidar-lifelong' needs lidar scans; grid has none"):
            run(make_estimator(name), log, rng=np.random.default_rng(0))
    assert run(make_estimator("ekf"), log, rng=np.random.default_rng(0)).trajectory.shape == (11, 3)


def test_run_named_refuses_a_bad_estimator_value_before_simulating(monkeypatch: pytest.MonkeyPatch) -> None:
    """A typo or a bad value in an ``estimator.`` override used to be found only after the scenario was simulated."""
    import slam2d.lab.runner as runner

    def no_simulation(*args: object) -> None:
        raise AssertionError("simulated before the estimator's overrides were checked")

    monkeypatch.setattr(runner, "simulate", no_simulation)
    with pytest.raises(ValueError, match="nope"):
        runner.run_named("ekf", "room", overrides={"estimator.nope": 1})
    with pytest.raises(ValueError, match="particles"):
        runner.run_named("fastslam", "room", overrides={"particles": "many"})
