"""Format dispatch for graph files: by ``--format``, else by extension, else by sniffing the tags."""

from __future__ import annotations

import os
from collections.abc import Callable

from slam2d.io import bounded
from slam2d.io._text import GraphFile, GraphFormatError
from slam2d.io.g2o import read_g2o
from slam2d.io.isam import read_isam
from slam2d.io.toro import read_toro

FORMATS: dict[str, Callable[..., GraphFile]] = {"g2o": read_g2o, "toro": read_toro, "isam": read_isam}
_EXT = {".g2o": "g2o", ".graph": "toro", ".toro": "toro", ".isam": "isam"}


def detect_format(path: str | os.PathLike[str]) -> str:
    """g2o / toro / isam from the extension, else from the first tags (EDGE2 without VERTEX2 is iSAM)."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in _EXT:
        return _EXT[ext]
    tags = set()
    for i, line in enumerate(bounded.iter_lines(path, GraphFormatError)):
        tok = line.split("#", 1)[0].split()
        if tok:
            tags.add(tok[0][:40])
        if i > 2000:
            break
    if tags & {"VERTEX_SE2", "EDGE_SE2", "VERTEX_XY", "EDGE_SE2_XY"}:
        return "g2o"
    if "VERTEX2" in tags:
        return "toro"
    if tags & {"ODOMETRY", "LANDMARK", "EDGE2"}:
        return "isam"
    raise GraphFormatError(f"{os.fspath(path)}: cannot tell the graph format (tags seen: {sorted(tags)[:8]}); "
                           "pass --format g2o|toro|isam")


def read_graph(path: str | os.PathLike[str], format: str | None = None, *, on_unknown: str = "warn") -> GraphFile:
    """Read a graph file in the given or detected format."""
    fmt = format or detect_format(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown graph format {fmt!r}; choose one of {', '.join(FORMATS)}")
    return FORMATS[fmt](path, on_unknown=on_unknown)
