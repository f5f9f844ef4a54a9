"""``slam2d run --estimator lidar --map-in A.db --map-out B.db``: a lidar session over a simulated scenario that
starts from a saved map (global relocalisation, then localisation and mapping in the map's frame) and/or saves the
map it estimated (see ``slam2d.graph.lidar_session``).

Every file is checked before the run: ``--map-in`` must be a readable slam2d map of this scenario's world (a file
that is not ours, truncated, from a newer schema or of another world is a one-line error, nothing written);
``--map-out`` must be writable and, when it exists, a slam2d map of the same world (it is replaced atomically, so it
may be the ``--map-in`` file).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from slam2d.config import split_overrides, to_dict, with_overrides
from slam2d.geometry import se2
from slam2d.graph.lidar_session import LidarSession, LidarSessionConfig
from slam2d.lab.registry import get_spec, make_config
from slam2d.lab.runner import run
from slam2d.maps.store import MapFormatError, MapSnapshot, MapStore, sim_world_id
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import simulate, spawn_streams

#: the estimators a session with saved maps runs: the lidar back end, plain or lifelong (map layers)
SESSION_ESTIMATORS = ("lidar", "lidar-lifelong")


def world_of(scenario: ScenarioConfig, seed: int) -> str:
    cfg = scenario.resolved()
    return sim_world_id({"scenario": cfg.name, "seed": seed, "config": to_dict(cfg)})


def check_map_files(map_in: str | None, map_out: str | None, world: str) -> MapSnapshot | None:
    """Read ``map_in`` (of ``world``) and check ``map_out`` can be replaced; MapFormatError naming the file."""
    snap = MapStore.read(map_in, world_id=world) if map_in else None
    if map_out:
        out = Path(map_out)
        if out.is_dir() or not out.parent.is_dir():
            raise MapFormatError(f"{out}: cannot write a map there (a directory, or its directory does not exist)")
        if out.exists() and (map_in is None or out.resolve() != Path(map_in).resolve()):
            MapStore.check_replaceable(out, world)  # not ours, corrupt or another world's: nothing overwritten
    return snap


def relocalisation_record(est: LidarSession, true_poses: np.ndarray | None, t0: float) -> dict[str, Any]:
    """What the JSON says about relocalisation: hypotheses over time, the decision, its error against the truth."""
    rel = est.relocaliser
    out: dict[str, Any] = {"relocalised": est.relocalised, "accepted_step": est.accepted_step,
                           "accepted_time_s": est.accepted_time_s,
                           "time_to_decide_s": None if est.accepted_time_s is None else est.accepted_time_s - t0,
                           "map_loops": est.map_loops,
                           "history": [] if rel is None else [{k: h[k] for k in ("step", "time_s", "hypotheses",
                                                                                 "evidence", "margin", "decided")}
                                                              for h in rel.history]}
    if est.accepted_pose is not None and true_poses is not None and est.accepted_step is not None:
        e = se2.local(true_poses[est.accepted_step], est.accepted_pose)
        out["error_m"] = float(np.hypot(e[0], e[1]))
        out["error_deg"] = float(np.degrees(abs(e[2])))
    return out


def run_session(args: argparse.Namespace, overrides: dict[str, Any]) -> tuple[dict[str, Any], LidarSession]:
    """Simulate, check the map files, run the session; returns (record, estimator)."""
    if args.estimator not in SESSION_ESTIMATORS:
        raise ValueError(f"--map-in/--map-out need --estimator lidar or lidar-lifelong (got {args.estimator!r})")
    if args.log or args.dataset:
        raise ValueError("--map-in/--map-out work with simulated scenarios (--scenario), whose world is known")
    spec = get_spec(args.estimator)
    est_only = {k.split(".", 1)[1]: v for k, v in overrides.items() if k.startswith("estimator.")}
    rest = {k.split(".", 1)[1] if k.startswith("scenario.") else k: v for k, v in overrides.items()
            if not k.startswith("estimator.")}
    scen_over, est_over = split_overrides(rest, ScenarioConfig, spec.config_cls)
    scenario = with_overrides(ScenarioConfig(name=args.scenario or "room"), scen_over)
    world = world_of(scenario, args.seed)
    prior = check_map_files(args.map_in, args.map_out, world)
    log = simulate(scenario, args.seed)
    lidar_cfg = make_config(args.estimator, {**est_over, **est_only}, log.metadata, has_ids=False)
    est = LidarSession(LidarSessionConfig(lidar=lidar_cfg), prior=prior, world_id=world,
                       metadata={"scenario": scenario.name, "seed": args.seed})
    result = run(est, log, rng=spawn_streams(args.seed)["estimator"], progress=None)
    record: dict[str, Any] = {"estimator": args.estimator, "scenario": scenario.name, "seed": int(args.seed),
                              **result.metrics, "map_in": args.map_in, "map_out": args.map_out,
                              "estimator_config": to_dict(lidar_cfg), "scenario_config": log.metadata["config"]}
    if prior is not None:
        record["relocalisation"] = relocalisation_record(est, log.true_poses, float(log.stamps_s[0]))
    return record, est


def save_session_map(path: str, est: LidarSession) -> None:
    """``--map-out``: write the session's map atomically, or a one-line error when it never relocalised."""
    if not est.relocalised:
        raise ValueError(f"{path}: not written: relocalisation stayed undecided over the whole run (the previous "
                         "file, if any, is unchanged)")
    est.save_map(path)
