"""``slam2d experiment NAME``: run a named experiment over seeds, print its table, optionally write JSON.

Experiments: ``association`` (method comparison on the scramble scenario), ``scaling`` (time per step vs number of
landmarks, log-log slopes), ``consistency`` (pose NEES against the chi-square band). ``--json OUT`` writes the
record; put it in DIR as scaling.json / consistency.json for ``slam2d report DIR``.

Experiments are registered in ``EXPERIMENTS`` (name -> function). Each function takes the parsed seeds and the
``--set KEY=VALUE`` overrides (validated against the experiment's own config) and returns an :class:`ExperimentOutput`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from slam2d.cli.common import (
    add_set_argument,
    check_number,
    check_outputs,
    overrides_from,
    print_table,
    write_json,
)
from slam2d.config import check_positive, to_dict, with_overrides
from slam2d.io.atomic import atomic_path, check_output


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


@dataclass(frozen=True, slots=True, kw_only=True)
class ScalingExperimentConfig:
    """Settings of ``slam2d experiment scaling`` (only the first seed is used: it is a timing, not a statistic)."""

    estimators: tuple[str, ...] = ()
    """estimators to time (empty: every registered one)."""
    landmarks: tuple[int, ...] = (100, 400, 1600, 6400)
    """landmark counts N of the grid scenario."""
    steps: int = 0
    """steps per run (0: one lap of the grid's circle plus 15 %)."""
    dt_s: float = 0.5
    """time step of the simulated runs (s); larger steps make the laps of big grids affordable."""
    max_run_s: float = 120.0
    """an estimator stops at the first N whose run takes longer than this (s)."""
    blas_threads: int = 1
    """BLAS threads while timing (0: leave BLAS as it is)."""

    def __post_init__(self) -> None:
        if not self.landmarks or min(self.landmarks) < 1:
            raise ValueError(f"ScalingExperimentConfig.landmarks must be positive counts (got {self.landmarks})")
        if self.steps < 0 or self.blas_threads < 0:
            raise ValueError("ScalingExperimentConfig.steps and blas_threads must be >= 0")
        check_positive(self, "dt_s", "max_run_s")


@dataclass(frozen=True, slots=True, kw_only=True)
class ConsistencyExperimentConfig:
    """Settings of ``slam2d experiment consistency`` (Monte-Carlo runs = the seeds)."""

    estimators: tuple[str, ...] = ()
    """estimators to test (empty: every registered one)."""
    scenario: str = "room"
    """simulated scenario."""
    steps: int = 200
    """steps per run."""
    probability: float = 0.95
    """probability of the two-sided chi-square band."""
    workers: int = 0
    """local worker processes for the runs (0: serial)."""

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ValueError(f"ConsistencyExperimentConfig.steps must be >= 1 (got {self.steps})")
        if not 0 < self.probability < 1:
            raise ValueError(f"ConsistencyExperimentConfig.probability must be in (0, 1) (got {self.probability})")
        if self.workers < 0:
            raise ValueError(f"ConsistencyExperimentConfig.workers must be >= 0 (got {self.workers})")


def _scaling(seeds: Sequence[int], overrides: Mapping[str, str]) -> ExperimentOutput:
    from slam2d.lab.experiments import scaling

    cfg = with_overrides(ScalingExperimentConfig(), dict(overrides))
    res = scaling(cfg.estimators or None, cfg.landmarks, seed=seeds[0], steps=cfg.steps or None,
                  overrides={"dt_s": cfg.dt_s}, max_run_s=cfg.max_run_s, blas_threads=cfg.blas_threads or None,
                  report=print)
    rows = [{"estimator": k, **v} for k, v in res["fits"].items()]
    rows += [{"estimator": k, "claim": f"skipped: {why}"} for k, why in res["skipped"].items()]
    print_table(res["rows"], ["estimator", "landmarks", "mapped", "obs_per_step", "step_ms_median",
                              "wall_step_ms_median", "steps"])
    print()
    return ExperimentOutput(rows, ["estimator", "slope_vs_mapped", "end_slope_vs_mapped", "slope_vs_landmarks",
                                   "claim", "points"], res,
                            f"log-log slopes of CPU time per step (grid scenario, seed {seeds[0]})")


def _consistency(seeds: Sequence[int], overrides: Mapping[str, str]) -> ExperimentOutput:
    from slam2d.lab.experiments import consistency
    from slam2d.lab.sweep import make_executor

    cfg = with_overrides(ConsistencyExperimentConfig(), dict(overrides))
    if list(seeds) != list(range(seeds[0], seeds[0] + len(seeds))) or seeds[0] != 0:
        raise ValueError("the consistency experiment uses seeds 0..N-1: give --seeds N without --first-seed")
    kw: dict[str, Any] = dict(scenario=cfg.scenario, seeds=len(seeds), steps=cfg.steps, probability=cfg.probability,
                              report=print)
    if cfg.workers:
        with make_executor(cfg.workers) as ex:
            res = consistency(cfg.estimators or None, executor=ex, **kw)
    else:
        res = consistency(cfg.estimators or None, **kw)
    rows = [{"estimator": k, "overall_mean": v["overall_mean"], "band_low": v["band"][0], "band_high": v["band"][1],
             "fraction_inside": v["fraction_inside"], "ate_rmse_m_mean": v["ate_rmse_m_mean"]}
            for k, v in res["results"].items()]
    rows += [{"estimator": k, "overall_mean": f"skipped: {why}"} for k, why in res["skipped"].items()]
    return ExperimentOutput(rows, ["estimator", "overall_mean", "band_low", "band_high", "fraction_inside",
                                   "ate_rmse_m_mean"], res,
                            f"pose NEES on '{cfg.scenario}' over {len(seeds)} seeds, "
                            f"{100 * cfg.probability:.0f} % band per step")


@dataclass(frozen=True, slots=True, kw_only=True)
class BreakitExperimentConfig:
    """Settings of ``slam2d experiment breakit``."""

    estimators: tuple[str, ...] = ("ekf", "fastslam", "graph")
    """estimators to break."""
    scenario: str = "loop"
    """simulated scenario (the loop makes 'no loop closure' matter)."""
    steps: int = 0
    """steps per run (0: the scenario's default)."""
    figure: str = "out/breakit.png"
    """where to draw the bar chart ("" for none)."""

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise ValueError(f"BreakitExperimentConfig.steps must be >= 0 (got {self.steps})")


def _breakit(seeds: Sequence[int], overrides: Mapping[str, str]) -> ExperimentOutput:
    from slam2d.lab.breakit import breakit_experiment

    cfg = with_overrides(BreakitExperimentConfig(), dict(overrides))
    if cfg.figure:
        check_output(cfg.figure, "--set figure")  # before the runs, not after them
    rows = breakit_experiment(cfg.estimators, tuple(seeds), cfg.scenario, cfg.steps or None)
    if cfg.figure:
        from slam2d.viz.figures import save_breakit_figure

        with atomic_path(cfg.figure) as tmp:  # a failed drawing leaves the previous figure as it was
            save_breakit_figure(rows, tmp)
        print(f"wrote {cfg.figure}")
    cols = ["estimator", "condition", "runs", "ate_mean_m", "ate_std_m", "map_rmse_mean_m"]
    return ExperimentOutput(rows, cols, {"config": to_dict(cfg), "seeds": list(seeds), "rows": rows},
                            f"break-it on '{cfg.scenario}' over {len(seeds)} seeds (known association)")


def _loop_closure(seeds: Sequence[int], overrides: Mapping[str, str]) -> ExperimentOutput:
    from slam2d.lab.loop_experiment import loop_closure_experiment

    if overrides:
        raise ValueError(f"the loop-closure experiment takes no --set keys (got {sorted(overrides)})")
    rows = [loop_closure_experiment(seed) for seed in seeds]
    cols = ["seed", "loop_closed", "final_error_before_m", "final_error_after_m", "ate_no_loop_closure_m",
            "ate_closed_once_m", "ate_online_loop_closure_m", "correction_distance_corr"]
    return ExperimentOutput(rows, cols, {"rows": rows},
                            "graph SLAM around the 200 m loop: drift without loop closure, then one closure")


def _offset_puzzle(seeds: Sequence[int], overrides: Mapping[str, str]) -> ExperimentOutput:
    from slam2d.lab.loop_experiment import offset_puzzle

    if overrides:
        raise ValueError(f"the offset-puzzle experiment takes no --set keys (got {sorted(overrides)})")
    rows = [{"seed": seed, **r} for seed in seeds for r in offset_puzzle(seed)]
    cols = ["seed", "case", "loop_accepted", "gap_m", "final_error_m", "ate_m", "chi2_per_dof_odometry",
            "chi2_per_dof_loop", "chi2_per_dof_range_bearing"]
    return ExperimentOutput(rows, cols, {"rows": rows},
                            "the '2 m offset' puzzle: a loop that fires but cannot pull the path back")


#: experiment name -> function(seeds, overrides) -> ExperimentOutput; add new experiments here
EXPERIMENTS: dict[str, Callable[[Sequence[int], Mapping[str, str]], ExperimentOutput]] = {
    "association": _association,
    "scaling": _scaling,
    "consistency": _consistency,
    "breakit": _breakit,
    "loop-closure": _loop_closure,
    "offset-puzzle": _offset_puzzle,
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
    if args.seeds > 100_000:
        raise ValueError(f"--seeds must be <= 100000 (got {args.seeds})")
    check_number("--first-seed", args.first_seed, low=0, high=2**63 - args.seeds)  # every seed in 0..2**63-1
    check_outputs(args, [], [("--json", args.json_out)])
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    out = EXPERIMENTS[args.name](seeds, overrides_from(args))
    if out.title:
        print(out.title)
    print_table(out.rows, out.columns)
    if args.json_out:
        write_json(args.json_out, out.record)
        print(f"wrote {args.json_out}")
    return 0
