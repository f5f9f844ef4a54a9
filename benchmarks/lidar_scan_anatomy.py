"""Where the lidar back end's slowest scans spend their time: tracking, verification stages, loops entering the graph.

    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_scan_anatomy.py --log fr079
    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_scan_anatomy.py --log mit-csail --over-ms 30 --show 40

Runs one log with the default ``lidar`` estimator and times, per scan (CPU time of the thread): the whole ``step``,
tracking (``track_scan``), each verification stage (its kind and whether it ran because its candidate was due:
"finished at once"), the graph updates of loops entering (``add_loop``) and whole-graph iterations
(``solve_full``). Prints the scans over ``--over-ms`` by what they contained, then the slowest ``--show`` of them,
one line each. The wrappers time the estimator's own methods; they change nothing it computes.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from typing import Any

import numpy as np


def anatomy(name: str) -> list[dict[str, Any]]:
    import slam2d.graph.lidar as lidar
    from slam2d.cli.lidar import load_laser_log
    from slam2d.graph.incremental import IncrementalPoseGraph
    from slam2d.lab.registry import make_estimator
    from slam2d.lab.runner import run

    cur: dict[str, Any] = {}
    records: list[dict[str, Any]] = []

    def timed(fn: Any, key: str) -> Any:
        def wrapper(*a: Any, **k: Any) -> Any:
            t = time.thread_time()
            out = fn(*a, **k)
            cur[key] = cur.get(key, 0.0) + 1e3 * (time.thread_time() - t)
            return out
        return wrapper

    saved = (lidar.track_scan, IncrementalPoseGraph.add_loop, IncrementalPoseGraph.solve_full)
    lidar.track_scan = timed(lidar.track_scan, "track")  # type: ignore[assignment]
    IncrementalPoseGraph.add_loop = timed(IncrementalPoseGraph.add_loop, "add_loop")  # type: ignore[method-assign]
    IncrementalPoseGraph.solve_full = timed(IncrementalPoseGraph.solve_full, "solve_full")  # type: ignore[method-assign]
    try:
        log = load_laser_log(name)
        est: Any = make_estimator("lidar", {})  # its private scheduler state is read below
        step = est.step

        def timed_step(s: Any) -> None:
            cur.clear()
            cur.update(stages=[], forced=0)
            record = est._stage_costs.record

            def stage(kind: str, ms: float) -> None:
                cur["stages"].append((kind, ms))
                active = est._active
                cur["forced"] += active is not None and active[3] <= est.steps
                record(kind, ms)

            est._stage_costs.record = stage
            t = time.thread_time()
            step(s)
            cur["total"] = 1e3 * (time.thread_time() - t)
            est._stage_costs.record = record
            records.append(dict(cur))

        est.step = timed_step
        run(est, log, rng=np.random.default_rng(0), progress=False)
    finally:
        lidar.track_scan, IncrementalPoseGraph.add_loop, IncrementalPoseGraph.solve_full = saved  # type: ignore[assignment,method-assign]
    return records


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--log", default="fr079", help="Radish log (default fr079)")
    ap.add_argument("--over-ms", type=float, default=30.0, help="scans slower than this are described (ms)")
    ap.add_argument("--show", type=int, default=25, help="print this many of the slowest scans")
    args = ap.parse_args()
    if args.show < 0:
        ap.error(f"--show must be >= 0 (got {args.show})")
    from slam2d.io.carmen import resolve_carmen

    try:
        resolve_carmen(args.log)  # a missing or unknown log in one line
    except FileNotFoundError as e:
        ap.error(str(e))
    recs = anatomy(args.log)
    total = np.array([r["total"] for r in recs])
    print(f"{args.log}: {len(total)} scans, CPU per scan p50 {np.percentile(total, 50):.1f} p99 "
          f"{np.percentile(total, 99):.1f} max {total.max():.1f} ms; over {args.over_ms:g} ms: "
          f"{int((total > args.over_ms).sum())}")
    slow = np.argsort(-total)[: int((total > args.over_ms).sum())]
    kinds: Counter[str] = Counter()
    for i in slow:
        r = recs[i]
        parts = [p for p, on in (("finished at once", r["forced"]), ("loops entered", r.get("add_loop")),
                                 ("whole-graph iteration", r.get("solve_full"))) if on]
        kinds[" + ".join(parts) or "tracking and budgeted stages"] += 1
    for k, n in kinds.most_common():
        print(f"  {n:4d}  {k}")
    for i in slow[: args.show]:
        r = recs[i]
        st = r["stages"]
        print(f"{total[i]:6.1f} ms: tracking {r.get('track', 0):5.1f}, {len(st):2d} stages {sum(m for _, m in st):5.1f}"
              f" ({r['forced']} finished at once), loops entering {r.get('add_loop', 0):5.1f}, whole-graph"
              f" {r.get('solve_full', 0):5.1f}; longest stage {max(st, key=lambda x: x[1], default=('-', 0))}")


if __name__ == "__main__":
    main()
