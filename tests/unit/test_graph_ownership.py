"""Optimising never changes the caller's FactorGraph or Values: the optimiser works on copies (or, for a robust
kernel override, on a private view of the graph), and Values own their arrays."""

from __future__ import annotations

import copy

import numpy as np

from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.optimizer import Optimizer, OptimizerConfig, optimize


def _graph(rng: np.random.Generator) -> tuple[FactorGraph, Values]:
    g = FactorGraph()
    g.add_between(np.arange(5), np.arange(1, 6), np.tile([1.0, 0.0, 0.3], (5, 1)) + 0.1 * rng.normal(size=(5, 3)),
                  np.eye(3) * 50)
    g.add_between([0], [5], [[3.0, 3.0, 1.5]], np.eye(3) * 10, robust="cauchy", robust_param=2.0)
    g.add_point([0, 2, 4], [0, 0, 1], rng.normal(size=(3, 2)) + 3.0, np.eye(2) * 20)
    vals = Values(np.arange(6), 0.2 * rng.normal(size=(6, 3)), [0, 1], rng.normal(size=(2, 2)))
    return g, vals


def _snapshot(g: FactorGraph) -> list[tuple[str, np.ndarray, ...]]:
    return [(b.kind, b.keys.copy(), b.z.copy(), b.sqrt_info.copy(), b.kernel.copy(), b.kernel_param.copy())
            for b in g.blocks()]


def _same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(x[0] == y[0] and all(np.array_equal(p, q) for p, q in zip(x[1:], y[1:],
                                                                                               strict=True))
                                    for x, y in zip(a, b, strict=True))


def test_optimize_leaves_the_callers_graph_and_values_unchanged():
    rng = np.random.default_rng(3)
    for cfg in (OptimizerConfig(), OptimizerConfig(method="gn"), OptimizerConfig(method="dogleg"),
                OptimizerConfig(robust_kernel="huber", robust_param=0.5),
                OptimizerConfig(robust_kernel="none", robust_kinds=("between",))):
        g, vals = _graph(rng)
        g_before, v_before = _snapshot(g), copy.deepcopy(vals)
        version = g.structure_version
        out, _ = optimize(g, vals, cfg)
        assert _same(_snapshot(g), g_before), cfg
        assert g.structure_version == version
        for name in ("pose_keys", "poses", "point_keys", "points"):
            np.testing.assert_array_equal(getattr(vals, name), getattr(v_before, name))
            assert not np.shares_memory(getattr(out, name), getattr(vals, name))


def test_a_kernel_override_acts_only_inside_the_optimiser():
    rng = np.random.default_rng(4)
    g, vals = _graph(rng)
    plain, s_plain = optimize(g, vals)
    opt = Optimizer(g, OptimizerConfig(robust_kernel="huber", robust_param=0.1))
    robust, s_rob = opt.optimize(vals)
    assert s_rob.cost_final < s_rob.chi2_final  # the override was applied ...
    assert np.all(g.block("between").kernel[:-1] == 0) and g.block("between").kernel[-1] == 2  # ... not to g
    # switching the override off on the same optimiser uses the caller's own kernels again
    opt.config = OptimizerConfig()
    again, s_again = opt.optimize(vals)
    np.testing.assert_allclose(again.poses, plain.poses, atol=1e-9)
    assert s_again.cost_final == s_plain.cost_final
    # the caller's later per-factor changes are seen by a reused optimiser
    g.set_robust("point", "cauchy", 0.1)
    _, s_cauchy = opt.optimize(vals)
    assert s_cauchy.cost_final < s_again.cost_final


def test_values_own_their_arrays():
    poses = np.zeros((2, 3))
    keys = np.array([0, 1])
    v = Values(keys, poses)
    v.poses[0, 0] = 5.0
    keys[0] = 7
    assert poses[0, 0] == 0.0 and v.pose_keys[0] == 0
    c = v.copy()
    c.poses[1, 1] = 3.0
    assert v.poses[1, 1] == 0.0
    v.add_points([4], [[1.0, 2.0]])
    assert v.point(4).tolist() == [1.0, 2.0]
