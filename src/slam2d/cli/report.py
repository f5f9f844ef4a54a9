"""``slam2d report DIR``: an HTML page with tables and PNG figures of a sweep / experiment result directory."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser("report", help="write an HTML report of a result directory",
                       description="Summarise DIR (results.jsonl from 'slam2d sweep', scaling.json / "
                                   "consistency.json from 'slam2d experiment ... --out DIR') as DIR/report/index.html "
                                   "with ATE boxplots, NEES with its chi-square band and scaling curves.")
    p.add_argument("directory", metavar="DIR")
    p.add_argument("--out", default=None, metavar="OUTDIR", help="where to write (default DIR/report)")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    try:
        from slam2d.viz.report import build_report
    except ImportError as e:  # matplotlib is the optional 'viz' extra
        raise ValueError(f"the report needs matplotlib: pip install 'slam2d[viz]' ({e})") from None
    page = build_report(args.directory, args.out)
    print(f"wrote {page}")
    return 0
