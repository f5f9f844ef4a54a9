"""``slam2d map save|load|info``: saved maps in one SQLite file (see ``slam2d.maps.store``).

``save`` builds a map from a simulated run: by default from its TRUE poses (keyframe scans at the true poses, the
occupancy grid of those scans, a chain pose graph), or with ``--source lidar`` from the lidar estimator's run (its
keyframes, pose graph with loops, static layer and the floor markers it read; a cold start at the true start).
``load`` reads and validates every array and prints a summary; ``info`` prints the metadata and counts.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from slam2d.cli.common import add_set_argument, check_number, overrides_from
from slam2d.config import to_dict, with_overrides
from slam2d.io.atomic import check_output
from slam2d.maps.occupancy import OccupancyConfig
from slam2d.maps.store import MapFormatError, MapStore, sim_world_id, snapshot_from_truth
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.simulator import simulate


def register(sub: Any) -> None:
    p = sub.add_parser("map", help="save, load and inspect saved maps (SQLite)",
                       description="Saved maps: keyframes, pose graph, static occupancy layer and metadata in one "
                                   "SQLite file, written atomically.")
    msub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)

    s = msub.add_parser("save", help="build a map from a simulated run (true poses or the lidar estimator) and save it",
                        description="Simulate a scenario and save a map built from the TRUE poses (keyframe scans, "
                                    "occupancy grid, chain pose graph), or with --source lidar the map the lidar "
                                    "estimator built (cold start).")
    s.add_argument("--source", choices=("truth", "lidar"), default="truth",
                   help="truth: map at the true poses (default); lidar: the lidar estimator's map")
    s.add_argument("--scenario", default="warehouse", help=f"one of: {', '.join(sorted(SCENARIOS))} "
                                                           "(default warehouse)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument("--out", required=True, help="map file to write (.db); replaced atomically")
    s.add_argument("--keyframe-every-m", type=float, default=1.0, help="keyframe spacing (m, default 1.0)")
    s.add_argument("--keyframe-every-deg", type=float, default=30.0, help="keyframe on turns of (deg, default 30)")
    s.add_argument("--resolution", type=float, default=0.1, help="occupancy cell size (m, default 0.1)")
    s.add_argument("--replace-other-world", action="store_true",
                   help="allow replacing an existing map of another world")
    add_set_argument(s)
    s.set_defaults(func=cmd_save)

    ld = msub.add_parser("load", help="read and validate a map, print a summary",
                         description="Read every table of a map, check it, and summarise it.")
    ld.add_argument("path", help="map file (.db)")
    ld.add_argument("--scenario", help="also check the map belongs to this scenario's world (with --seed/--set)")
    ld.add_argument("--seed", type=int, default=0, help="seed of that world (default 0)")
    add_set_argument(ld)
    ld.set_defaults(func=cmd_load)

    i = msub.add_parser("info", help="print a map's metadata and counts",
                        description="Print the metadata and row counts of a map file.")
    i.add_argument("path", help="map file (.db)")
    i.add_argument("--json", action="store_true", help="print as JSON")
    i.set_defaults(func=cmd_info)


def _world_id(scenario: str, seed: int, overrides: dict[str, str]) -> str:
    cfg = with_overrides(ScenarioConfig(name=scenario), overrides).resolved()
    return sim_world_id({"scenario": scenario, "seed": seed, "config": to_dict(cfg)})


def _check_save_target(args: argparse.Namespace, scenario: ScenarioConfig) -> None:
    """Refuse a bad ``--out`` before the simulation and the run (``MapStore.write`` checks again when it writes):
    a directory or unwritable place, a missing folder, a file that is not a slam2d map, or (without
    --replace-other-world) one that holds another world's map."""
    from slam2d.cli.map_session import world_of

    path = check_output(args.out, "--out")
    if not path.parent.is_dir():
        raise MapFormatError(f"{path}: cannot write a map there ({path.parent} does not exist)")
    if path.exists():
        MapStore.check_replaceable(path, world_of(scenario, args.seed), args.replace_other_world)


def cmd_save(args: argparse.Namespace) -> int:
    check_number("--seed", args.seed, low=0, high=2**63 - 1)
    check_number("--keyframe-every-m", args.keyframe_every_m, low=0, low_open=True)
    check_number("--keyframe-every-deg", args.keyframe_every_deg, low=0, low_open=True)
    check_number("--resolution", args.resolution, low=0, low_open=True)
    if args.source == "lidar":
        return _save_from_lidar(args)
    cfg = with_overrides(ScenarioConfig(name=args.scenario), overrides_from(args))
    occupancy = OccupancyConfig(resolution_m=args.resolution)
    _check_save_target(args, cfg)
    log = simulate(cfg, args.seed)
    snap = snapshot_from_truth(log, keyframe_every_m=args.keyframe_every_m,
                               keyframe_every_rad=float(np.deg2rad(args.keyframe_every_deg)), occupancy=occupancy)
    path = MapStore.write(args.out, snap, created_by="slam2d map save (from truth)",
                          replace_other_world=args.replace_other_world)
    c = snap.counts()
    print(f"wrote {path}: world {snap.world_id}, {c['keyframes']} keyframes, {c['edges']} edges, "
          f"occupancy {snap.occupancy_logodds.shape[1]} x {snap.occupancy_logodds.shape[0]} cells "
          f"at {snap.occupancy_resolution_m} m (built from true poses)")
    return 0


def _save_from_lidar(args: argparse.Namespace) -> int:
    """``--source lidar``: the lidar session (cold start) over the simulated scenario; its map is saved."""
    from slam2d.cli.map_session import world_of
    from slam2d.config import split_overrides
    from slam2d.graph.lidar_session import LidarSession, LidarSessionConfig
    from slam2d.lab.registry import get_spec, make_config
    from slam2d.lab.runner import run
    from slam2d.sim.simulator import spawn_streams

    over = overrides_from(args)
    est_only = {k.split(".", 1)[1]: v for k, v in over.items() if k.startswith("estimator.")}
    rest = {k: v for k, v in over.items() if not k.startswith("estimator.")}
    scen_over, est_over = split_overrides(rest, ScenarioConfig, get_spec("lidar").config_cls)
    cfg = with_overrides(ScenarioConfig(name=args.scenario), scen_over)
    world = world_of(cfg, args.seed)
    _check_save_target(args, cfg)  # refuse a bad target before the run
    log = simulate(cfg, args.seed)
    lidar = make_config("lidar", {**est_over, **est_only}, log.metadata, has_ids=False)
    est = LidarSession(LidarSessionConfig(lidar=lidar, save_resolution_m=args.resolution), world_id=world,
                       metadata={"scenario": args.scenario, "seed": args.seed})
    run(est, log, rng=spawn_streams(args.seed)["estimator"], progress=None)
    snap = est.snapshot()
    path = MapStore.write(args.out, snap, created_by="slam2d map save (lidar estimator)",
                          replace_other_world=args.replace_other_world)
    c = snap.counts()
    print(f"wrote {path}: world {snap.world_id}, {c['keyframes']} keyframes, {c['edges']} edges, "
          f"occupancy {snap.occupancy_logodds.shape[1]} x {snap.occupancy_logodds.shape[0]} cells "
          f"at {snap.occupancy_resolution_m} m (built by the lidar estimator)")
    return 0


def cmd_load(args: argparse.Namespace) -> int:
    world = _world_id(args.scenario, args.seed, overrides_from(args)) if args.scenario else None
    snap = MapStore.read(args.path, world_id=world)
    occ = snap.occupancy_logodds
    prob = 1.0 - 1.0 / (1.0 + np.exp(occ.astype(np.float64)))
    lo = snap.keyframe_poses[:, :2].min(axis=0) if len(snap.keyframe_poses) else np.zeros(2)
    hi = snap.keyframe_poses[:, :2].max(axis=0) if len(snap.keyframe_poses) else np.zeros(2)
    print(f"{args.path}: valid slam2d map of world {snap.world_id}")
    print(f"  keyframes   {len(snap.keyframe_poses)} ({snap.keyframe_scans.shape[1]} beams, "
          f"descriptors of {snap.descriptors.shape[1]}), spanning x {lo[0]:.1f}..{hi[0]:.1f} m, "
          f"y {lo[1]:.1f}..{hi[1]:.1f} m")
    print(f"  pose graph  {len(snap.node_ids)} nodes, {len(snap.edge_nodes)} edges")
    print(f"  occupancy   {occ.shape[1]} x {occ.shape[0]} cells at {snap.occupancy_resolution_m} m from "
          f"({snap.occupancy_origin[0]:.2f}, {snap.occupancy_origin[1]:.2f}); {int((prob > 0.65).sum())} occupied, "
          f"{int((prob < 0.35).sum())} free")
    if world:
        print(f"  matches the world of --scenario {args.scenario} --seed {args.seed}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    info = MapStore.info(args.path)
    record = {"path": str(info.path), "schema_version": info.schema_version, "world_id": info.world_id,
              "created_at": info.created_at, "created_by": info.created_by, "counts": info.counts,
              "metadata": info.metadata}
    if args.json:
        print(json.dumps(record, indent=2, sort_keys=True))
        return 0
    for k in ("path", "schema_version", "world_id", "created_at", "created_by"):
        print(f"{k:15s} {record[k]}")
    print("counts          " + ", ".join(f"{k} {v}" for k, v in info.counts.items()))
    for k, v in sorted(info.metadata.items()):
        print(f"  {k:13s} {v}")
    return 0
