"""``slam2d simulate``: write a scenario's Log to disk."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from slam2d.cli.common import add_set_argument, check_number, check_outputs, overrides_from
from slam2d.config import with_overrides
from slam2d.io.atomic import atomic_write
from slam2d.io.survey import write_marker_survey
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.simulator import simulate
from slam2d.sim.world import marker_survey


def register(sub: Any) -> None:
    p = sub.add_parser("simulate", help="simulate a scenario and save the log (.npz)",
                       description="Simulate a scenario with a seed and save the Log (npz + JSON metadata).")
    p.add_argument("--scenario", default="room", help=f"one of: {', '.join(sorted(SCENARIOS))} (default room)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", required=True, help="output file (.npz)")
    p.add_argument("--marker-survey", default=None, metavar="OUT.csv",
                   help="also write the world's floor markers as a survey gives them (id,x,y; each position off the "
                        "truth by --survey-sigma per axis), for 'slam2d run --marker-survey'")
    p.add_argument("--survey-sigma", type=float, default=0.01, metavar="M",
                   help="survey error per axis (m, default 0.01)")
    add_set_argument(p)
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    check_number("--seed", args.seed, low=0, high=2**63 - 1)
    check_number("--survey-sigma", args.survey_sigma, low=0)
    check_outputs(args, [], [("--out", args.out), ("--marker-survey", args.marker_survey)])
    if not args.out.lower().endswith(".npz"):  # a .txt name would hold a binary archive
        raise ValueError(f"--out {args.out}: the log is written as a NumPy .npz archive; give a name ending in .npz")
    cfg = with_overrides(ScenarioConfig(name=args.scenario), overrides_from(args))
    log = simulate(cfg, args.seed)
    if args.marker_survey and (log.true_markers is None or not len(log.true_markers)):
        raise ValueError(f"--marker-survey: scenario {cfg.name!r} has no floor markers here (a warehouse scenario "
                         "with --set warehouse.floor_markers=true has); nothing written")
    with atomic_write(args.out, "wb") as fh:
        log.write_npz(fh)
    print(f"wrote {args.out}: {log.num_steps} steps, {len(log.obs_step)} observations, "
          f"{0 if log.true_landmarks is None else len(log.true_landmarks)} landmarks")
    if args.marker_survey:
        assert log.true_markers is not None
        # its own generator (seed, 17): the simulation's streams are untouched, as in benchmarks/warehouse_shift.py
        survey = marker_survey(log.true_markers, args.survey_sigma, np.random.default_rng([args.seed, 17]))
        write_marker_survey(args.marker_survey, survey)
        print(f"wrote {args.marker_survey}: {len(survey)} floor markers, survey error {args.survey_sigma:g} m per axis")
    return 0
