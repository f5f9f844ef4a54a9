"""``slam2d experiment scaling|consistency``: the lab experiments of :mod:`slam2d.lab.experiments`.

``EXPERIMENTS`` maps a name to an :class:`Experiment` (help text, ``add_arguments(parser)``, ``run(args) -> int``;
calling it with an argv list parses and runs). ``register`` adds an ``experiment`` command with one sub-command
per entry when no other module has claimed that name yet; :func:`add_to` adds the entries to an existing
``experiment`` command's sub-parsers, so two experiment catalogues can share one command.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slam2d.cli.common import add_set_argument, overrides_from, print_table


@dataclass(frozen=True)
class Experiment:
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]

    def __call__(self, argv: Sequence[str]) -> int:
        p = argparse.ArgumentParser(prog="slam2d experiment", description=self.help)
        self.add_arguments(p)
        return self.run(p.parse_args(list(argv)))


def _ints(text: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not vals or min(vals) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return vals


def _names(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def _save(out: str | None, name: str, result: dict[str, Any]) -> None:
    if out:
        p = Path(out)
        p.mkdir(parents=True, exist_ok=True)
        (p / f"{name}.json").write_text(json.dumps(result, indent=1, sort_keys=True, default=float) + "\n")
        print(f"wrote {p / f'{name}.json'} (draw it with: slam2d report {p})")


def _scaling_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--estimators", type=_names, default=None, help="comma-separated (default: all registered)")
    p.add_argument("--landmarks", type=_ints, default=[100, 400, 1600, 6400], help="comma-separated N values")
    p.add_argument("--steps", type=int, default=None, help="steps per run (default: one lap of the grid + 15%%)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-run-s", type=float, default=120.0, help="stop an estimator after a run longer than this")
    p.add_argument("--blas-threads", type=int, default=1, help="BLAS threads while timing (0: leave as is)")
    p.add_argument("--out", default=None, metavar="DIR", help="write DIR/scaling.json")
    add_set_argument(p)


def _scaling_run(args: argparse.Namespace) -> int:
    from slam2d.lab.experiments import scaling

    res = scaling(args.estimators, args.landmarks, seed=args.seed, steps=args.steps, overrides=overrides_from(args),
                  max_run_s=args.max_run_s, blas_threads=args.blas_threads or None, report=print)
    print_table(res["rows"], ["estimator", "landmarks", "mapped", "obs_per_step", "step_ms_median", "steps"])
    print()
    print_table([{"estimator": k, **v} for k, v in res["fits"].items()],
                ["estimator", "slope_vs_mapped", "end_slope_vs_mapped", "slope_vs_landmarks", "claim", "points"])
    _save(args.out, "scaling", res)
    return 0


def _consistency_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--estimators", type=_names, default=None, help="comma-separated (default: all registered)")
    p.add_argument("--scenario", default="room")
    p.add_argument("--seeds", type=int, default=20, help="Monte-Carlo runs per estimator")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--probability", type=float, default=0.95, help="two-sided band probability")
    p.add_argument("--workers", type=int, default=None, help="local processes (default: serial)")
    p.add_argument("--out", default=None, metavar="DIR", help="write DIR/consistency.json")
    add_set_argument(p)


def _consistency_run(args: argparse.Namespace) -> int:
    from slam2d.lab.experiments import consistency
    from slam2d.lab.sweep import make_executor

    kw = dict(scenario=args.scenario, seeds=args.seeds, steps=args.steps, overrides=overrides_from(args),
              probability=args.probability, report=print)
    if args.workers:
        with make_executor(args.workers) as ex:
            res = consistency(args.estimators, executor=ex, **kw)  # type: ignore[arg-type]
    else:
        res = consistency(args.estimators, **kw)  # type: ignore[arg-type]
    rows = [{"estimator": k, "overall_mean": v["overall_mean"], "band_low": v["band"][0], "band_high": v["band"][1],
             "fraction_inside": v["fraction_inside"], "ate_rmse_m_mean": v["ate_rmse_m_mean"]}
            for k, v in res["results"].items()]
    print_table(rows, ["estimator", "overall_mean", "band_low", "band_high", "fraction_inside", "ate_rmse_m_mean"])
    for k, why in res["skipped"].items():
        print(f"skipped {k}: {why}")
    _save(args.out, "consistency", res)
    return 0


EXPERIMENTS: dict[str, Experiment] = {
    "scaling": Experiment("time per step vs number of landmarks for every estimator, with log-log slopes",
                          _scaling_args, _scaling_run),
    "consistency": Experiment("pose NEES over Monte-Carlo seeds against the chi-square band",
                              _consistency_args, _consistency_run),
}


def add_to(experiment_subparsers: Any) -> None:
    """Add one sub-command per entry of ``EXPERIMENTS`` to an ``experiment`` command's sub-parsers."""
    for name, exp in EXPERIMENTS.items():
        p = experiment_subparsers.add_parser(name, help=exp.help, description=exp.help)
        exp.add_arguments(p)
        p.set_defaults(func=exp.run)


def register(sub: Any) -> None:
    if "experiment" in sub.choices:  # another catalogue owns the command; it can call add_to()
        return
    p = sub.add_parser("experiment", help="run a lab experiment (scaling, consistency)",
                       description="Run a lab experiment over every registered estimator.")
    add_to(p.add_subparsers(dest="experiment", metavar="NAME", required=True))
