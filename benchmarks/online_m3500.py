"""Online pose-graph optimisation on M3500: one pose and its edges per step, slam2d vs GTSAM iSAM2.

slam2d's scheme is ``slam2d.graph.incremental.IncrementalPoseGraph``: each step appends the new pose (initialised by
composing its odometry edge) and its edges; a step that brings a loop closure solves a local problem (the newest
``--window`` poses and the neighbourhood of the old loop endpoints free, the boundary held), and every
``--full-every`` steps one whole-graph Gauss-Newton iteration spreads the corrections. At the end both systems are
compared with the batch optimum of the same graph (g2o chi2, first pose held).

Run: OPENBLAS_NUM_THREADS=1 python benchmarks/online_m3500.py [--window W] [--full-every K] [--limit N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.incremental import IncrementalConfig, IncrementalPoseGraph
from slam2d.graph.optimizer import OptimizerConfig, optimize
from slam2d.graph.problem import chi2
from slam2d.io import read_graph

DATA = (Path(os.environ.get("SLAM2D_DATA") or Path(__file__).resolve().parents[2] / "shared" / "datasets")
        / "manhattan-m3500" / "input_M3500_g2o.g2o")


def steps_of(block):
    """Edges grouped by the newer pose they bring: dict t -> edge indices."""
    newer = np.maximum(block.keys[0], block.keys[1])
    order = np.argsort(newer, kind="stable")
    bounds = np.searchsorted(newer[order], np.arange(newer.max() + 2))
    return order, bounds


def run_slam2d(block, n, cfg):
    order, bounds = steps_of(block)
    info = block.information
    inc = IncrementalPoseGraph(np.zeros(3), cfg)
    times = []
    for t in range(1, n):
        t0 = time.perf_counter()
        idx = order[bounds[t]:bounds[t + 1]]
        inc.add_step(t, block.keys[0][idx], block.keys[1][idx], block.z[idx], info[idx])
        times.append(time.perf_counter() - t0)
    online = chi2(inc.graph(), Values(np.arange(n), inc.poses))
    inc.finalize()
    return np.array(times), online, chi2(inc.graph(), Values(np.arange(n), inc.poses)), inc


def run_isam2(block, n):
    import gtsam

    order, bounds = steps_of(block)
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    est = gtsam.Pose2(0, 0, 0)
    times = []
    first = gtsam.NonlinearFactorGraph()
    first.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(0, 0, 0), gtsam.noiseModel.Constrained.All(3)))
    v0 = gtsam.Values()
    v0.insert(0, est)
    isam.update(first, v0)
    for t in range(1, n):
        t0 = time.perf_counter()
        idx = order[bounds[t]:bounds[t + 1]]
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        prev = isam.calculateEstimatePose2(t - 1)
        init = prev
        for e in idx:
            i, j = int(block.keys[0][e]), int(block.keys[1][e])
            z = gtsam.Pose2(*block.z[e])
            g.add(gtsam.BetweenFactorPose2(i, j, z, gtsam.noiseModel.Gaussian.Information(block.information[e])))
            if i == t - 1 and j == t:
                init = prev.compose(z)
        vals.insert(t, init)
        isam.update(g, vals)
        times.append(time.perf_counter() - t0)
    result = isam.calculateEstimate()
    poses = np.array([[result.atPose2(k).x(), result.atPose2(k).y(), result.atPose2(k).theta()] for k in range(n)])
    return np.array(times), poses


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=int, default=30)
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--full-every", type=int, default=500)
    ap.add_argument("--limit", type=int, default=0, help="use only the first N poses (0: all)")
    args = ap.parse_args()
    for flag, v, lo in (("--window", args.window, 1), ("--iterations", args.iterations, 1),
                        ("--full-every", args.full_every, 1), ("--limit", args.limit, 0)):
        if v < lo:
            ap.error(f"{flag} must be >= {lo} (got {v})")
    if args.limit == 1:
        ap.error("--limit must be 0 (all poses) or >= 2")
    if not DATA.exists():
        print(f"dataset not found: {DATA} (set SLAM2D_DATA); skipped")
        return 0
    gf = read_graph(DATA)
    block = gf.graph.block("between")
    n = int(args.limit or block.keys.max() + 1)
    if args.limit:
        keep = np.maximum(block.keys[0], block.keys[1]) < n
        from dataclasses import replace

        block = replace(block, keys=block.keys[:, keep], z=block.z[keep], sqrt_info=block.sqrt_info[keep],
                        kernel=block.kernel[keep], kernel_param=block.kernel_param[keep])
    batch_graph = FactorGraph()
    batch_graph.add_between(block.keys[0], block.keys[1], block.z, block.information)
    init = gf.values if not args.limit else Values(np.arange(n), gf.values.poses[:n])
    _, summary = optimize(batch_graph, init, OptimizerConfig(method="lm"))
    batch = summary.chi2_final
    cfg = IncrementalConfig(window=args.window, iterations=args.iterations, full_every=args.full_every)
    times, online, final, inc = run_slam2d(block, n, cfg)
    print(f"M3500 online, {n} poses, {block.size} edges; batch chi2 {batch:.4f}")
    print(f"slam2d: {inc.local_solves} local solves, {inc.full_solves - 1} whole-graph solves while driving; "
          f"chi2 of the online estimate before finalize {online:.4f} ({online / batch - 1:+.2%} vs batch)")
    print(f"{'system':<28} {'mean ms':>8} {'p99 ms':>8} {'max ms':>8} {'final chi2':>12} {'vs batch':>9}")
    label = f"slam2d incremental (w={cfg.window})"
    print(f"{label:<28} {1e3 * times.mean():8.2f} "
          f"{1e3 * np.percentile(times, 99):8.2f} {1e3 * times.max():8.2f} {final:12.4f} {final / batch - 1:+9.2%}")
    try:
        it, poses = run_isam2(block, n)
        vals = Values(np.arange(n), poses)
        c = chi2(batch_graph, vals)
        print(f"{'GTSAM iSAM2':<28} {1e3 * it.mean():8.2f} {1e3 * np.percentile(it, 99):8.2f} "
              f"{1e3 * it.max():8.2f} {c:12.4f} {c / batch - 1:+9.2%}")
    except ImportError:
        print("GTSAM not installed: iSAM2 comparison skipped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
