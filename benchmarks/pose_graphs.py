"""slam2d vs GTSAM (LM) and g2o (GN via the ``g2opy`` wheel, if it imports) on intel, M3500 and city10000.

g2o runs exactly as many GN iterations as slam2d's GN needed (g2o's optimize(n) has no convergence test), with
its Eigen sparse LDL^T block solver (the wheel has no CHOLMOD/CSparse).

One process, runs alternate between the libraries (so machine load hits all of them alike), medians printed with
ratios. Timed: the optimisation only (graph construction / file parsing excluded for everyone; slam2d's time
includes its symbolic analysis). Also printed: slam2d time / (linear solves x one numeric factorisation), i.e. how
close the Python side is to the linear-algebra floor, and the factorisation time of each available linear solver.

Usage: OPENBLAS_NUM_THREADS=1 python benchmarks/pose_graphs.py [--repeats 3] [--datasets intel,m3500,city]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

from slam2d.graph import OptimizerConfig, Values, chi2, optimize
from slam2d.graph.linear import available_solvers, make_solver
from slam2d.graph.problem import Analysis
from slam2d.io import read_graph

DATA = Path(os.environ.get("SLAM2D_DATA", Path(__file__).resolve().parents[2] / "shared" / "datasets"))
DATASETS = {
    "intel": DATA / "intel-g2o" / "intel.g2o",
    "m3500": DATA / "manhattan-m3500" / "input_M3500_g2o.g2o",
    "city": DATA / "city10000" / "city10000.g2o",
}
REL_TOL = 1e-7  # the same relative-decrease tolerance for slam2d and GTSAM


def gtsam_runner(gf):
    try:
        import gtsam
    except ImportError:
        return None
    b = gf.graph.block("between")
    om = b.information
    g = gtsam.NonlinearFactorGraph()
    for k in range(b.size):
        g.add(gtsam.BetweenFactorPose2(int(b.keys[0, k]), int(b.keys[1, k]), gtsam.Pose2(*b.z[k]),
                                       gtsam.noiseModel.Gaussian.Information(om[k])))
    k0 = int(gf.values.pose_keys[0])
    g.add(gtsam.NonlinearEqualityPose2(k0, gtsam.Pose2(*gf.values.pose(k0))))
    init = gtsam.Values()
    for key, p in zip(gf.values.pose_keys, gf.values.poses, strict=True):
        init.insert(int(key), gtsam.Pose2(*p))

    def run():
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(REL_TOL)
        params.setAbsoluteErrorTol(1e-9)
        params.setMaxIterations(100)
        t = time.perf_counter()
        opt = gtsam.LevenbergMarquardtOptimizer(g, init, params)
        res = opt.optimize()
        dt = time.perf_counter() - t
        poses = np.array([[res.atPose2(int(k)).x(), res.atPose2(int(k)).y(), res.atPose2(int(k)).theta()]
                          for k in gf.values.pose_keys])
        return dt, opt.iterations(), chi2(gf.graph, Values(gf.values.pose_keys, poses))

    return run


def g2o_runner(gf, iterations):
    try:
        import g2opy as g2o  # the "g2opy" wheel (pip install g2opy)
    except ImportError:
        return None

    def run():
        opt = g2o.SparseOptimizer()
        opt.set_algorithm(g2o.OptimizationAlgorithmGaussNewton(g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())))
        k0 = int(gf.values.pose_keys[0])
        for key, p in zip(gf.values.pose_keys, gf.values.poses, strict=True):
            v = g2o.VertexSE2()
            v.set_id(int(key))
            v.set_estimate(g2o.SE2(*p))
            v.set_fixed(bool(key == k0))
            opt.add_vertex(v)
        b = gf.graph.block("between")
        om = b.information
        for f in range(b.size):
            e = g2o.EdgeSE2()
            e.set_vertex(0, opt.vertex(int(b.keys[0, f])))
            e.set_vertex(1, opt.vertex(int(b.keys[1, f])))
            e.set_measurement(g2o.SE2(*b.z[f]))
            e.set_information(np.ascontiguousarray(om[f]))
            opt.add_edge(e)
        t = time.perf_counter()
        opt.initialize_optimization()
        opt.optimize(iterations)
        dt = time.perf_counter() - t
        return dt, iterations, opt.chi2()

    return run


def factorisation_runners(gf):
    """One numeric refactorisation per available solver (symbolic work done beforehand), as alternating runners."""
    an = Analysis(gf.graph, gf.values)
    _, _, data, _ = an.linearize(gf.values.poses, gf.values.points)
    up = an.upper(data)
    out = {}
    for name in available_solvers():
        if name == "dense":
            continue
        s = make_solver(name)
        s.factorize(up)  # symbolic work on the first call

        def run(s=s):
            t = time.perf_counter()
            s.factorize(up)
            return time.perf_counter() - t, 1, float("nan")

        out[f"factor {name}"] = run
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--datasets", default="intel,m3500,city", help=f"comma-separated, of {', '.join(DATASETS)}")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1 (got {args.repeats})")
    bad = [n for n in args.datasets.split(",") if n not in DATASETS]
    if bad:
        ap.error(f"--datasets: unknown {', '.join(map(repr, bad))}; known: {', '.join(DATASETS)}")
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}  python {sys.version.split()[0]}  "
          f"numpy {np.__version__}")
    for name in args.datasets.split(","):
        path = DATASETS[name]
        if not path.exists():
            print(f"{name}: dataset missing ({path}), skipped")
            continue
        gf = read_graph(path)
        runners = {
            "slam2d LM": lambda gf=gf: _slam(gf, "lm"),
            "slam2d GN": lambda gf=gf: _slam(gf, "gn"),
            "slam2d DL": lambda gf=gf: _slam(gf, "dogleg"),
        }
        g = gtsam_runner(gf)
        if g:
            runners["GTSAM LM"] = g
        gn_iters = _slam(gf, "gn")[1]
        o = g2o_runner(gf, gn_iters)
        if o:
            runners["g2o GN"] = o
        facs = factorisation_runners(gf)
        runners.update(facs)
        times = {k: [] for k in runners}
        info = {}
        for _ in range(args.repeats):
            for k, run in runners.items():  # alternate
                dt, it, c2 = run()
                times[k].append(dt)
                info[k] = (it, c2)
        med = {k: statistics.median(v) for k, v in times.items()}
        print(f"\n== {name}: {path.name}  ({gf.values.pose_keys.size} poses, {gf.graph.num_factors} factors)")
        print("   one numeric factorisation: " + ", ".join(f"{k[7:]} {med[k] * 1e3:.1f} ms" for k in facs))
        for k in runners:
            if k in facs:
                continue
            it, c2 = info[k]
            line = f"   {k:10s} median {med[k]:.3f} s  iterations {it:3d}  chi2 {c2:.10g}"
            if k.startswith("slam2d"):
                floor = it * med.get("factor qdldl", float("nan"))
                line += f"  time/(iterations x factorisation) {med[k] / floor:.2f}"
            print(line)
        for ref in ("GTSAM LM", "g2o GN"):
            if ref in med:
                print(f"   ratio slam2d LM / {ref}: {med['slam2d LM'] / med[ref]:.2f}   "
                      f"slam2d GN / {ref}: {med['slam2d GN'] / med[ref]:.2f}")
    return 0


def _slam(gf, method):
    t = time.perf_counter()
    _, s = optimize(gf.graph, gf.values, OptimizerConfig(method=method, relative_decrease_tol=REL_TOL))
    return time.perf_counter() - t, s.linear_solves, s.chi2_final


if __name__ == "__main__":
    sys.exit(main())
