"""Multi-robot graph SLAM on MRCLAM 7 (all five robots, one clock) against each robot's single-robot graph SLAM.

    python benchmarks/multi_robot.py --mode known-known --out OUT.json     # known starts, known ids
    python benchmarks/multi_robot.py --mode unknown-known                  # unknown relative starts, known ids
    python benchmarks/multi_robot.py --mode known-unknown                  # known starts, unknown association
    python benchmarks/multi_robot.py --mode unknown-unknown                # neither
    python benchmarks/multi_robot.py --single                              # slam2d run --robot N --estimator graph

Writes the metrics of ``slam2d.lab.multi_robot.run_multi`` (per-robot ATE, joint ATE, map error, start-transform
errors, merge decisions, wall seconds) as JSON; ``--single`` the single-robot online graph SLAM ATE of each robot
with the same loader defaults (the baseline the joint graph must not be worse than). Thresholds were chosen on
robots 1-2 (synthetic tests and the first 100 s) and are the library defaults; nothing here is tuned per robot.
Without ids the landmark factors' robust kernel has the association gate as its scale (the chi-square(2) quantile
at ``gate_probability``): no number was fitted to MRCLAM.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

MODES = {"known-known": (False, "known"), "unknown-known": (True, "known"),
         "known-unknown": (False, "mahalanobis"), "unknown-unknown": (True, "mahalanobis")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=sorted(MODES), default="known-known")
    ap.add_argument("--single", action="store_true", help="single-robot graph SLAM baselines instead")
    ap.add_argument("--max-time", type=float, default=None, help="use only the first S seconds")
    ap.add_argument("--out", default=None, help="JSON output file")
    args = ap.parse_args()
    from slam2d.io.datasets import data_dir, dataset_status, load_dataset

    # refused now, not after the (15-25 min) run: a missing dataset, an output file that cannot be written
    folder, missing = dataset_status("mrclam")
    if missing:
        ap.error(f"MRCLAM 7 not found at {folder} (data directory from {data_dir()[1]}; missing {missing[0]}"
                 f"{' and more' if len(missing) > 1 else ''}; set SLAM2D_DATA)")
    if args.max_time is not None and args.max_time <= 0:
        ap.error(f"--max-time must be > 0 (got {args.max_time})")
    if args.out:
        from slam2d.io.atomic import check_output

        try:
            check_output(args.out, "--out")
        except OSError as e:
            ap.error(f"{e.filename}: {e.strerror}")
    if args.single:
        from slam2d.lab.runner import run_named

        out: dict[str, object] = {}
        for r in (1, 2, 3, 4, 5):
            log = load_dataset("mrclam", robot=r, max_time_s=args.max_time)
            t0 = time.perf_counter()
            _, rec = run_named("graph", log=log, seed=0)
            out[str(r)] = {"ate_rmse_m": rec["ate_rmse_m"], "seconds": time.perf_counter() - t0}
            print(r, out[str(r)], flush=True)
    else:
        from slam2d.lab.multi_robot import run_multi

        unknown_starts, association = MODES[args.mode]
        mlog = load_dataset("mrclam", robot="all", max_time_s=args.max_time)
        res = run_multi(mlog, unknown_starts=unknown_starts, association=association, seed=0)
        out = {"mode": args.mode, **res.metrics}
        print(json.dumps(out, indent=1, default=float))
    if args.out:
        path = Path(args.out)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(out, indent=1, default=float) + "\n")
        tmp.replace(path)


if __name__ == "__main__":
    main()
