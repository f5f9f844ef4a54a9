"""The Kümmerle et al. (2009) relation metric: how well an estimate reproduces manually verified relative poses.

A relations file has one line ``t1 t2 x y z roll pitch yaw``: the true pose at ``t2`` expressed in the frame of the
pose at ``t1`` (2D data: z = roll = pitch = 0). For an estimate ``x(t)`` the error of one relation is
``e = between(d*, between(x(t1), x(t2)))``; the metric reports the mean and spread of ``|e_xy|`` and ``|e_theta|``
over all relations. ``x(t)`` is the pose whose timestamp equals ``t`` within ``tol_s`` (the files round the log's
timestamps, e.g. to 5 decimals on mit-csail).

A relation whose stamp matches no pose is an error naming ``file:line`` (``on_missing="raise"``) or a counted skip
(``on_missing="skip"``, listed in :attr:`RelationErrors.skipped`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle
from slam2d.log import LogFormatError

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: the longest line a relations file may have (one holds 8 numbers): a binary file fails at its first long line
MAX_LINE_CHARS = 10_000


@dataclass(frozen=True)
class Relations:
    """Relations read from a file. Shapes: stamps (R,2) [t1, t2], rel (R,3) [x, y, yaw], lines (R,) 1-based line
    numbers in ``path`` (for messages)."""

    path: str
    stamps: Array
    rel: Array
    lines: IntArray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def where(self, k: int) -> str:
        """``file:line`` of relation ``k``."""
        return f"{self.path}:{int(self.lines[k])}"


def read_relations(path: str | Path) -> Relations:
    """Read a relations file; raises :class:`LogFormatError` naming file:line on a malformed or non-finite line."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such relations file")
    if path.is_dir():
        raise IsADirectoryError(21, "is a directory, not a relations file", str(path))
    if not path.is_file():  # /dev/zero would never end, a FIFO would block
        raise LogFormatError(f"{path}: not a regular file (a relations file has lines 't1 t2 x y z roll pitch yaw')")
    st: list[list[float]] = []
    rel: list[list[float]] = []
    lines: list[int] = []
    with open(path, encoding="ascii", errors="replace") as f:
        for lineno, line in enumerate(iter(lambda: f.readline(MAX_LINE_CHARS + 1), ""), start=1):
            if len(line) > MAX_LINE_CHARS:
                raise LogFormatError(f"{path}:{lineno}: line longer than {MAX_LINE_CHARS} characters (not a "
                                     "relations file?)")
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                continue
            if len(tok) < 8:
                raise LogFormatError(f"{path}:{lineno}: relation needs 8 fields (t1 t2 x y z roll pitch yaw), "
                                     f"got {len(tok)}")
            try:
                v = [float(t) for t in tok[:8]]
            except ValueError:
                raise LogFormatError(f"{path}:{lineno}: non-numeric field in relation") from None
            if not all(np.isfinite(v)):
                raise LogFormatError(f"{path}:{lineno}: non-finite field in relation")
            st.append(v[:2])
            rel.append([v[2], v[3], v[7]])
            lines.append(lineno)
    return Relations(str(path), np.asarray(st, dtype=np.float64).reshape(-1, 2),
                     np.asarray(rel, dtype=np.float64).reshape(-1, 3), np.asarray(lines, dtype=np.int64))


@dataclass(frozen=True)
class RelationErrors:
    """Per-relation errors of one estimate. Shapes: trans_m (R',), rot_rad (R',) over the relations used;
    ``skipped`` holds ``file:line: reason`` of relations left out (stamps not in the log)."""

    trans_m: Array
    rot_rad: Array
    skipped: tuple[str, ...] = ()

    @property
    def missing(self) -> int:
        return len(self.skipped)

    def summary(self) -> dict[str, float]:
        """Mean/std of the translational (m) and rotational (deg) errors, plus the counts."""
        empty = len(self.trans_m) == 0
        nan = float("nan")
        return {
            "relations": float(len(self.trans_m)),
            "trans_mean_m": nan if empty else float(np.mean(self.trans_m)),
            "trans_std_m": nan if empty else float(np.std(self.trans_m)),
            "trans_sq_mean_m2": nan if empty else float(np.mean(self.trans_m**2)),
            "rot_mean_deg": nan if empty else float(np.degrees(np.mean(self.rot_rad))),
            "rot_std_deg": nan if empty else float(np.degrees(np.std(self.rot_rad))),
            "rot_sq_mean_deg2": nan if empty else float(np.mean(np.degrees(self.rot_rad) ** 2)),
            "missing": float(self.missing),
        }


def match_stamps(stamps_s: ArrayLike, query_s: ArrayLike, tol_s: float) -> tuple[IntArray, NDArray[np.bool_]]:
    """Index of the pose whose stamp is nearest each query, and whether it lies within ``tol_s``.

    Shapes: stamps (S,), query (...) -> (...), (...).
    """
    st = np.asarray(stamps_s, dtype=np.float64)
    q = np.asarray(query_s, dtype=np.float64)
    if len(st) == 0:
        return np.zeros(q.shape, dtype=np.int64), np.zeros(q.shape, dtype=bool)
    order = np.argsort(st, kind="stable")
    s = st[order]
    k = np.clip(np.searchsorted(s, q), 1, max(len(s) - 1, 1)) if len(s) > 1 else np.zeros(q.shape, np.int64)
    if len(s) > 1:
        k = np.where(np.abs(s[k - 1] - q) <= np.abs(s[k] - q), k - 1, k)
    return np.asarray(order[k], dtype=np.int64), np.abs(s[k] - q) <= tol_s


def relation_errors(stamps_s: ArrayLike, poses: ArrayLike, relations: Relations, *, tol_s: float = 1e-3,
                    on_missing: Literal["raise", "skip"] = "raise") -> RelationErrors:
    """Errors of ``poses`` (S,3) with timestamps ``stamps_s`` (S,) against ``relations``.

    A relation with a stamp farther than ``tol_s`` from every pose raises a ``ValueError`` naming its file:line, or
    with ``on_missing="skip"`` is left out and listed in ``skipped``.
    """
    if on_missing not in ("raise", "skip"):
        raise ValueError(f"relation_errors: on_missing must be 'raise' or 'skip' (got {on_missing!r})")
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    st = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    if len(st) != len(p):
        raise ValueError(f"relation_errors: {len(st)} stamps for {len(p)} poses")
    idx, ok = match_stamps(st, relations.stamps, tol_s)
    both = ok.all(axis=1)
    skipped = []
    for k in np.flatnonzero(~both).tolist():
        t = relations.stamps[k, 0] if not ok[k, 0] else relations.stamps[k, 1]
        skipped.append(f"{relations.where(k)}: stamp {t:.6f} matches no pose within {tol_s} s")
    if skipped and on_missing == "raise":
        more = f" (and {len(skipped) - 1} more)" if len(skipped) > 1 else ""
        raise ValueError(f"{skipped[0]}{more}")
    d = se2.between(p[idx[both, 0]], p[idx[both, 1]])
    e = se2.between(relations.rel[both], d)
    return RelationErrors(np.hypot(e[:, 0], e[:, 1]), np.abs(wrap_angle(e[:, 2])), tuple(skipped))
