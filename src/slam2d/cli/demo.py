"""``slam2d demo``: every estimator on one scenario, a results table and a figure (what ``make run`` shows)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slam2d.cli.common import check_number, check_outputs, print_table, write_json
from slam2d.cli.run import COLUMNS
from slam2d.io.atomic import atomic_path
from slam2d.lab.registry import estimator_names, get_spec
from slam2d.lab.runner import check_inputs, run_named
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.simulator import simulate


def register(sub: Any) -> None:
    p = sub.add_parser("demo", help="run every estimator on a scenario; print a table and write a figure",
                       description="Run every registered estimator on one scenario and seed, print a results "
                                   "table, and write a figure of true vs estimated paths and maps.")
    p.add_argument("--scenario", default="room", help=f"one of: {', '.join(sorted(SCENARIOS))} (default room)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulation and of every estimator (default 0)")
    p.add_argument("--out", default="out", help="output folder for demo.png and demo.json (default out/)")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    check_number("--seed", args.seed, low=0, high=2**63 - 1)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(20, "--out must be a folder", str(out))
    check_outputs(args, [], [("--out", out / "demo.json")])
    log = simulate(ScenarioConfig(name=args.scenario), args.seed)
    rows, results = [], {}
    for name in estimator_names():
        try:
            check_inputs(get_spec(name), log)
        except ValueError as e:  # e.g. lidar in a world without walls: no row rather than a dead-reckoned one
            print(f"skipped: {e}")
            continue
        result, record = run_named(name, log=log, seed=args.seed)
        rows.append(record)
        results[name] = result
    print_table(rows, COLUMNS)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "demo.json", {"runs": [{k: v for k, v in r.items() if not k.endswith("_config")}
                                            for r in rows]})
    from slam2d.viz.figures import save_runs_figure

    with atomic_path(out / "demo.png") as tmp:
        save_runs_figure(log, results, tmp)
    path = out / "demo.png"
    print(f"wrote {path} and {out / 'demo.json'}")
    return 0
