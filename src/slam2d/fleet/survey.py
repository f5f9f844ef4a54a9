"""A floor-marker survey as a CSV file for the map server (``slam2d map-server --survey FILE.csv``).

One marker per line: ``id,x,y`` (integer id as printed on the tag, x and y in metres in the warehouse frame). An
optional header line ``id,x,y``, blank lines and lines starting with ``#`` are skipped. Any other line that is not
three fields, an id that is not a non-negative integer, a coordinate that is not a finite number, or an id listed
twice is refused with ``FILE:LINE``.

Why the server reads the survey (and not the drones' hello): the survey belongs to the site, like the map; one
copy at the one place that anchors the joint graph, instead of every drone carrying it and the server having to
decide what to do when two drones disagree.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

Survey = tuple[tuple[int, float, float], ...]


def read_survey(path: str | Path) -> Survey:
    """The survey in ``path`` as ((id, x, y), ...); ValueError naming FILE:LINE for a bad row."""
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"--survey: {p} is a directory, not a CSV file")
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"--survey: {p}: no such file") from None
    except UnicodeDecodeError:
        raise ValueError(f"--survey: {p} is not a text file (expected CSV lines id,x,y)") from None
    rows: list[tuple[int, float, float]] = []
    seen: dict[int, int] = {}
    first = True  # the header may only be the first row
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        header, first = first and line.replace(" ", "").lower() == "id,x,y", False
        if header:
            continue
        parts = [f.strip() for f in line.split(",")]
        where = f"{p}:{n}"
        if len(parts) != 3:
            raise ValueError(f"{where}: expected 3 fields id,x,y, got {len(parts)}: {raw.strip()[:60]!r}")
        try:
            mid = int(parts[0])
        except ValueError:
            raise ValueError(f"{where}: marker id {parts[0][:30]!r} is not an integer") from None
        if mid < 0 or mid >= 2**32:
            raise ValueError(f"{where}: marker id {mid} is outside 0..{2**32 - 1}")
        try:
            x, y = float(parts[1]), float(parts[2])
        except ValueError:
            raise ValueError(f"{where}: x, y must be numbers in metres, got {parts[1][:30]!r}, {parts[2][:30]!r}") \
                from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"{where}: x, y must be finite, got {parts[1]!r}, {parts[2]!r}")
        if mid in seen:
            raise ValueError(f"{where}: marker id {mid} is already listed on line {seen[mid]}")
        seen[mid] = n
        rows.append((mid, x, y))
    if not rows:
        raise ValueError(f"--survey: {p} lists no marker (expected CSV lines id,x,y)")
    return tuple(rows)


def write_survey(path: str | Path, survey: Survey) -> None:
    """Write ``survey`` as CSV (a temp file beside the target, then renamed)."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}")
    tmp.write_text("id,x,y\n" + "".join(f"{i},{x:.4f},{y:.4f}\n" for i, x, y in survey), encoding="utf-8")
    os.replace(tmp, p)
