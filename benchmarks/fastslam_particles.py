"""FastSLAM 2.0 needs fewer particles than 1.0: ATE on ``room`` (known association) versus particle count.

Runs both versions for M in {5, 10, 25, 50, 100} over 5 seeds (the same simulated logs for both) and prints the
mean and worst ATE per cell, next to dead reckoning. Takes a few minutes on 2 cores; ``--quick`` runs 2 seeds.

    python benchmarks/fastslam_particles.py
"""

from __future__ import annotations

import argparse

import numpy as np

import slam2d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 seeds instead of 5")
    ap.add_argument("--scenario", default="room")
    ap.add_argument("--method", default="known", help="association method (known, or e.g. mahalanobis = ML)")
    args = ap.parse_args()
    from slam2d.lab.registry import make_config
    from slam2d.sim.scenarios import SCENARIOS

    if args.scenario not in SCENARIOS:
        ap.error(f"--scenario: unknown {args.scenario!r}; scenarios: {', '.join(sorted(SCENARIOS))}")
    try:
        make_config("fastslam2", {"association.method": args.method})
    except ValueError as e:
        ap.error(f"--method: {e}")
    seeds = range(2 if args.quick else 5)
    ms = [5, 10, 25, 50, 100]
    logs = {s: slam2d.simulate(args.scenario, s) for s in seeds}
    dr = [slam2d.run_named("dead-reckoning", log=logs[s], seed=s)[1]["ate_rmse_m"] for s in seeds]
    print(f"scenario {args.scenario}, association {args.method}, seeds {list(seeds)}; "
          f"dead reckoning ATE mean {np.mean(dr):.3f} m")
    print(f"{'M':>4} | {'fastslam (1.0) ATE mean / max':>30} | {'fastslam2 (2.0) ATE mean / max':>30}")
    for m in ms:
        cells = []
        for est in ("fastslam", "fastslam2"):
            a = [slam2d.run_named(est, log=logs[s], seed=s, overrides={"particles": m, "association.method":
                                                                        args.method})[1]["ate_rmse_m"]
                 for s in seeds]
            cells.append(f"{np.mean(a):>17.3f} / {np.max(a):.3f} m")
        print(f"{m:>4} | {cells[0]:>30} | {cells[1]:>30}", flush=True)


if __name__ == "__main__":
    main()
