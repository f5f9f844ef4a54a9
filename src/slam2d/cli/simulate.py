"""``slam2d simulate``: write a scenario's Log to disk."""

from __future__ import annotations

import argparse
from typing import Any

from slam2d.cli.common import add_set_argument, check_number, check_outputs, overrides_from
from slam2d.config import with_overrides
from slam2d.io.atomic import atomic_write
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.simulator import simulate


def register(sub: Any) -> None:
    p = sub.add_parser("simulate", help="simulate a scenario and save the log (.npz)",
                       description="Simulate a scenario with a seed and save the Log (npz + JSON metadata).")
    p.add_argument("--scenario", default="room", help=f"one of: {', '.join(sorted(SCENARIOS))} (default room)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", required=True, help="output file (.npz)")
    add_set_argument(p)
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    check_number("--seed", args.seed, low=0, high=2**63 - 1)
    check_outputs(args, [], [("--out", args.out)])
    cfg = with_overrides(ScenarioConfig(name=args.scenario), overrides_from(args))
    log = simulate(cfg, args.seed)
    with atomic_write(args.out, "wb") as fh:
        log.write_npz(fh)
    print(f"wrote {args.out}: {log.num_steps} steps, {len(log.obs_step)} observations, "
          f"{0 if log.true_landmarks is None else len(log.true_landmarks)} landmarks")
    return 0
