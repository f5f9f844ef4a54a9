"""Floor markers in the lidar back end: the warehouse drive with and without marker readings, seed by seed.

    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_markers.py                       # README, "Floor markers"
    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_markers.py --steps 600 --seeds 5-8   # a single pass

Each seed simulates the ``warehouse`` scenario with floor markers (``floor_markers=true``: a marker every 10 m along
each aisle, read by the downward camera) and runs the default ``lidar`` estimator twice on the same log: with the
readings, and with ``markers.enabled=false`` (the readings ignored, the back end as without markers). Per run: ATE
RMSE, the end-of-run position error, accepted loops and false ones (the runner's rule: poses truly > 16 m apart or
a measurement off the truth by > 1 m). ``--workers`` runs seeds in parallel processes (results do not depend on it).
"""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from typing import Any


def one_seed(seed: int, steps: int) -> dict[str, Any]:
    from slam2d.config import with_overrides
    from slam2d.lab.runner import run_named
    from slam2d.sim import ScenarioConfig, simulate

    log = simulate(with_overrides(ScenarioConfig(name="warehouse"), {"floor_markers": "true", "steps": str(steps)}),
                   seed)
    out: dict[str, Any] = {"seed": seed, "steps": steps}
    for name, over in (("markers", {}), ("no_markers", {"markers.enabled": "false"})):
        res, _ = run_named("lidar", None, seed=seed, overrides=over, log=log)
        m = res.metrics
        out[name] = {"ate_m": m["ate_rmse_m"], "end_error_m": m["final_pose_error_m"],
                     "loops": m.get("loops_accepted", 0), "false_loops": m.get("loops_false", 0)}
    return out


def seeds_arg(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("1-8"), help="seed range, e.g. 1-8")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=None, help="write every run's record here")
    args = ap.parse_args()
    if not args.seeds:
        ap.error("--seeds: the range is empty (write it low-high, e.g. 1-8)")
    if args.steps < 1:
        ap.error(f"--steps must be >= 1 (got {args.steps})")
    if args.workers < 1:
        ap.error(f"--workers must be >= 1 (got {args.workers})")
    if args.json:  # refused now, not after the runs
        from slam2d.io.atomic import check_output

        try:
            check_output(args.json, "--json")
        except OSError as e:
            ap.error(f"{e.filename}: {e.strerror}")
    with ProcessPoolExecutor(args.workers) as ex:
        rows = list(ex.map(one_seed, args.seeds, [args.steps] * len(args.seeds)))
    print(f"warehouse, floor markers, {args.steps} steps, default lidar estimator; with / without the readings")
    print(f"{'seed':>4}  {'ATE (m)':>15}  {'end error (m)':>15}  {'loops (false)':>17}")
    for r in rows:
        on, off = r["markers"], r["no_markers"]
        print(f"{r['seed']:>4}  {on['ate_m']:6.2f} / {off['ate_m']:6.2f}  {on['end_error_m']:6.2f} / "
              f"{off['end_error_m']:6.2f}  {on['loops']:3d} ({on['false_loops']}) / {off['loops']:3d} "
              f"({off['false_loops']})")
    for k in ("markers", "no_markers"):
        a = [r[k]["ate_m"] for r in rows]
        e = [r[k]["end_error_m"] for r in rows]
        f = sum(r[k]["false_loops"] for r in rows)
        print(f"{k:>10}: ATE {min(a):.2f}-{max(a):.2f} m, end error {min(e):.2f}-{max(e):.2f} m, false loops {f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
