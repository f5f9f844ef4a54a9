"""Online graph SLAM in window mode (``GraphSLAMConfig.window``): bounded work per step, the same optimum at the
end, a conservative pose covariance, and window solves that are exactly the fixed-boundary sub-problem."""

import numpy as np
import pytest

import slam2d
import slam2d.graph.online as online
from slam2d.graph.graph import Values
from slam2d.graph.online import GraphSLAM
from slam2d.graph.optimizer import Optimizer, OptimizerConfig
from slam2d.graph.sliding_window import solve_window
from slam2d.lab.registry import make_config
from slam2d.sim.simulator import spawn_streams


def _run(log, seed=0, **over):
    est = GraphSLAM(make_config("graph", over, log.metadata))
    est.reset(log.initial_pose, rng=spawn_streams(seed)["estimator"])
    return est


def test_window_mode_finalises_at_the_whole_graph_optimum():
    """Loop closure off: both modes build the same graph; finalize must land on the same optimum."""
    log = slam2d.simulate("loop", seed=1, steps=300)
    finals, chi2 = [], []
    for window in (0, 20):
        est = _run(log, loop_closure="false", window=window)
        for step in log:
            est.step(step)
        est.finalize()
        finals.append(est.estimate())
        chi2.append(est.chi2_per_dof())
    assert finals[0].trajectory.shape == finals[1].trajectory.shape
    # equal up to Levenberg-Marquardt's stopping tolerance, and at the same cost
    np.testing.assert_allclose(finals[1].trajectory, finals[0].trajectory, atol=1e-4)
    np.testing.assert_allclose(finals[1].landmarks, finals[0].landmarks, atol=1e-4)
    for k in chi2[0]:
        assert chi2[1][k] == pytest.approx(chi2[0][k], rel=1e-6), k


def test_window_solve_is_the_fixed_boundary_optimum_of_the_whole_graph():
    """Without the sightings cap, a window solve iterated to convergence equals optimising the whole graph with every
    pose outside the window held (the landmarks the window never saw are decoupled from it then)."""
    log = slam2d.simulate("room", seed=2, steps=120)
    est = _run(log, window=15, loop_closure="false")
    for step in log:
        est.step(step)
    free = est.values.pose_keys[-15:]
    rb = est.graph.block("range_bearing")
    pts = np.unique(rb.keys[1][np.isin(rb.keys[0], free)])
    ws = solve_window(est.graph, est.values, free, pts, iterations=50)
    held = np.setdiff1d(est.values.pose_keys, free)
    ref, _ = Optimizer(est.graph, OptimizerConfig(method="lm", max_iterations=50),
                       fixed_pose_keys=held).optimize(est.values)
    rows = np.searchsorted(ref.pose_keys, ws.values.pose_keys)
    np.testing.assert_allclose(ws.values.poses, ref.poses[rows], atol=1e-7)
    prow = [int(np.flatnonzero(ref.point_keys == k)[0]) for k in ws.values.point_keys]
    np.testing.assert_allclose(ws.values.points, ref.points[prow], atol=1e-7)
    assert ws.boundary.size > 0 and np.all(~np.isin(ws.boundary, free))


def test_work_per_window_solve_does_not_grow_with_the_drive(monkeypatch):
    """Three laps of the loop world: the factors in each window solve stay bounded while the graph triples."""
    sizes = []
    real = online.solve_window

    def spy(graph, values, free_poses, free_points, iterations, boundary_sightings=None):
        ws = real(graph, values, free_poses, free_points, iterations, boundary_sightings)
        sizes.append((int(values.pose_keys[-1]), ws.graph.num_factors, graph.num_factors))
        return ws

    monkeypatch.setattr(online, "solve_window", spy)
    log = slam2d.simulate("loop", seed=0, steps=1380)
    est = _run(log, window=25)
    for step in log:
        est.step(step)
    s = np.array(sizes)
    first, last = s[(s[:, 0] > 100) & (s[:, 0] <= 460)], s[s[:, 0] > 920]
    assert last[:, 2].min() > 2 * first[:, 2].max()  # the graph grew ...
    assert last[:, 1].max() <= 1.5 * first[:, 1].max()  # ... the window problems did not
    assert est.estimate().diagnostics.loops_accepted > 0


def test_window_pose_covariance_is_conservative():
    """Before any loop closure the window's pose covariance is never smaller than the whole-graph marginal."""
    log = slam2d.simulate("loop", seed=0, steps=300)
    est = _run(log, window=25, loop_closure="false")
    checked = 0
    for step in log:
        est.step(step)
        if step.index % 10 == 5 and step.index > 30:  # right after a window solve
            exact = est._marginals([step.index])
            ev = np.linalg.eigvalsh(est.pose_cov - exact)
            assert ev.min() > -1e-9 * np.abs(exact).max(), (step.index, ev)
            checked += 1
    assert checked >= 25


def test_window_config_validation():
    with pytest.raises(ValueError, match="window"):
        make_config("graph", {"window": -1})
    with pytest.raises(ValueError, match="full_every"):
        make_config("graph", {"window": 10, "full_every": 0})


def test_window_values_are_written_back_only_inside_the_window():
    log = slam2d.simulate("room", seed=0, steps=60)
    est = _run(log, window=10)
    for step in log.head(55):
        est.step(step)
    before = est.values.copy()
    est._optimize(2, local=True)
    moved = np.any(est.values.poses != before.poses, axis=1)
    assert not np.any(moved[:-10]) and isinstance(est.values, Values)


def test_window_mode_leaves_unknown_association_on_the_whole_graph():
    """Unknown association gates with the joint belief of the whole graph: window mode changes nothing there."""
    log = slam2d.simulate("loop", seed=0, steps=120)
    snaps = []
    for window in (0, 25):
        est = _run(log, window=window, **{"association.method": "mahalanobis"})
        for step in log:
            est.step(step)
        snaps.append(est.estimate())
    np.testing.assert_array_equal(snaps[0].trajectory, snaps[1].trajectory)
    np.testing.assert_array_equal(snaps[0].pose_cov, snaps[1].pose_cov)
