"""Entry point: builds one sub-command per module in ``COMMANDS`` and turns library errors into clean messages."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from slam2d.graph.linear import SolverError
from slam2d.log import LogFormatError

#: one module per sub-command; each defines ``register(subparsers)`` and sets ``func`` on its parser
COMMANDS = [
    "slam2d.cli.simulate",
    "slam2d.cli.run",
    "slam2d.cli.demo",
    "slam2d.cli.experiment",
    "slam2d.cli.sweep",
    "slam2d.cli.report",
    "slam2d.cli.datasets",
    "slam2d.cli.optimize",
    "slam2d.cli.lab",
    "slam2d.cli.exercise",
    "slam2d.cli.lidar",
    "slam2d.cli.map",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slam2d", description="Classical 2D SLAM: simulate, estimate, evaluate.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, LogFormatError, FileNotFoundError, SolverError) as e:
        print(f"slam2d {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"slam2d {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
