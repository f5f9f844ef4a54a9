"""Shared machinery of the line-based graph readers (g2o, TORO, iSAM) and the result type.

Error policy (all readers):

* every problem with the file content raises :class:`GraphFormatError` (a ``ValueError``) whose message starts with
  ``file:line:`` and names the offending token: wrong field count, a token that is not a number / integer id,
  NaN or infinite numbers, an information matrix that is not positive definite, a duplicate vertex, an edge to a
  vertex that was never declared (when the file declares vertices), a self-loop edge;
* a file in which no line has a known tag (another format, binary data) raises ``GraphFormatError``;
  lines longer than ``SLAM2D_MAX_LINE_CHARS`` or files larger than ``SLAM2D_MAX_FILE_MB`` too (``io.bounded``);
* unknown tags are skipped and counted (``GraphFile.skipped``); with ``on_unknown="warn"`` (default) one
  :class:`GraphFormatWarning` summarises them, ``"ignore"`` stays silent, ``"error"`` raises at the first one;
* files without vertex lines get their initial guess from the measurements (spanning tree of the relative-pose
  edges, landmarks from their first observation) and say so in ``GraphFile.initial_guess``;
* disconnected graphs are accepted; the optimiser holds the lowest-key pose of every component (reported).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.graph.graph import FactorGraph, Values
from slam2d.io import bounded

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_INT64_MAX = 2**63 - 1
#: largest information entry a reader accepts: squares and sums of the normal equations stay finite in float64
MAX_INFORMATION = 1e100


class GraphFormatError(ValueError):
    """Malformed graph file; the message names ``file:line`` and the offending token."""


class GraphFormatWarning(UserWarning):
    """Lines with unknown tags were skipped (counts in the message)."""


@dataclass
class GraphFile:
    """A graph read from a file: factors, initial values and what the reader did."""

    graph: FactorGraph
    values: Values
    format: str
    fixed_pose_keys: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    initial_guess: str = "vertices"
    """"vertices" (the file's vertex lines) or "spanning tree" (composed from the measurements)."""
    skipped: dict[str, int] = field(default_factory=dict)
    """unknown tag -> number of skipped lines."""


@dataclass
class Rows:
    """Lines of one tag: integer fields, float fields and the line numbers."""

    ints: IntArray
    floats: Array
    lines: IntArray


def read_lines(path: str | os.PathLike[str]) -> list[str]:
    """The file's lines, read in chunks with the size and line-length caps of :mod:`slam2d.io.bounded`."""
    return bounded.read_lines(path, GraphFormatError)


def tokenize(path: str | os.PathLike[str], lines: Iterable[str], spec: dict[str, tuple[int, int]],
             on_unknown: str, variable: dict[str, int] | None = None) -> tuple[dict[str, Rows], dict[str, int]]:
    """Split lines by tag. ``spec[tag] = (n_int, n_float)`` fixes the field count; ``variable[tag] = min`` marks
    tags with a variable number of integer fields (like FIX). Returns parsed rows per tag and skipped counts."""
    if on_unknown not in ("warn", "ignore", "error"):
        raise ValueError(f"on_unknown must be 'warn', 'ignore' or 'error' (got {on_unknown!r})")
    name = os.fspath(path)
    buckets: dict[str, tuple[list[list[str]], list[int]]] = {t: ([], []) for t in spec}
    var_rows: dict[str, list[tuple[int, list[str]]]] = {t: [] for t in (variable or {})}
    skipped: dict[str, int] = {}
    for no, raw in enumerate(lines, start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tok = line.split()
        tag = tok[0]
        if variable and tag in variable:
            if len(tok) - 1 < variable[tag]:
                raise GraphFormatError(f"{name}:{no}: {tag} needs at least {variable[tag]} id(s)")
            var_rows[tag].append((no, tok[1:]))
            continue
        if tag not in spec:
            if on_unknown == "error":
                raise GraphFormatError(f"{name}:{no}: unknown tag {tag!r}")
            skipped[tag] = skipped.get(tag, 0) + 1
            continue
        n_int, n_float = spec[tag]
        if len(tok) - 1 != n_int + n_float:
            raise GraphFormatError(
                f"{name}:{no}: {tag} expects {n_int + n_float} fields, got {len(tok) - 1} (line {line[:80]!r})")
        buckets[tag][0].append(tok[1:])
        buckets[tag][1].append(no)
    out = {}
    for tag, (rows, nos) in buckets.items():
        n_int, n_float = spec[tag]
        out[tag] = _convert(name, tag, rows, np.asarray(nos, np.int64), n_int, n_float)
    for tag, items in var_rows.items():
        ints = [(_int(name, no, t)) for no, toks in items for t in toks]
        lines_ = [no for no, toks in items for _ in toks]
        out[tag] = Rows(np.asarray(ints, np.int64), np.zeros((len(ints), 0)), np.asarray(lines_, np.int64))
    if skipped and not any(len(r[0]) for r in buckets.values()) and not any(var_rows.values()):
        seen = ", ".join(sorted(skipped)[:6])
        raise GraphFormatError(f"{name}: no line is in this format (expected tags {', '.join(spec)}; found {seen}); "
                               "wrong --format?")
    if skipped and on_unknown == "warn":
        desc = ", ".join(f"{t} x{c}" for t, c in sorted(skipped.items()))
        warnings.warn(f"{name}: skipped lines with unknown tags: {desc}", GraphFormatWarning, stacklevel=3)
    return out, skipped


def _int(name: str, no: int, tok: str) -> int:
    try:
        v = int(tok)
    except ValueError:
        raise GraphFormatError(f"{name}:{no}: expected an integer id, got {tok!r}") from None
    if abs(v) > _INT64_MAX:
        raise GraphFormatError(f"{name}:{no}: id {tok!r} out of range")
    return v


def _float(name: str, no: int, tok: str) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise GraphFormatError(f"{name}:{no}: expected a number, got {tok!r}") from None
    if not np.isfinite(v):
        raise GraphFormatError(f"{name}:{no}: non-finite number {tok!r}")
    return v


def _convert(name: str, tag: str, rows: list[list[str]], nos: IntArray, n_int: int, n_float: int) -> Rows:
    if not rows:
        return Rows(np.zeros((0, n_int), np.int64), np.zeros((0, n_float)), nos)
    # fast path: numpy converts the whole table; on failure locate the first bad token row by row
    try:
        ints = np.array([r[:n_int] for r in rows]).astype(np.int64)
        floats = np.array([r[n_int:] for r in rows]).astype(np.float64)
        if not np.all(np.isfinite(floats)):
            raise ValueError
        # numpy accepts some spellings python's int() rejects (and vice versa); re-check exotic ones cheaply
        return Rows(ints, floats, nos)
    except (ValueError, OverflowError):
        pass
    for r, no in zip(rows, nos, strict=True):
        for t in r[:n_int]:
            _int(name, int(no), t)
        for t in r[n_int:]:
            _float(name, int(no), t)
    # every token parsed individually but numpy still failed (e.g. an id that does not fit int64)
    raise GraphFormatError(f"{name}:{int(nos[0])}: {tag}: could not convert the fields to numbers")  # pragma: no cover


#: an information matrix whose smallest eigenvalue is below this fraction of its largest is singular for Cholesky
#: in double precision (the same floor as :func:`slam2d.graph.graph.sqrt_information`)
PD_RELATIVE_FLOOR = 1e-13


def check_pd(name: str, tag: str, om: Array, lines: IntArray) -> None:
    """GraphFormatError naming the first line whose (N, m, m) information matrix is not positive definite."""
    if om.shape[0] == 0:
        return
    big = ~(np.abs(om).reshape(om.shape[0], -1).max(axis=1) <= MAX_INFORMATION)  # NaN too
    if np.any(big):
        i = int(np.flatnonzero(big)[0])
        raise GraphFormatError(f"{name}:{int(lines[i])}: {tag} information entry above {MAX_INFORMATION:g} "
                               "(its products overflow in the solver)")
    ev = np.linalg.eigvalsh(om)
    bad = ~(ev[:, 0] > PD_RELATIVE_FLOOR * ev[:, -1])  # numerically singular fails Cholesky later: refuse it here
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise GraphFormatError(f"{name}:{int(lines[i])}: {tag} information matrix is not positive definite "
                               f"(eigenvalues {np.array2string(ev[i], precision=4)})")


def upper6_to_matrix(u: Array) -> Array:
    """Six upper-triangle numbers (row-major 11 12 13 22 23 33) -> symmetric (N, 3, 3)."""
    a, b, c, d, e, f = (u[:, k] for k in range(6))
    return np.stack([np.stack([a, b, c], -1), np.stack([b, d, e], -1), np.stack([c, e, f], -1)], axis=1)


def upper3_to_matrix(u: Array) -> Array:
    """Three upper-triangle numbers (11 12 22) -> symmetric (N, 2, 2)."""
    a, b, d = u[:, 0], u[:, 1], u[:, 2]
    return np.stack([np.stack([a, b], -1), np.stack([b, d], -1)], axis=1)


def measurement_frame_rotation(dtheta: Array) -> Array:
    """T = blockdiag(R(dtheta)^T, 1), (N, 3, 3): Omega_g2o = T Omega_frame_i T^T (see datasets README)."""
    c, s = np.cos(dtheta), np.sin(dtheta)
    T = np.zeros((dtheta.size, 3, 3))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, s, -s, c
    T[:, 2, 2] = 1.0
    return T


def check_duplicates(name: str, tag: str, ids: IntArray, lines: IntArray) -> None:
    if ids.size == 0:
        return
    order = np.argsort(ids, kind="stable")
    dup = np.flatnonzero(np.diff(ids[order]) == 0)
    if dup.size:
        k = order[dup[0] + 1]
        raise GraphFormatError(f"{name}:{int(lines[k])}: duplicate {tag} id {int(ids[k])}")


def check_known(name: str, tag: str, what: str, ids: IntArray, known: IntArray, lines: IntArray) -> None:
    """Every id in ``ids`` must be in ``known``."""
    if ids.size == 0:
        return
    ok = np.isin(ids, known)
    if not np.all(ok):
        k = int(np.flatnonzero(~ok)[0])
        raise GraphFormatError(f"{name}:{int(lines[k])}: {tag} refers to {what} {int(ids[k])}, which is not declared")


def fmt(x: float) -> str:
    """Shortest text that reads back to the same float."""
    return repr(float(x))
