"""``slam2d run``: one estimator over a simulated scenario or a saved log; prints a table, optionally JSON."""

from __future__ import annotations

import argparse
from typing import Any

from slam2d.association import METHODS
from slam2d.cli.common import add_set_argument, overrides_from, print_table, write_json
from slam2d.lab.registry import estimator_names
from slam2d.lab.runner import run_named
from slam2d.log import Log
from slam2d.sim.scenarios import SCENARIOS

COLUMNS = ["estimator", "scenario", "seed", "steps", "ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_rad",
           "final_pose_error_m", "landmarks_estimated", "step_ms_mean", "assoc_precision", "assoc_recall"]


def register(sub: Any) -> None:
    p = sub.add_parser("run", help="run an estimator and score it",
                       description="Run an estimator over a scenario (simulated with --seed) or a saved log.")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--scenario", default=None, help=f"one of: {', '.join(sorted(SCENARIOS))} (default room)")
    src.add_argument("--log", default=None, help="a log saved by 'slam2d simulate'")
    p.add_argument("--estimator", default="dead-reckoning", help=f"one of: {', '.join(estimator_names())}")
    p.add_argument("--seed", type=int, default=0, help="seed for the simulation and the estimator (default 0)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the flat result record as JSON")
    p.add_argument("--association", default=None, choices=list(METHODS),
                   help="data association method of the estimator (estimators that associate)")
    add_set_argument(p)
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    log = Log.load(args.log) if args.log else None
    overrides: dict[str, str] = overrides_from(args)
    if args.association:
        overrides["estimator.association.method"] = args.association
    _, record = run_named(args.estimator, args.scenario or "room", seed=args.seed, overrides=overrides,
                          log=log, progress=None)
    print_table([record], [c for c in COLUMNS if c in record])
    if args.json:
        write_json(args.json, record)
    return 0
