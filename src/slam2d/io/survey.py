"""Floor-marker survey files: the map-frame position of each ID'd floor marker, as a survey of the floor gives them.

Format (CSV or whitespace separated), one marker per line: ``id, x, y`` (integer id >= 0, metres). Blank lines and
lines starting with ``#`` are skipped; a first line ``id,x,y`` is a header. Every problem names ``file:line``: a
wrong field count, a token that is not a number / integer id, a negative id, NaN or infinite coordinates, a
duplicate id; an empty survey is an error too. Files go through the bounded reader (size and line caps).

The rows are what :class:`slam2d.graph.lidar_config.LidarSLAMConfig` takes as ``surveyed_markers``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

import numpy as np

from slam2d.io import bounded
from slam2d.io.atomic import atomic_write

Survey = tuple[tuple[int, float, float], ...]


class SurveyFormatError(ValueError):
    """Malformed survey file; the message names ``file:line``."""


def read_marker_survey(path: str | os.PathLike[str]) -> Survey:
    """The rows (id, x, y) of a survey file, in file order. SurveyFormatError naming ``file:line`` on bad input."""
    name = os.fspath(path)
    rows: list[tuple[int, float, float]] = []
    seen: dict[int, int] = {}
    for lineno, line in enumerate(bounded.iter_lines(name, SurveyFormatError, errors="strict"), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if not rows and [p.lower() for p in parts] == ["id", "x", "y"]:
            continue
        if len(parts) != 3:
            raise SurveyFormatError(f"{name}:{lineno}: expected 3 fields (id, x, y), got {len(parts)}")
        try:
            mid = int(parts[0])
        except ValueError:
            raise SurveyFormatError(f"{name}:{lineno}: marker id {parts[0]!r} is not an integer") from None
        if mid < 0:
            raise SurveyFormatError(f"{name}:{lineno}: marker id {mid} is negative")
        try:
            x, y = float(parts[1]), float(parts[2])
        except ValueError:
            raise SurveyFormatError(f"{name}:{lineno}: not a number in {s!r}") from None
        if not (np.isfinite(x) and np.isfinite(y)):
            raise SurveyFormatError(f"{name}:{lineno}: marker {mid} has a non-finite position")
        if mid in seen:
            raise SurveyFormatError(f"{name}:{lineno}: marker {mid} is listed twice (first on line {seen[mid]})")
        seen[mid] = lineno
        rows.append((mid, x, y))
    if not rows:
        raise SurveyFormatError(f"{name}: no marker rows (expected lines 'id, x, y')")
    return tuple(rows)


def write_marker_survey(path: str | os.PathLike[str], rows: Iterable[tuple[int, float, float]]) -> None:
    """Write rows (id, x, y) as a survey file (atomically; full float precision)."""
    with atomic_write(os.fspath(path)) as f:
        f.write("id,x,y\n")
        for mid, x, y in rows:
            f.write(f"{int(mid)},{float(x)!r},{float(y)!r}\n")
