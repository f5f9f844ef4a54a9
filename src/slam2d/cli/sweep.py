"""``slam2d sweep CONFIG.toml --out DIR``: run configurations x seeds, locally or on a Dask cluster, resumably."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slam2d.io.atomic import check_output
from slam2d.lab.sweep import STORE_FILE, load_sweep, make_executor, run_sweep


def register(sub: Any) -> None:
    p = sub.add_parser(
        "sweep", help="run a sweep of configurations x seeds (resumable)",
        description="Run every (configuration, seed) of a sweep TOML file and store one JSON record per run in "
                    "DIR/results.jsonl. Runs already stored are skipped, so re-running after an interruption "
                    "finishes only the missing ones. Local processes by default; a Dask cluster with --scheduler "
                    "(or DASK_SCHEDULER_ADDRESS).")
    p.add_argument("config", metavar="CONFIG.toml", help="sweep description (estimators, scenarios, seeds, set, "
                                                          "grid, configs)")
    p.add_argument("--out", required=True, metavar="DIR", help="result directory (created; resumed if it exists)")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: CPU count)")
    p.add_argument("--scheduler", default=None, metavar="ADDR",
                   help="Dask scheduler address, e.g. tcp://127.0.0.1:8786 (default: $DASK_SCHEDULER_ADDRESS, "
                        "else local processes)")
    p.add_argument("--dry-run", action="store_true", help="validate and list the runs, run nothing")
    bar = p.add_mutually_exclusive_group()
    bar.add_argument("--progress", dest="progress", action="store_true", default=None,
                     help="always show the progress bar (default: when stderr is a terminal)")
    bar.add_argument("--no-progress", dest="progress", action="store_false")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(20, "is a file, not a result directory", f"--out {out}")
    if not (out / STORE_FILE).is_dir():  # a directory there is quarantined by the store
        check_output(out / STORE_FILE, "--out")
    plan = load_sweep(args.config)  # validates every expanded configuration before anything runs
    if args.dry_run:
        for s in plan.specs:
            print(f"{s.key}  {s.label()}")
        print(f"{len(plan.specs)} configs x {len(plan.seeds)} seeds = {len(plan.jobs())} runs")
        return 0
    with make_executor(args.workers, args.scheduler) as ex:
        summary = run_sweep(plan, args.out, ex, progress=args.progress, report=print)
    print(f"ran {summary.ran} runs ({summary.errors} with errors); {summary.already_done + summary.ran} of "
          f"{summary.total} stored in {args.out}")
    if summary.interrupted:
        return 130
    return 0 if summary.complete else 1
