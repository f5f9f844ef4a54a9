"""TORO 2D text format: ``VERTEX2 id x y th`` and ``EDGE2 i j dx dy dth I11 I12 I22 I33 I13 I23``.

The information is given in the order xx, xy, yy, thth, xth, yth and belongs to the error expressed in the frame of
pose i, ``e_T = [R_i^T (t_j - t_i) - [dx, dy] ; wrap(th_j - th_i - dth)]``. slam2d uses g2o's error
``e = Tr e_T`` with ``Tr = blockdiag(R(dth)^T, 1)``, so the equivalent information is ``Omega_g2o = Tr Omega_T Tr^T``
and both problems have the same chi2 at every configuration (``../shared/datasets/README.md``). Reading converts,
writing converts back. Error handling: see ``slam2d.io._text``.
"""

from __future__ import annotations

import os

import numpy as np

from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.initialization import spanning_tree_poses
from slam2d.io._text import (
    GraphFile,
    GraphFormatError,
    check_duplicates,
    check_known,
    check_pd,
    fmt,
    measurement_frame_rotation,
    read_lines,
    tokenize,
)
from slam2d.io.atomic import atomic_write

SPEC = {"VERTEX2": (1, 3), "EDGE2": (2, 9)}


def toro_to_matrix(u: np.ndarray) -> np.ndarray:
    """TORO's six numbers (xx, xy, yy, thth, xth, yth) -> symmetric (N, 3, 3)."""
    xx, xy, yy, tt, xt, yt = (u[:, k] for k in range(6))
    return np.stack([np.stack([xx, xy, xt], -1), np.stack([xy, yy, yt], -1), np.stack([xt, yt, tt], -1)], axis=1)


def read_toro(path: str | os.PathLike[str], *, on_unknown: str = "warn") -> GraphFile:
    """Read a TORO 2D graph; information converted to slam2d's (g2o) error convention."""
    name = os.fspath(path)
    rows, skipped = tokenize(path, read_lines(path), SPEC, on_unknown)
    if not any(r.lines.size for r in rows.values()):  # empty, blank or only comments: no graph to optimise
        raise GraphFormatError(f"{name}: no TORO lines (the file is empty or holds only comments)")
    v, e = rows["VERTEX2"], rows["EDGE2"]
    check_duplicates(name, "VERTEX2", v.ints[:, 0], v.lines)
    loop = e.ints[:, 0] == e.ints[:, 1]
    if np.any(loop):
        k = int(np.flatnonzero(loop)[0])
        raise GraphFormatError(f"{name}:{int(e.lines[k])}: EDGE2 connects vertex {int(e.ints[k, 0])} to itself")
    om_t = toro_to_matrix(e.floats[:, 3:])
    check_pd(name, "EDGE2", om_t, e.lines)
    T = measurement_frame_rotation(e.floats[:, 2])
    om = T @ om_t @ np.swapaxes(T, 1, 2)
    om = 0.5 * (om + np.swapaxes(om, 1, 2))
    check_pd(name, "EDGE2", om, e.lines)  # again after the rotation: a borderline matrix can lose definiteness
    g = FactorGraph()
    if e.ints.shape[0]:
        g.add_between(e.ints[:, 0], e.ints[:, 1], e.floats[:, :3], om)
    if v.ints.shape[0]:
        check_known(name, "EDGE2", "VERTEX2", e.ints[:, 0], v.ints[:, 0], e.lines)
        check_known(name, "EDGE2", "VERTEX2", e.ints[:, 1], v.ints[:, 0], e.lines)
        return GraphFile(g, Values(v.ints[:, 0], v.floats), "toro", initial_guess="vertices", skipped=skipped)
    keys = np.unique(e.ints[:, :2])
    return GraphFile(g, Values(keys, spanning_tree_poses(g, keys)), "toro", initial_guess="spanning tree",
                     skipped=skipped)


def write_toro(path: str | os.PathLike[str], graph: FactorGraph, values: Values) -> None:
    """Write poses and between factors as TORO VERTEX2/EDGE2 (information converted to TORO's frame and order)."""
    unsupported = [k for k in graph.kinds() if k != "between"]
    if unsupported:
        raise ValueError(f"write_toro: TORO 2D stores only relative-pose edges; cannot write {unsupported}")
    out = [f"VERTEX2 {int(k)} {fmt(p[0])} {fmt(p[1])} {fmt(p[2])}" for k, p in
           zip(values.pose_keys, values.poses, strict=True)]
    b = graph.block("between")
    T = measurement_frame_rotation(b.z[:, 2])
    om = np.swapaxes(T, 1, 2) @ b.information @ T
    for f in range(b.size):
        o = om[f]
        nums = [*b.z[f], o[0, 0], o[0, 1], o[1, 1], o[2, 2], o[0, 2], o[1, 2]]
        out.append(f"EDGE2 {int(b.keys[0, f])} {int(b.keys[1, f])} " + " ".join(fmt(x) for x in nums))
    with atomic_write(path) as fh:
        fh.write("\n".join(out) + ("\n" if out else ""))
