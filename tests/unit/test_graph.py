import numpy as np
import pytest

from slam2d import _jacobians
from slam2d.eval.trajectory import ate
from slam2d.geometry import se2
from slam2d.graph import (
    FactorGraph,
    GraphError,
    Optimizer,
    OptimizerConfig,
    SolverError,
    Values,
    chi2,
    chi2_by_kind,
    density_arrays,
    marginal_covariances,
    optimize,
)
from slam2d.graph import factors as F
from slam2d.graph.initialization import chordal_poses
from slam2d.graph.linear import available_solvers, make_solver
from slam2d.graph.problem import Analysis, factor_chi2
from slam2d.graph.robust import robustify
from slam2d.graph.synthetic import false_loop_closures, manhattan_walk
from slam2d.testing import assert_jacobian_matches

GRAPH_PAIRS = [p for p in _jacobians.REGISTRY if p.name.startswith("slam2d.graph.")]


def test_every_factor_kind_is_registered_for_the_fd_check():
    names = {p.name.rsplit(".", 1)[-1] for p in GRAPH_PAIRS}
    assert names == {f"{k}_error" for k in F.KINDS}


@pytest.mark.parametrize("edge", ["random", "zero", "pi", "-pi"])
@pytest.mark.parametrize("pair", GRAPH_PAIRS, ids=[p.name for p in GRAPH_PAIRS])
def test_factor_jacobians_match_finite_differences(pair, edge):
    rng = np.random.default_rng(3)
    kwargs = dict(pair.kwargs)
    for _ in range(5):
        args = [_jacobians.sample_arg(k, rng, edge) for k in pair.arg_kinds]
        analytic = pair.jacobians(*args, **kwargs)
        for i, kind in enumerate(pair.arg_kinds):

            def f(xi, i=i, args=args):
                a = list(args)
                a[i] = xi
                return pair.function(*a, **kwargs)

            assert_jacobian_matches(f, args[i], analytic[i], input_angles=_jacobians.ARG_KINDS[kind][1],
                                    output_angles=pair.output_angles, rtol=1e-5, atol=1e-6)


def test_between_error_is_g2o_edge_se2():
    rng = np.random.default_rng(0)
    xi, xj, z = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    # t2v(Z^-1 (Xi^-1 Xj)) computed with the group operations
    expected = se2.compose(se2.inverse(z), se2.between(xi, xj))
    np.testing.assert_allclose(F.between_error(xi, xj, z), expected, atol=1e-12)


def test_hand_solvable_graph_weighted_mean():
    # two measurements of the same relative pose with information 1 and 3 on every axis: the optimum is the
    # information-weighted mean (the problem is linear because the first heading is held at 0)
    g = FactorGraph()
    g.add_between([0, 0], [1, 1], [[1.0, 0.0, 0.1], [1.2, 0.0, 0.3]], np.stack([np.eye(3), 3 * np.eye(3)]))
    vals = Values([0, 1], [[0, 0, 0], [5.0, -3.0, 1.0]])
    for method in ("gn", "lm"):
        out, s = optimize(g, vals, OptimizerConfig(method=method))
        x1 = out.pose(1)
        # translation: R(th1)... the error rotates by R(dth)^T, which does not change the isotropic weighting
        np.testing.assert_allclose(x1, [1.15, 0.0, 0.25], atol=1e-7)
        assert s.chi2_final == pytest.approx(1 * (0.15**2 + 0.15**2) + 3 * (0.05**2 + 0.05**2), rel=1e-9)
        np.testing.assert_array_equal(out.pose(0), [0, 0, 0])  # gauge held
        assert s.gauge_pose_keys == [0]


def _random_graph(rng, P=12, L=5):
    truth = np.column_stack([rng.uniform(-5, 5, (P, 2)), rng.uniform(-np.pi, np.pi, P)])
    lms = rng.uniform(-8, 8, (L, 2))
    g = FactorGraph()
    keys = np.arange(P)
    def om(m):
        a = rng.normal(size=(m, m))
        return a @ a.T + m * np.eye(m)
    g.add_between(keys[:-1], keys[1:], se2.between(truth[:-1], truth[1:]) + 0.05 * rng.normal(size=(P - 1, 3)),
                  np.stack([om(3) for _ in range(P - 1)]))
    g.add_between([0, 3], [9, 11], se2.between(truth[[0, 3]], truth[[9, 11]]), np.eye(3) * 4)
    pi = rng.integers(0, P, 20)
    li = rng.integers(0, L, 20)
    g.add_point(pi, li, se2.inverse_transform_points(truth[pi], lms[li]) + 0.02 * rng.normal(size=(20, 2)),
                np.stack([om(2) for _ in range(20)]))
    g.add_range_bearing(pi[:6], li[:6], np.column_stack([np.hypot(*(lms[li[:6]] - truth[pi[:6], :2]).T),
                                                         rng.uniform(-3, 3, 6)]), np.eye(2))
    g.add_bearing(pi[6:9], li[6:9], rng.uniform(-3, 3, (3, 1)), np.eye(1) * 2)
    g.add_range(pi[9:12], li[9:12], rng.uniform(1, 5, (3, 1)), np.eye(1) * 2)
    g.add_position([2, 5], truth[[2, 5], :2] + 0.1, np.eye(2))
    g.add_point_prior([1], lms[[1]], np.eye(2))
    vals = Values(keys, truth + 0.1 * rng.normal(size=(P, 3)), np.arange(L), lms + 0.2 * rng.normal(size=(L, 2)))
    return g, vals


def test_sparse_step_equals_dense_lstsq_of_the_same_system():
    rng = np.random.default_rng(11)
    g, vals = _random_graph(rng)
    an = Analysis(g, vals)
    _, chi2v, data, grad = an.linearize(vals.poses, vals.points)
    # independent dense assembly from the single-factor API
    rows_A, rows_r = [], []
    cols_of = {}
    for k, _i in zip(vals.pose_keys, range(vals.pose_keys.size), strict=True):
        cols_of[("pose", int(k))] = an.variable_slices([k])[0]
    for k in vals.point_keys:
        cols_of[("point", int(k))] = an.variable_slices((), [k])[0]
    for b in g.blocks():
        kind = F.KINDS[b.kind]
        err = getattr(F, f"{b.kind}_error")
        jac = getattr(F, f"{b.kind}_error_jacobians")
        for f in range(b.size):
            args = [vals.pose(int(b.keys[a, f])) if vk == "pose" else vals.point(int(b.keys[a, f]))
                    for a, vk in enumerate(kind.var_kinds)]
            L = b.sqrt_info[f]
            row = np.zeros((kind.dim, an.n))
            for a, (vk, J) in enumerate(zip(kind.var_kinds, jac(*args, b.z[f]), strict=True)):
                c = cols_of[(vk, int(b.keys[a, f]))]
                ok = c >= 0
                row[:, c[ok]] += (L @ J)[:, ok]
            rows_A.append(row)
            rows_r.append(L @ err(*args, b.z[f]))
    A, r = np.vstack(rows_A), np.concatenate(rows_r)
    assert float(r @ r) == pytest.approx(chi2v, rel=1e-12)
    dx_dense = np.linalg.lstsq(A, -r, rcond=None)[0]
    np.testing.assert_allclose(grad, A.T @ r, rtol=1e-9, atol=1e-9)
    up = an.upper(data)
    assert up.nnz == an.nnz and np.all(np.diff(an.indptr) >= 1)
    np.testing.assert_allclose(up.toarray(), np.triu(A.T @ A), rtol=1e-9, atol=1e-9)
    for k in range(an.n):  # strictly increasing rows in every column, ending on the diagonal
        rows = an.indices[an.indptr[k] : an.indptr[k + 1]]
        assert np.all(np.diff(rows) > 0) and rows[-1] == k and an.diag_pos[k] == an.indptr[k + 1] - 1
    for name in available_solvers():
        s = make_solver(name)
        s.factorize(an.upper(data))
        np.testing.assert_allclose(s.solve(-grad), dx_dense, rtol=1e-7, atol=1e-9, err_msg=name)


def test_optimizer_decreases_and_gn_lm_agree_on_random_graph():
    rng = np.random.default_rng(5)
    g, vals = _random_graph(rng)
    a, sa = optimize(g, vals, OptimizerConfig(method="gn", relative_decrease_tol=1e-12))
    b, sb = optimize(g, vals, OptimizerConfig(method="lm", relative_decrease_tol=1e-12))
    c, sc = optimize(g, vals, OptimizerConfig(method="dogleg", relative_decrease_tol=1e-12))
    assert sa.chi2_final < sa.chi2_initial
    assert sa.chi2_final == pytest.approx(sb.chi2_final, rel=1e-8)
    assert sc.chi2_final == pytest.approx(sb.chi2_final, rel=1e-8)
    np.testing.assert_allclose(a.poses, b.poses, atol=1e-5)
    # the gradient vanishes at the optimum
    an = Analysis(g, a)
    _, _, _, grad = an.linearize(a.poses, a.points)
    _, _, _, grad0 = an.linearize(vals.poses, vals.points)
    assert np.abs(grad).max() < 1e-5 * np.abs(grad0).max()
    assert chi2(g, a) == pytest.approx(sa.chi2_final, rel=1e-12)
    by = chi2_by_kind(g, a)
    assert set(by) == set(g.kinds()) | {"total"}


def test_an_optimal_graph_stops_at_once_with_damped_methods():
    """At zero cost every damped step is rejected: LM and dog leg stop before the first one instead of growing the
    damping to its limit (they took 13 rejected iterations on a two-pose graph)."""
    rng = np.random.default_rng(5)
    g, vals = _random_graph(rng)
    best, _ = optimize(g, vals, OptimizerConfig(method="gn", relative_decrease_tol=1e-12))
    exact = FactorGraph()
    ij = g.block("between").keys
    exact.add_between(ij[0], ij[1], se2.between(best.poses[ij[0]], best.poses[ij[1]]),
                      np.repeat(np.eye(3)[None], ij.shape[1], axis=0))
    poses = Values(best.pose_keys, best.poses)
    for method in ("lm", "dogleg"):
        out, s = optimize(exact, poses, OptimizerConfig(method=method))
        assert (s.termination, s.iterations, s.linear_solves) == ("zero cost", 0, 0)
        np.testing.assert_array_equal(out.poses, best.poses)


def test_marginals_equal_blocks_of_the_dense_inverse():
    rng = np.random.default_rng(2)
    g, vals = _random_graph(rng)
    out, _ = optimize(g, vals)
    an = Analysis(g, out)
    _, _, data, _ = an.linearize(out.poses, out.points)
    up = an.upper(data).toarray()
    H = up + up.T - np.diag(np.diag(up))
    Pfull = np.linalg.inv(H)
    m = marginal_covariances(g, out, pose_keys=[3, 0], point_keys=[2])
    c3 = an.variable_slices([3])[0]
    np.testing.assert_allclose(m.block("pose", 3), Pfull[np.ix_(c3, c3)], rtol=1e-8, atol=1e-12)
    np.testing.assert_array_equal(m.block("pose", 0), np.zeros((3, 3)))  # held gauge pose
    cl = an.variable_slices((), [2])[0]
    np.testing.assert_allclose(m.joint[6:, :3], Pfull[np.ix_(cl, c3)], rtol=1e-8, atol=1e-12)
    d = density_arrays(g, out)
    assert d.information_pattern.shape == (17, 17)
    assert d.covariance_fill > d.information_fill  # P is dense, Omega is sparse
    assert d.covariance_fill == pytest.approx((16 / 17) ** 2)  # every free block non-zero; pose 0 is held


def test_optimizer_reuses_analysis_until_structure_changes():
    rng = np.random.default_rng(4)
    sg = manhattan_walk(rng, num_poses=60)
    opt = Optimizer(sg.graph)
    v1, s1 = opt.optimize(sg.initial)
    v2, s2 = opt.optimize(v1)
    assert opt.analyses_done == 1
    assert s2.chi2_final <= s1.chi2_final * (1 + 1e-9)
    # append a pose and an odometry factor: new analysis, same result as a fresh optimiser
    sg.graph.add_between([59], [60], [[1.0, 0.0, 0.0]], np.eye(3) * 100)
    v2 = v1.copy()
    v2.add_poses([60], se2.compose(v1.pose(59), [1.0, 0.0, 0.0]))
    v3, s3 = opt.optimize(v2)
    assert opt.analyses_done == 2
    v4, s4 = optimize(sg.graph, v2)
    assert s3.chi2_final == pytest.approx(s4.chi2_final, rel=1e-12)


def test_marginals_reuse_the_optimizers_symbolic_factorisation_and_give_the_same_numbers():
    sg = manhattan_walk(np.random.default_rng(5), num_poses=80)
    opt = Optimizer(sg.graph)
    out, _ = opt.optimize(sg.initial)
    fresh = marginal_covariances(sg.graph, out, [79, 40], analysis=opt.analysis)
    refactored = []
    solver = opt.solver
    assert solver is not None
    factorize = solver.factorize
    solver.factorize = lambda upper: (refactored.append(upper.nnz), factorize(upper))[1]  # type: ignore[method-assign]
    reused = marginal_covariances(sg.graph, out, [79, 40], analysis=opt.analysis, solver=solver)
    assert len(refactored) == 1  # the optimiser's solver did the work
    np.testing.assert_array_equal(reused.joint, fresh.joint)  # same ordering: the same numbers, bit for bit
    assert np.all(np.linalg.eigvalsh(reused.joint) > 0)


def test_disconnected_graph_holds_one_pose_per_component():
    g = FactorGraph()
    g.add_between([0, 10], [1, 11], [[1, 0, 0], [0, 1, 0]], np.eye(3))
    vals = Values([0, 1, 10, 11], [[0, 0, 0], [0.5, 0.2, 0.1], [3, 3, 0], [3.2, 3.5, 0.2]])
    out, s = optimize(g, vals, OptimizerConfig(method="gn"))
    assert s.num_components == 2 and s.gauge_pose_keys == [0, 10]
    assert s.chi2_final < 1e-12
    np.testing.assert_allclose(out.pose(11), se2.compose(vals.pose(10), [0, 1, 0]), atol=1e-8)


def test_prior_anchors_the_gauge_and_position_factors_work():
    g = FactorGraph()
    g.add_prior([0], [[1.0, 2.0, 0.5]], np.eye(3) * 10)
    g.add_between([0], [1], [[1.0, 0, 0]], np.eye(3))
    g.add_position([1], [[2.0, 2.6]], np.eye(2))
    out, s = optimize(g, Values([0, 1], np.zeros((2, 3))))
    assert s.gauge_pose_keys == []
    assert s.chi2_final < s.chi2_initial


def test_bad_graph_input_is_rejected_clearly():
    g = FactorGraph()
    with pytest.raises(GraphError, match="not positive definite"):
        g.add_between([0], [1], [[1, 0, 0]], np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(GraphError, match="not finite"):
        g.add_between([0], [1], [[np.nan, 0, 0]], np.eye(3))
    with pytest.raises(GraphError, match="itself"):
        g.add_between([0], [0], [[1, 0, 0]], np.eye(3))
    g.add_between([0], [1], [[1, 0, 0]], np.eye(3))
    with pytest.raises(GraphError, match="pose 1"):
        optimize(g, Values([0], [[0, 0, 0]]))
    with pytest.raises(GraphError, match="duplicate"):
        Values([0, 0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="robust"):
        OptimizerConfig(robust_kernel="tukey")
    with pytest.raises(ValueError, match="max_iterations"):
        OptimizerConfig(max_iterations=0)
    # an unobservable landmark (one bearing) makes H singular: GN says so, LM damps and returns
    g2 = FactorGraph()
    g2.add_between([0], [1], [[1, 0, 0]], np.eye(3))
    g2.add_bearing([0], [0], [[0.3]], np.eye(1))
    vals = Values([0, 1], [[0, 0, 0], [1, 0, 0]], [0], [[2.0, 1.0]])
    with pytest.raises(SolverError):
        optimize(g2, vals, OptimizerConfig(method="gn", linear_solver="dense"))


def test_robust_kernel_weights():
    s = np.array([0.25, 4.0, 100.0])
    for code, p in ((1, 1.0), (2, 1.0), (3, 1.0)):
        rho, w = robustify(s, np.full(3, code, np.int8), np.full(3, p))
        # IRLS weight is the derivative of rho
        h = 1e-6
        rp, _ = robustify(s + h, np.full(3, code, np.int8), np.full(3, p))
        np.testing.assert_allclose(w, (rp - rho) / h, rtol=1e-4)
        assert np.all(w <= 1.0 + 1e-12) and w[2] < w[0]
    rho, w = robustify(s, np.zeros(3, np.int8), np.ones(3))
    np.testing.assert_array_equal(rho, s)
    np.testing.assert_array_equal(w, 1.0)


@pytest.mark.slow
def test_false_loop_closures_destroy_the_map_and_a_robust_kernel_recovers_it():
    rng = np.random.default_rng(21)
    sg = manhattan_walk(rng, num_poses=400)
    clean, s_clean = optimize(sg.graph, sg.initial)
    ate_clean = ate(clean.poses, sg.truth.poses).rmse_m
    n_in = sg.graph.block("between").size
    i, j, z = false_loop_closures(rng, 400, 20)
    sg.graph.add_between(i, j, z, np.diag(1.0 / np.square(sg.sigmas)))
    bad, _ = optimize(sg.graph, sg.initial)
    ate_bad = ate(bad.poses, sg.truth.poses).rmse_m
    inlier_chi2_bad = factor_chi2(sg.graph, bad, "between")[:n_in].sum()
    results = {}
    for kernel, param in (("dcs", 10.0), ("cauchy", 3.0)):
        cfg = OptimizerConfig(robust_kernel=kernel, robust_param=param, max_iterations=200)
        rob, _ = optimize(sg.graph, sg.initial, cfg)
        sg.graph.set_robust(None, None)
        results[kernel] = (ate(rob.poses, sg.truth.poses).rmse_m, factor_chi2(sg.graph, rob, "between")[:n_in].sum())
    assert ate_bad > 10 * ate_clean  # the map is destroyed
    assert inlier_chi2_bad > 20 * s_clean.chi2_final
    for kernel, (ate_r, chi2_in) in results.items():
        assert ate_r < 1.1 * ate_clean, kernel
        assert chi2_in < 1.05 * s_clean.chi2_final, kernel


def test_chordal_initialisation_is_close_to_the_optimum():
    rng = np.random.default_rng(8)
    sg = manhattan_walk(rng, num_poses=150)
    ch = Values(sg.initial.pose_keys, chordal_poses(sg.graph, sg.initial.pose_keys))
    assert chi2(sg.graph, ch) < chi2(sg.graph, sg.initial)
    out, s = optimize(sg.graph, ch)
    ref, s2 = optimize(sg.graph, sg.initial)
    assert s.chi2_final == pytest.approx(s2.chi2_final, rel=1e-6)


def test_graph_and_io_import_no_plotting_or_reference_libraries():
    import subprocess
    import sys

    code = ("import importlib, sys\n"
            "for m in ['slam2d.graph', 'slam2d.graph.synthetic', 'slam2d.io', 'slam2d.cli.optimize']:\n"
            "    importlib.import_module(m)\n"
            "print(','.join(m for m in ['matplotlib', 'gtsam', 'g2opy', 'g2o', 'fastapi'] if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


def test_robust_kernel_per_factor_and_per_type():
    rng = np.random.default_rng(1)
    g, vals = _random_graph(rng)
    g.add_between([0], [5], [[9.0, 9.0, 3.0]], np.eye(3) * 100, robust="cauchy", robust_param=2.0)
    b = g.block("between")
    assert b.kernel[-1] == 2 and b.kernel_param[-1] == 2.0 and np.all(b.kernel[:-1] == 0)
    opt = Optimizer(g, OptimizerConfig(robust_kernel="huber", robust_param=1.5, robust_kinds=("point",)))
    _, s = opt.optimize(vals)
    work = opt.analysis.plans[[p.block.kind for p in opt.analysis.plans].index("point")].block
    assert np.all(work.kernel == 1) and np.all(g.block("point").kernel == 0)  # overridden in the optimiser's copy
    assert g.block("between").kernel[-1] == 2  # per-factor kernel kept
    assert s.cost_final < s.chi2_final  # the robust cost is below the raw chi2 when some residuals are large
