"""``slam2d lidar``: scan-matching + loop-closure SLAM on a CARMEN laser log; writes the occupancy map as PNG."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from slam2d.cli.common import overrides_from, print_table, write_json

DATASETS = {"intel-laser": "intel", "intel": "intel", "aces": "aces", "fr079": "fr079", "mit-csail": "mit-csail"}


def register(sub: Any) -> None:
    p = sub.add_parser("lidar", help="2D lidar SLAM on a CARMEN log (occupancy map PNG)",
                       description="Scan-matching odometry (ICP to a local map), ICP loop closures and a pose "
                                   "graph over a CARMEN .clf log; writes the occupancy map as PNG and, when a "
                                   "<log>.relations file sits next to the log, the Kümmerle et al. relation errors.")
    p.add_argument("--dataset", required=True,
                   help=f"one of {', '.join(sorted(DATASETS))} (from ../shared/datasets/radish-laser-logs or "
                        "$SLAM2D_DATA) or a path to a .clf/.clf.bz2 file")
    p.add_argument("--out", default=None, help="occupancy map PNG (default <dataset>_map.png)")
    p.add_argument("--resolution", type=float, default=0.05, help="grid cell size in m (default 0.05)")
    p.add_argument("--no-loops", action="store_true", help="scan-matching odometry only (no loop closure)")
    p.add_argument("--no-track-scans", action="store_true",
                   help="match keyframes only, placing the scans in between by odometry (about 3x faster; "
                        "fails when odometry lags the laser, e.g. fr079)")
    p.add_argument("--refine-scans", action="store_true",
                   help="also match every non-keyframe scan by ICP (slower; better short relations)")
    p.add_argument("--relations", default=None, help="relations file (default: <log>.relations if present)")
    p.add_argument("--path", action="store_true", help="draw the estimated trajectory on the map")
    p.add_argument("--json", default=None, metavar="OUT", help="write the result record as JSON")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a LidarSlamConfig field (repeatable), e.g. --set keyframe_distance_m=0.05 "
                        "--set icp.trim_fraction=0.9")
    p.set_defaults(func=cmd)


def resolve_dataset(name: str) -> Path:
    """A dataset name or a path to the .clf(.bz2) file."""
    import os

    if name in DATASETS:
        root = Path(os.environ.get("SLAM2D_DATA", Path.cwd().parent / "shared" / "datasets"))
        p = root / "radish-laser-logs" / f"{DATASETS[name]}.clf.bz2"
        if not p.exists():
            raise FileNotFoundError(f"dataset {name!r} not found at {p} (set SLAM2D_DATA to the datasets folder)")
        return p
    p = Path(name)
    if not p.exists():
        raise FileNotFoundError(f"{name}: not a known dataset ({', '.join(sorted(DATASETS))}) nor an existing file")
    return p


def cmd(args: argparse.Namespace) -> int:
    import dataclasses

    import numpy as np

    from slam2d.config import with_overrides
    from slam2d.eval.relations import read_relations, relation_errors
    from slam2d.frontend.lidar_slam import LidarSlamConfig, run_lidar_slam
    from slam2d.io.carmen import read_carmen
    from slam2d.maps.occupancy import (
        OccupancyConfig,
        OccupancyGrid,
        transform_scan_points,
        wall_thickness_cells,
    )
    from slam2d.viz.maps import save_occupancy_png

    path = resolve_dataset(args.dataset)
    t0 = time.perf_counter()
    log = read_carmen(path)
    print(log.summary())
    if log.num_scans < 2:
        raise ValueError(f"{path}: fewer than 2 usable scans")
    cfg = with_overrides(LidarSlamConfig(loop_closure=not args.no_loops, refine_scans=args.refine_scans,
                                         track_scans=not args.no_track_scans),
                         overrides_from(args))
    t1 = time.perf_counter()
    res = run_lidar_slam(log.poses, log.ranges_m, log.angles_rad, log.max_range_m, cfg)
    t2 = time.perf_counter()
    # the map: keyframe scans at their estimated poses (the scans in between add little but cost 5x the time);
    # no-return beams clear nothing (through windows and doors they would paint fans of free space outside)
    lim = cfg.max_range_m
    sample = np.vstack([transform_scan_points(p, r, log.angles_rad, lim)
                        for p, r in zip(res.keyframe_poses, log.ranges_m[res.keyframes], strict=True)])
    grid = OccupancyGrid.around(np.vstack([sample, res.poses[:, :2]]), 1.0,
                                OccupancyConfig(resolution_m=args.resolution, free_range_cap_m=0.0))
    grid.integrate(res.keyframe_poses, log.ranges_m[res.keyframes], log.angles_rad, log.max_range_m)
    name = Path(path).name.split(".")[0]
    out = Path(args.out or f"{name}_map.png")
    save_occupancy_png(grid, out, res.poses if args.path else None)
    thick = wall_thickness_cells(grid)
    t3 = time.perf_counter()
    record: dict[str, Any] = {
        "log": str(path), "scans": log.num_scans, "keyframes": len(res.keyframes), "loops": res.loops_accepted,
        "loops_tried": res.loops_tried, "icp_failures": res.icp_failures, "map": str(out),
        "map_cells": f"{grid.shape[1]}x{grid.shape[0]}",
        "wall_cells_median": float(np.median(thick)) if len(thick) else float("nan"),
        "wall_cells_p90": round(float(np.percentile(thick, 90)), 2) if len(thick) else float("nan"),
        "read_s": round(t1 - t0, 1), "slam_s": round(t2 - t1, 1), "map_s": round(t3 - t2, 1),
    }
    rel_path = Path(args.relations) if args.relations else Path(str(path).replace(".clf.bz2", ".relations")
                                                                     .replace(".clf", ".relations"))
    if rel_path.exists() and rel_path != path:
        rel = read_relations(rel_path)
        for label, poses in (("odometry", log.poses), ("slam", res.poses)):
            s = relation_errors(log.stamps_s, poses, rel).summary()
            record.update({f"{label}_{k}": v for k, v in s.items() if k not in ("relations", "missing")})
        record["relations"] = len(rel)
    print_table([record], list(record))
    if args.json:
        write_json(args.json, {**record, "config": dataclasses.asdict(cfg)})
    return 0
