"""``slam2d datasets``: which real datasets the loaders know, where they are looked for, and what is present: the
landmark and range datasets and the Radish lidar logs (``slam2d run --dataset NAME``), and the pose-graph files found
in the data directory (``slam2d optimize PATH``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slam2d.cli.common import check_outputs, print_table, write_json
from slam2d.io.carmen import RADISH_LOGS
from slam2d.io.datasets import DATASETS, data_dir, dataset_status

#: pose-graph files ``slam2d optimize`` reads by their extension (iSAM text is told by its tags: not listed)
_GRAPH_EXTENSIONS = (".g2o", ".graph")


def register(sub: Any) -> None:
    p = sub.add_parser("datasets", help="list the real datasets and where they are looked for",
                       description="List the datasets 'slam2d run --dataset NAME' can load (landmark and range "
                                   "datasets, the Radish lidar logs), the data directory searched ($SLAM2D_DATA, "
                                   "--data-dir, or ../shared/datasets), which are present, and the pose-graph "
                                   "files (.g2o, .graph) in its folders for 'slam2d optimize PATH'.")
    p.add_argument("--data-dir", default=None, help="directory holding the dataset folders (overrides SLAM2D_DATA)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the listing as JSON")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    check_outputs(args, [], [("--json", args.json)])
    root, why = data_dir(args.data_dir)
    state = "" if root.is_dir() or "absent" in why else "; missing" if not root.exists() else "; not a directory"
    print(f"data directory: {root}  ({why}{state})")
    rows = []
    for name, info in DATASETS.items():
        folder, missing = dataset_status(name, root)
        state = "yes" if not missing else ("no" if len(missing) == len(info.files) else f"partial ({len(missing)} "
                                                                                     "files missing)")
        rows.append({"dataset": name, "present": state, "folder": str(folder), "description": info.description,
                     "missing": missing})
    lidar = root / "radish-laser-logs"
    for name in RADISH_LOGS:
        log, rel = lidar / f"{name}.clf.bz2", lidar / f"{name}.relations"
        rows.append({"dataset": name, "present": "yes" if log.is_file() else "no", "folder": str(lidar),
                     "description": "Radish lidar log (CARMEN), relations file "
                                    f"{'beside it' if rel.is_file() else 'missing'}",
                     "missing": [p.name for p in (log, rel) if not p.is_file()]})
    print_table(rows, ["dataset", "present", "folder", "description"])
    print("load one with: slam2d run --dataset NAME [--robot K] [--dataset-path DIR] --estimator ...")
    graphs = _graph_files(root)
    if graphs:
        print_table([{"pose graph": str(g.relative_to(root)), "MB": round(g.stat().st_size / 1e6, 1)} for g in graphs],
                    ["pose graph", "MB"])
        print("optimise one with: slam2d optimize PATH")
    if args.json:
        write_json(args.json, {"data_dir": str(root), "source": why, "datasets": rows,
                               "pose_graphs": [str(g) for g in graphs]})
    return 0


def _graph_files(root: Path) -> list[Path]:
    """Pose-graph files in the data directory's folders (one level down), sorted; a folder that cannot be read is
    passed over (this is a listing, not a check)."""
    found: list[Path] = []
    try:
        folders = [d for d in root.iterdir() if d.is_dir()] if root.is_dir() else []
    except OSError:
        return found
    for d in folders:
        try:
            found += [p for p in d.iterdir() if p.suffix.lower() in _GRAPH_EXTENSIONS and p.is_file()]
        except OSError:
            continue
    return sorted(found)
