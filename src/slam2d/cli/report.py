"""``slam2d report DIR``: an HTML page with tables and PNG figures of a sweep / experiment result directory."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from slam2d.io.atomic import check_output


def register(sub: Any) -> None:
    p = sub.add_parser("report", help="write an HTML report of a result directory",
                       description="Summarise DIR (results.jsonl from 'slam2d sweep', scaling.json / "
                                   "consistency.json from 'slam2d experiment scaling|consistency --json "
                                   "DIR/NAME.json') as DIR/report/index.html with ATE boxplots, NEES with its "
                                   "chi-square band and scaling curves.")
    p.add_argument("directory", metavar="DIR", help="a sweep's result directory or a folder of experiment records")
    p.add_argument("--out", default=None, metavar="OUTDIR", help="where to write (default DIR/report)")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    try:
        from slam2d.viz.report import build_report
    except ImportError as e:  # matplotlib is the optional 'viz' extra
        raise ValueError(f"the report needs matplotlib: pip install 'slam2d[viz]' ({e})") from None
    d = Path(args.directory)
    if not d.is_dir():
        raise (NotADirectoryError if d.exists() else FileNotFoundError)(20 if d.exists() else 2,
                                                                        "not a result directory", str(d))
    out_dir = Path(args.out) if args.out else d / "report"
    if out_dir.exists() and not out_dir.is_dir():
        raise NotADirectoryError(20, "--out must be a folder", str(out_dir))
    check_output(out_dir / "index.html", "--out")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    # build beside the target, then move the files in (figures first, the page last): a failed report leaves the
    # previous one as it was
    with tempfile.TemporaryDirectory(prefix=f".{out_dir.name}.", dir=out_dir.parent) as tmp:
        page = build_report(d, tmp)
        out_dir.mkdir(exist_ok=True)
        for f in sorted(Path(tmp).iterdir(), key=lambda f: f.name == page.name):
            os.replace(f, out_dir / f.name)
    print(f"wrote {out_dir / page.name}")
    from slam2d.lab.sweep import ResultStore

    records, problems = ResultStore(d).scan()
    if problems:  # the page lists them too; a script reading only the exit code and stderr should hear of them
        print(f"slam2d report: note: {len(problems)} unusable lines in {d / 'results.jsonl'} ({len(records)} usable "
              f"runs); first: line {problems[0].line}: {problems[0].reason} (the next 'slam2d sweep' re-runs them)",
              file=sys.stderr)
    return 0
