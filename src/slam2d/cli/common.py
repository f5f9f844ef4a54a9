"""Small helpers shared by the CLI commands: --set parsing, tables, JSON output."""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from slam2d.config import parse_set_args
from slam2d.io.atomic import check_output, refuse_overwrite_input, write_text_atomic
from slam2d.io.json_text import dumps


def add_set_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scenario or estimator config field (repeatable), e.g. --set landmarks=1000; "
                        "prefix with estimator. to change only the estimator's copy")


def overrides_from(args: argparse.Namespace) -> dict[str, str]:
    return parse_set_args(args.overrides)


def fmt(v: Any) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.3e}"
    return str(v)


def print_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> None:
    """Print rows as an aligned text table with the given columns."""
    cells = [[c for c in columns]] + [[fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    for k, row in enumerate(cells):
        print("  ".join(s.rjust(w) if k else s.ljust(w) for s, w in zip(row, widths, strict=True)))
        if k == 0:
            print("  ".join("-" * w for w in widths))


def write_json(path: str | Path, record: Mapping[str, Any]) -> None:
    text = dumps(record, indent=2, sort_keys=True) + "\n"  # serialised before the file is touched; NaN as null
    write_text_atomic(path, text)


def add_force_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true", help="allow an output to overwrite one of the inputs")


def check_outputs(args: argparse.Namespace, inputs: Sequence[str | Path | None],
                  outputs: Sequence[tuple[str, str | Path | None]]) -> None:
    """Before any long work: every output path is writable, none is a directory, none is an input (unless
    ``--force``) and no two outputs are the same file. Errors name the option and the path."""
    for name, o in outputs:
        if o is not None:
            check_output(o, name)
    refuse_overwrite_input(inputs, outputs, force=bool(getattr(args, "force", False)))


def check_number(name: str, value: float | int | None, *, low: float | None = None, high: float | None = None,
                 low_open: bool = False) -> None:
    """ValueError naming the option unless ``value`` is finite and inside [low, high] ((low, high] if low_open)."""
    if value is None:
        return
    ok = math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        lo = "" if low is None else f"{'>' if low_open else '>='} {low:g}"
        hi = "" if high is None else f"<= {high:g}"
        raise ValueError(f"{name} must be a finite number {' and '.join(x for x in (lo, hi) if x)} (got {value!r})")


def dataset_options(pairs: Sequence[str]) -> dict[str, Any]:
    """``--dataset-opt KEY=VALUE`` (repeatable) as loader options: each value an int, float, true/false, none, else
    the string itself."""
    return {k: _literal(v) for k, v in parse_set_args(pairs).items()}


def _literal(text: str) -> Any:
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low == "none":
        return None
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text
