"""``slam2d experiment NAME``: run a named experiment over seeds, print its table, optionally write JSON.

Experiments are registered in ``EXPERIMENTS`` (name -> function). Each function takes the parsed seeds and the
``--set KEY=VALUE`` overrides (validated against the experiment's own config) and returns an :class:`ExperimentOutput`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from slam2d.cli.common import add_set_argument, overrides_from, print_table, write_json


@dataclass(frozen=True)
class ExperimentOutput:
    """What an experiment hands back to the command: table rows, the columns to print, and the JSON record."""

    rows: list[dict[str, Any]]
    columns: list[str]
    record: dict[str, Any]
    title: str = ""


def _association(seeds: Sequence[int], overrides: Mapping[str, str]) -> ExperimentOutput:
    from slam2d.config import with_overrides
    from slam2d.lab.association_experiment import (
        AssociationExperimentConfig,
        run_association_experiment,
        summary_record,
    )

    cfg = with_overrides(AssociationExperimentConfig(), dict(overrides)) if overrides else AssociationExperimentConfig()
    result = run_association_experiment(cfg, seeds)
    cols = ["method", "precision", "recall", "false_new_rate", "missed_new_rate", "precision_seed_min",
            "recall_seed_min", "matches", "ms_per_call"]
    title = (f"data association on '{cfg.scenario}': {len(result.seeds)} seeds x {cfg.snapshots_per_seed} snapshots, "
             f"pose error std {cfg.pose_std_xy_m} m / {cfg.pose_std_theta_rad} rad, "
             f"{cfg.unmapped_fraction:.0%} of landmarks unmapped (pooled ratios; *_seed_min = worst seed)")
    return ExperimentOutput(result.rows(), cols, summary_record(result), title)


#: experiment name -> function(seeds, overrides) -> ExperimentOutput; add new experiments here
EXPERIMENTS: dict[str, Callable[[Sequence[int], Mapping[str, str]], ExperimentOutput]] = {
    "association": _association,
}


def register(sub: Any) -> None:
    p = sub.add_parser("experiment", help="run a named experiment over seeds and print its table",
                       description="Run a named experiment over several seeds; print a table; --json writes the "
                                   "numbers and the config used.")
    p.add_argument("name", choices=sorted(EXPERIMENTS), help="which experiment")
    p.add_argument("--seeds", type=int, default=20, help="number of seeds (default 20)")
    p.add_argument("--first-seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--json", dest="json_out", metavar="OUT", help="write the results as JSON to OUT")
    add_set_argument(p)
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        raise ValueError(f"--seeds must be >= 1 (got {args.seeds})")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    out = EXPERIMENTS[args.name](seeds, overrides_from(args))
    if out.title:
        print(out.title)
    print_table(out.rows, out.columns)
    if args.json_out:
        write_json(args.json_out, out.record)
        print(f"wrote {args.json_out}")
    return 0
