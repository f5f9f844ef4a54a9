"""False loop closures vs robust kernels on a synthetic Manhattan-style pose graph (numbers for the note).

Prints ATE (m, after SE(2) alignment) and the chi2 of the TRUE factors (odometry + true loop closures) for: the clean
graph, the graph with generated false loop closures and no kernel, and with each robust kernel.
Usage: python benchmarks/robust_outliers.py [--poses 400] [--outliers 20] [--seed 21]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from slam2d.eval.trajectory import ate
from slam2d.graph import OptimizerConfig, optimize
from slam2d.graph.problem import factor_chi2
from slam2d.graph.synthetic import false_loop_closures, manhattan_walk


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", type=int, default=400)
    ap.add_argument("--outliers", type=int, default=20)
    ap.add_argument("--seed", type=int, default=21)
    a = ap.parse_args(argv)
    if a.poses < 2:
        ap.error(f"--poses must be >= 2 (got {a.poses})")
    if a.outliers < 0:
        ap.error(f"--outliers must be >= 0 (got {a.outliers})")
    rng = np.random.default_rng(a.seed)
    sg = manhattan_walk(rng, num_poses=a.poses)
    n_in = sg.graph.block("between").size
    clean, s = optimize(sg.graph, sg.initial)
    print(f"{a.poses} poses, {sg.num_loop_closures} true loop closures, {a.outliers} false ones; "
          f"odometry-chain start ATE {ate(sg.initial.poses, sg.truth.poses).rmse_m:.4f} m")
    print(f"{'case':22s} {'ATE m':>9s} {'chi2 true factors':>18s} {'iterations':>10s}")
    print(f"{'clean, no kernel':22s} {ate(clean.poses, sg.truth.poses).rmse_m:9.4f} {s.chi2_final:18.2f} "
          f"{s.iterations:10d}")
    i, j, z = false_loop_closures(rng, a.poses, a.outliers)
    sg.graph.add_between(i, j, z, np.diag(1.0 / np.square(sg.sigmas)))
    for kernel, param in ((None, 1.0), ("huber", 1.0), ("cauchy", 1.0), ("cauchy", 3.0), ("dcs", 1.0),
                          ("dcs", 10.0), ("dcs", 100.0)):
        cfg = OptimizerConfig(robust_kernel=kernel or "none", robust_param=param, max_iterations=200)
        est, s = optimize(sg.graph, sg.initial, cfg)
        name = f"outliers, {kernel}:{param:g}" if kernel else "outliers, no kernel"
        print(f"{name:22s} {ate(est.poses, sg.truth.poses).rmse_m:9.4f} "
              f"{factor_chi2(sg.graph, est, 'between')[:n_in].sum():18.2f} {s.iterations:10d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
