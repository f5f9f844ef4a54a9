"""``slam2d datasets``: which real datasets the loaders know, where they are looked for, and what is present."""

from __future__ import annotations

import argparse
from typing import Any

from slam2d.cli.common import check_outputs, print_table, write_json
from slam2d.io.datasets import DATASETS, data_dir, dataset_status


def register(sub: Any) -> None:
    p = sub.add_parser("datasets", help="list the real datasets and where they are looked for",
                       description="List the datasets 'slam2d run --dataset NAME' can load, the data directory "
                                   "searched ($SLAM2D_DATA, --data-dir, or ../shared/datasets) and which are present.")
    p.add_argument("--data-dir", default=None, help="directory holding the dataset folders (overrides SLAM2D_DATA)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the listing as JSON")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    check_outputs(args, [], [("--json", args.json)])
    root, why = data_dir(args.data_dir)
    print(f"data directory: {root}  ({why})")
    rows = []
    for name, info in DATASETS.items():
        folder, missing = dataset_status(name, root)
        state = "yes" if not missing else ("no" if len(missing) == len(info.files) else f"partial ({len(missing)} "
                                                                                     "files missing)")
        rows.append({"dataset": name, "present": state, "folder": str(folder), "description": info.description,
                     "missing": missing})
    print_table(rows, ["dataset", "present", "folder", "description"])
    print("load one with: slam2d run --dataset NAME [--robot K] [--dataset-path DIR] --estimator ...")
    if args.json:
        write_json(args.json, {"data_dir": str(root), "source": why, "datasets": rows})
    return 0
