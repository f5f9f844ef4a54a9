"""Batch landmark graph SLAM built from a log (slam2d.graph.batch): factor information, structure, optimisation."""

from __future__ import annotations

import numpy as np

from slam2d.eval.trajectory import ate
from slam2d.geometry import se2
from slam2d.graph import FactorGraph, Optimizer, OptimizerConfig, Values, density_arrays
from slam2d.graph.batch import information_pattern, landmark_graph
from slam2d.models.motion import MotionNoise
from slam2d.sim import simulate


def test_landmark_graph_from_a_log_reduces_the_trajectory_error() -> None:
    log = simulate("room", seed=3, steps=120)
    noise = MotionNoise()
    dr = se2.compose_chain(log.initial_pose, log.odometry)
    prob = landmark_graph(log, noise, np.diag([0.1**2, 0.02**2]), dr)
    n_obs = int((log.obs_id >= 0).sum())
    assert prob.graph.num_factors == log.num_steps + n_obs
    assert len(prob.obs_steps) == n_obs and set(prob.obs_ids.tolist()) == set(prob.initial.point_keys.tolist())
    values, _ = Optimizer(prob.graph, OptimizerConfig(method="gn", max_iterations=20)).optimize(prob.initial)
    order = np.argsort(values.pose_keys)
    assert ate(values.poses[order], log.true_poses).rmse_m < 0.5 * ate(dr, log.true_poses).rmse_m


def test_information_pattern_matches_the_linearised_information_matrix(rng: np.random.Generator) -> None:
    g = FactorGraph()
    g.add_prior([0], np.zeros((1, 3)), np.eye(3))
    g.add_between([0, 1, 2], [1, 2, 3], rng.normal(size=(3, 3)) * 0.3, np.eye(3))
    g.add_range_bearing([0, 3, 2], [10, 10, 11], np.array([[2.0, 0.1], [2.5, -0.2], [1.5, 0.4]]), np.eye(2))
    vals = Values(np.arange(4), rng.normal(size=(4, 3)), np.array([10, 11]), rng.normal(size=(2, 2)) + 5)
    pattern = information_pattern(g, vals.pose_keys, vals.point_keys)
    np.testing.assert_array_equal(pattern, density_arrays(g, vals).information_pattern)
    assert not pattern[0, 2] and pattern[0, 4] and pattern[3, 4] and not pattern[1, 4]
