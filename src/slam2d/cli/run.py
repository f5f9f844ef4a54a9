"""``slam2d run``: one estimator over a simulated scenario, a saved log or a real dataset; prints a table and JSON."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from slam2d.association import METHODS
from slam2d.cli.common import (
    add_force_argument,
    add_set_argument,
    check_number,
    check_outputs,
    dataset_options,
    overrides_from,
    print_table,
    write_json,
)
from slam2d.cli.lidar import find_relations, laser_outputs, load_laser_log, load_relations, report_log_problems
from slam2d.eval.gps import gps_ate
from slam2d.io.carmen import is_carmen_source, resolve_carmen
from slam2d.io.datasets import DATASETS, load_dataset
from slam2d.io.survey import read_marker_survey
from slam2d.lab.multi_robot import MULTI_ESTIMATORS, run_multi, table_rows
from slam2d.lab.registry import estimator_names, get_spec
from slam2d.lab.runner import run_named
from slam2d.log import Log
from slam2d.sim.scenarios import SCENARIOS

COLUMNS = ["estimator", "scenario", "robot", "seed", "steps", "ate_rmse_m", "gps_ate_rmse_m", "rpe_trans_rmse_m",
           "rpe_rot_rmse_rad", "final_pose_error_m", "landmarks_estimated", "step_ms_mean", "assoc_precision",
           "assoc_recall", "loops_accepted", "loops_false", "rel_trans_mean_m", "rel_trans_std_m", "rel_rot_mean_deg",
           "rel_rot_std_deg"]


def register(sub: Any) -> None:
    p = sub.add_parser("run", help="run an estimator and score it",
                       description="Run an estimator over a scenario (simulated with --seed) or a saved log.")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--scenario", default=None, help=f"one of: {', '.join(sorted(SCENARIOS))} (default room)")
    src.add_argument("--log", default=None, help="a log saved by 'slam2d simulate'")
    src.add_argument("--dataset", default=None, help=f"a real dataset: {', '.join(DATASETS)} (see 'slam2d datasets'), "
                     "a Radish laser log (aces, intel, fr079, mit-csail) or a path to a CARMEN .clf/.clf.bz2 file")
    p.add_argument("--robot", type=_robot, default=1,
                   help="MRCLAM robot 1..5 (default 1), or 'all': every robot on one clock (--estimator multi-graph)")
    p.add_argument("--unknown-starts", action="store_true",
                   help="multi-graph: robots start in their own frames, merged from common evidence")
    p.add_argument("--dataset-path", default=None, metavar="DIR",
                   help="folder in the dataset's format (default: the staged copy under the data directory)")
    p.add_argument("--data-dir", default=None, help="directory holding the dataset folders (overrides SLAM2D_DATA)")
    p.add_argument("--max-steps", type=int, default=None, help="use only the first N steps of the dataset")
    p.add_argument("--max-time", type=float, default=None, metavar="S", help="use only the first S seconds")
    p.add_argument("--dataset-opt", action="append", default=[], metavar="KEY=VALUE",
                   help="a loader option (repeatable), e.g. dt_s=0.2 or others=keep (mrclam), max_range_m=30 "
                        "(victoria-park, CARMEN logs), on_error=skip or backwards_stamps=skip (CARMEN logs)")
    p.add_argument("--estimator", default="dead-reckoning",
                   help=f"one of: {', '.join(estimator_names())} (default dead-reckoning); with --robot all: "
                        f"{', '.join(MULTI_ESTIMATORS)}")
    p.add_argument("--seed", type=int, default=None,
                   help="seed for the simulation and the estimator (default 0; with --log, the seed the log was "
                        "simulated with, so that the run and its record match 'run --scenario ... --seed' on it)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the flat result record as JSON")
    p.add_argument("--trajectory", default=None, metavar="OUT.txt",
                   help="write the final trajectory as TUM 'stamp x y z qx qy qz qw' (a CARMEN log's own stamps)")
    p.add_argument("--map", default=None, metavar="OUT.png",
                   help="write the occupancy map of the final trajectory over the log's lidar scans as PNG")
    p.add_argument("--association", default=None, choices=["auto", *METHODS],
                   help="data association method of the estimator (estimators that associate; their default, auto: "
                        "known ids when the data carry them, else mahalanobis)")
    p.add_argument("--no-loop-closure", action="store_true",
                   help="switch the estimator's loop closure off (estimators that have one, e.g. graph)")
    p.add_argument("--map-in", default=None, metavar="A.db",
                   help="--estimator lidar or lidar-lifelong on a simulated scenario: start from this saved map at an "
                        "unknown pose (global relocalisation, then localise and keep mapping in the map's frame)")
    p.add_argument("--map-out", default=None, metavar="B.db",
                   help="--estimator lidar or lidar-lifelong on a simulated scenario: save the estimated map "
                        "(keyframes, pose graph, static layer) here, atomically (may equal --map-in)")
    p.add_argument("--marker-survey", default=None, metavar="FILE.csv",
                   help="--estimator lidar-lifelong: the floor markers' surveyed map-frame positions (lines 'id,x,y'; "
                        "'slam2d simulate --marker-survey' writes one); each marker the camera reads corrects the pose")
    add_set_argument(p)
    add_force_argument(p)
    p.set_defaults(func=cmd)


def _robot(text: str) -> int | str:
    """--robot: an integer or 'all'."""
    if text == "all":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a robot number or 'all', got {text!r}") from None


def cmd(args: argparse.Namespace) -> int:
    log = Log.load(args.log) if args.log else None
    if args.seed is None:  # a saved log's own seed (its metadata), else 0
        args.seed = int(log.metadata.get("seed", 0)) if log is not None else 0
    check_number("--seed", args.seed, low=0, high=2**63 - 1)
    check_number("--max-steps", args.max_steps, low=1)
    check_number("--max-time", args.max_time, low=0, low_open=True)
    carmen = resolve_carmen(args.dataset, args.data_dir) if args.dataset and is_carmen_source(args.dataset) else None
    if carmen is not None and args.dataset_path:
        raise ValueError(f"--dataset-path does not apply to a CARMEN log (--dataset {args.dataset}): pass the file "
                         "itself as --dataset PATH.clf")
    # a CARMEN log and the relations beside it are inputs too: --trajectory LOG.clf must not overwrite the log
    inputs = [args.log, args.dataset_path, carmen, find_relations(carmen)]
    check_outputs(args, inputs, [("--json", args.json), ("--trajectory", args.trajectory), ("--map", args.map)])
    if args.robot == "all" or args.estimator in MULTI_ESTIMATORS or args.unknown_starts:
        return _cmd_multi(args)
    if args.marker_survey and args.estimator != "lidar-lifelong":
        raise ValueError(f"--marker-survey needs --estimator lidar-lifelong (got {args.estimator!r})")
    if args.map_in or args.map_out:
        return _cmd_session(args)
    problems: dict[str, int] = {}
    relations = None
    if carmen is not None:
        opts = dataset_options(args.dataset_opt)
        log = load_laser_log(args.dataset, args.data_dir, args.max_steps, args.max_time, opts)
        relations = load_relations(log)  # read before the run: a bad file fails now, not after it
        problems = report_log_problems(log)
    elif args.dataset:
        opts = dataset_options(args.dataset_opt)
        log = load_dataset(args.dataset, args.dataset_path, args.robot, data_dir_override=args.data_dir,
                           max_steps=args.max_steps, max_time_s=args.max_time, **opts)
    elif args.dataset_path or args.max_steps or args.max_time or args.dataset_opt:
        raise ValueError("--dataset-path, --dataset-opt, --max-steps and --max-time need --dataset NAME")
    overrides = _overrides(args)
    if {"name", "scenario.name"} & set(overrides):
        raise ValueError("--set name=...: the scenario is chosen with --scenario")
    if args.robot not in (1, "all") and not args.dataset:
        raise ValueError(f"--robot {args.robot}: a robot of a multi-robot dataset (--dataset mrclam)")
    fields = {f.name for f in dataclasses.fields(get_spec(args.estimator).config_cls)}
    if args.association:
        if "association" not in fields:
            raise ValueError(f"--association: estimator {args.estimator!r} does not associate observations")
        overrides["estimator.association.method"] = args.association
    if args.no_loop_closure:
        if "loop_closure" not in fields:
            raise ValueError(f"--no-loop-closure: estimator {args.estimator!r} has no loop closure")
        overrides["estimator.loop_closure"] = "false"
    result, record = run_named(args.estimator, args.scenario or "room", seed=args.seed,
                               overrides=overrides, log=log, progress=None)
    record.update(problems)
    if args.dataset and log is not None:
        record["dataset"] = str(log.metadata.get("dataset", args.dataset))
        record["dataset_path"] = str(log.metadata.get("dataset_path", ""))
        if "robot" in log.metadata:
            record["robot"] = int(log.metadata["robot"])
        if log.gps_step is not None and log.true_poses is None and log.gps_step.size >= 2:
            record["gps_ate_rmse_m"] = gps_ate(result.trajectory, log).rmse_m
    if args.trajectory or args.map or (log is not None and "stamps_original_s" in log.metadata):
        laser_outputs(log if log is not None else _simulated(args), result.trajectory, record,
                      trajectory_out=args.trajectory, map_out=args.map, relations=relations)
    print_table([record], [c for c in COLUMNS if c in record])
    if args.json:
        write_json(args.json, record)
    return 0


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``--set`` pairs, plus the survey rows of ``--marker-survey`` (read here: a bad file fails before the run)."""
    out: dict[str, Any] = dict(overrides_from(args))
    if args.marker_survey:
        out["estimator.surveyed_markers"] = read_marker_survey(args.marker_survey)
    return out


def _simulated(args: argparse.Namespace) -> Log:
    """The scenario log ``run_named`` simulated (same seed and overrides: simulation is deterministic)."""
    from slam2d.config import split_overrides, with_overrides
    from slam2d.lab.registry import get_spec
    from slam2d.sim.scenarios import ScenarioConfig
    from slam2d.sim.simulator import simulate

    rest = {k.split(".", 1)[1] if k.startswith("scenario.") else k: v for k, v in overrides_from(args).items()
            if not k.startswith("estimator.")}
    scen, _ = split_overrides(rest, ScenarioConfig, get_spec(args.estimator).config_cls)
    return simulate(with_overrides(ScenarioConfig(name=args.scenario or "room"), scen), args.seed)


def _cmd_session(args: argparse.Namespace) -> int:
    """``--map-in`` / ``--map-out``: a lidar session with saved maps (slam2d.cli.map_session)."""
    from slam2d.cli.map_session import run_session, save_session_map

    record, est = run_session(args, _overrides(args))
    print_table([record], [c for c in COLUMNS if c in record])
    rel = record.get("relocalisation")
    if rel is not None:
        err = f", error {rel['error_m']:.3f} m / {rel['error_deg']:.2f} deg" if "error_m" in rel else ""
        print(f"relocalisation: accepted at step {rel['accepted_step']} ({rel['time_to_decide_s']:.1f} s){err}"
              if rel["relocalised"] else "relocalisation: undecided over the whole run (no pose accepted)")
    if args.json:
        write_json(args.json, record)
    if args.map_out:
        save_session_map(args.map_out, est)
        print(f"wrote {args.map_out}")
    return 0


def _cmd_multi(args: argparse.Namespace) -> int:
    """``--robot all --estimator multi-graph``: the joint graph over every robot (slam2d.lab.multi_robot)."""
    if args.robot != "all" or args.estimator not in MULTI_ESTIMATORS or not args.dataset:
        raise ValueError(f"multi-robot runs need --dataset mrclam --robot all --estimator "
                         f"{'|'.join(MULTI_ESTIMATORS)} (got --robot {args.robot} --estimator {args.estimator})")
    if args.overrides or args.no_loop_closure:
        raise ValueError("--set and --no-loop-closure do not apply to multi-robot runs")
    opts = dataset_options(args.dataset_opt)
    log = load_dataset(args.dataset, args.dataset_path, robot="all", data_dir_override=args.data_dir,
                       max_steps=args.max_steps, max_time_s=args.max_time, **opts)
    res = run_multi(log, estimator=args.estimator, unknown_starts=args.unknown_starts,
                    association=args.association or "known", seed=args.seed)
    record = {**res.metrics, "dataset": str(log.metadata.get("dataset", args.dataset)),
              "dataset_path": str(log.metadata.get("dataset_path", ""))}
    print_table(table_rows(record), ["robot", "group", "ate_rmse_m", "start_error_m", "start_error_rad",
                                     "map_rmse_m", "landmarks"])
    if args.json:
        write_json(args.json, record)
    return 0

