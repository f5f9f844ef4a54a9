import numpy as np
import pytest

from slam2d.graph.graph import Values
from slam2d.graph.incremental import IncrementalConfig, IncrementalPoseGraph
from slam2d.graph.optimizer import OptimizerConfig, optimize
from slam2d.graph.problem import chi2
from slam2d.graph.synthetic import manhattan_walk


def _feed(block, inc, n):
    newer = np.maximum(block.keys[0], block.keys[1])
    for t in range(1, n):
        idx = np.flatnonzero(newer == t)
        inc.add_step(t, block.keys[0][idx], block.keys[1][idx], block.z[idx], block.information[idx])


def test_incremental_tracks_the_batch_optimum_and_finishes_on_it():
    syn = manhattan_walk(np.random.default_rng(4), num_poses=400)
    block = syn.graph.block("between")
    _, batch = optimize(syn.graph, syn.initial, OptimizerConfig(method="lm"))
    inc = IncrementalPoseGraph(syn.initial.poses[0], IncrementalConfig(window=20, full_every=150))
    _feed(block, inc, 400)
    assert inc.local_solves > 10 and inc.full_solves == 2
    online = chi2(syn.graph, Values(np.arange(400), inc.poses))
    odometry_only = chi2(syn.graph, syn.initial)
    assert online < 1.5 * batch.chi2_final < odometry_only
    inc.finalize()
    final = chi2(syn.graph, Values(np.arange(400), inc.poses))
    assert final == pytest.approx(batch.chi2_final, rel=1e-6)


def test_repeated_full_solves_reuse_one_analysis_and_equal_fresh_ones():
    syn = manhattan_walk(np.random.default_rng(7), num_poses=120)
    block = syn.graph.block("between")
    inc = IncrementalPoseGraph(syn.initial.poses[0], IncrementalConfig(window=10, full_every=1000))
    _feed(block, inc, 120)
    graph = inc.graph()
    for _ in range(3):  # the solves that follow a loop, one per scan, with nothing added in between
        fresh, _ = optimize(graph, Values(np.arange(120), inc.poses), OptimizerConfig(method="gn", max_iterations=1))
        inc.solve_full(1)
        assert np.allclose(inc.poses, fresh.poses, rtol=0, atol=1e-12)
    assert inc._full is not None and inc._full[1].analyses_done == 1
    z, info = np.array([[1.0, 0.0, 0.0]]), np.eye(3)[None] * 10
    inc.add_step(120, np.array([119]), np.array([120]), z, info)  # a new pose: a new analysis
    inc.solve_full(1)
    assert inc._full[1].analyses_done == 1 and inc._full[0][:2] == (121, inc.num_edges)


def test_incremental_rejects_out_of_order_input():
    inc = IncrementalPoseGraph(np.zeros(3))
    z, info = np.array([[1.0, 0.0, 0.0]]), np.eye(3)[None] * 10
    with pytest.raises(ValueError, match="in order"):
        inc.add_step(2, np.array([1]), np.array([2]), z, info)
    with pytest.raises(ValueError, match="existing older pose"):
        inc.add_step(1, np.array([1]), np.array([5]), z, info)
    with pytest.raises(ValueError, match="window"):
        IncrementalConfig(window=0)
