"""iSAM 1.x text format (the staged M3500, city10000 and Victoria Park files).

* ``ODOMETRY i j dx dy dth s11 s12 s13 s22 s23 s33`` (``EDGE2`` is accepted as a synonym): relative pose of j in
  the frame of i; the six numbers are the upper-triangular SQUARE-ROOT information ``S`` (row-major),
  ``Omega = S^T S``, for iSAM's error ``[R_i^T (t_j - t_i) - [dx, dy] ; wrap(...)]`` (frame of pose i, as TORO),
  converted to slam2d's g2o convention with ``Tr = blockdiag(R(dth)^T, 1)``: ``Omega_g2o = Tr S^T S Tr^T``.
* ``LANDMARK i l x y s11 s12 s22``: landmark l at (x, y) in the frame of pose i, ``Omega = S^T S`` (a ``point``
  factor; same error convention in both systems).
* Pose ids and landmark ids are separate namespaces (they overlap in cityTrees10000). No vertex lines: the initial
  guess is the spanning tree of the odometry (the odometry chain for these files) and each landmark's first
  observation (``GraphFile.initial_guess == "spanning tree"``). Duplicate odometry lines between the same pair are
  kept as separate factors (iSAM does).
"""

from __future__ import annotations

import os

import numpy as np

from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.initialization import initial_points, spanning_tree_poses
from slam2d.io._text import (
    GraphFile,
    GraphFormatError,
    check_pd,
    fmt,
    measurement_frame_rotation,
    read_lines,
    tokenize,
)
from slam2d.io.atomic import atomic_write

SPEC = {"ODOMETRY": (2, 9), "EDGE2": (2, 9), "LANDMARK": (2, 5)}


def _sqrt6(u: np.ndarray) -> np.ndarray:
    S = np.zeros((u.shape[0], 3, 3))
    S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2] = (u[:, k] for k in range(6))
    return S


def _sqrt3(u: np.ndarray) -> np.ndarray:
    S = np.zeros((u.shape[0], 2, 2))
    S[:, 0, 0], S[:, 0, 1], S[:, 1, 1] = u[:, 0], u[:, 1], u[:, 2]
    return S


def read_isam(path: str | os.PathLike[str], *, on_unknown: str = "warn") -> GraphFile:
    """Read an iSAM text graph (see module doc)."""
    name = os.fspath(path)
    rows, skipped = tokenize(path, read_lines(path), SPEC, on_unknown)
    if not any(r.lines.size for r in rows.values()):  # empty, blank or only comments: no graph to optimise
        raise GraphFormatError(f"{name}: no iSAM lines (the file is empty or holds only comments)")
    od, ed, lm = rows["ODOMETRY"], rows["EDGE2"], rows["LANDMARK"]
    order = np.argsort(np.concatenate([od.lines, ed.lines]), kind="stable")
    ints = np.concatenate([od.ints, ed.ints])[order]
    floats = np.concatenate([od.floats, ed.floats])[order]
    lines = np.concatenate([od.lines, ed.lines])[order]
    loop = ints[:, 0] == ints[:, 1]
    if np.any(loop):
        k = int(np.flatnonzero(loop)[0])
        raise GraphFormatError(f"{name}:{int(lines[k])}: odometry connects pose {int(ints[k, 0])} to itself")
    S = _sqrt6(floats[:, 3:])
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is reported by check_pd with file:line
        om_i = np.swapaxes(S, 1, 2) @ S
    check_pd(name, "ODOMETRY", om_i, lines)
    T = measurement_frame_rotation(floats[:, 2])
    om = T @ om_i @ np.swapaxes(T, 1, 2)
    om = 0.5 * (om + np.swapaxes(om, 1, 2))
    check_pd(name, "ODOMETRY", om, lines)  # again after the rotation: a borderline matrix can lose definiteness
    SL = _sqrt3(lm.floats[:, 2:])
    with np.errstate(over="ignore", invalid="ignore"):
        om_l = np.swapaxes(SL, 1, 2) @ SL
    check_pd(name, "LANDMARK", om_l, lm.lines)
    g = FactorGraph()
    if ints.shape[0]:
        g.add_between(ints[:, 0], ints[:, 1], floats[:, :3], om)
    if lm.ints.shape[0]:
        g.add_point(lm.ints[:, 0], lm.ints[:, 1], lm.floats[:, :2], om_l)
    pose_keys = np.unique(np.concatenate([ints[:, :2].reshape(-1), lm.ints[:, 0]]))
    point_keys = np.unique(lm.ints[:, 1])
    poses = spanning_tree_poses(g, pose_keys)
    points = initial_points(g, pose_keys, poses, point_keys)
    return GraphFile(g, Values(pose_keys, poses, point_keys, points), "isam", initial_guess="spanning tree",
                     skipped=skipped)


def write_isam(path: str | os.PathLike[str], graph: FactorGraph, values: Values | None = None) -> None:
    """Write between factors as ODOMETRY and point factors as LANDMARK lines (square-root information, iSAM's
    frame). iSAM text has no vertices, so ``values`` is not written."""
    unsupported = [k for k in graph.kinds() if k not in ("between", "point")]
    if unsupported:
        raise ValueError(f"write_isam: iSAM text has no tag for {unsupported}")
    out: list[str] = []
    b = graph.block("between")
    T = measurement_frame_rotation(b.z[:, 2])
    om = np.swapaxes(T, 1, 2) @ b.information @ T
    om = 0.5 * (om + np.swapaxes(om, 1, 2))
    S = np.swapaxes(np.linalg.cholesky(om), 1, 2) if b.size else np.zeros((0, 3, 3))
    iu3 = np.triu_indices(3)
    for f in range(b.size):
        nums = [*b.z[f], *S[f][iu3]]
        out.append(f"ODOMETRY {int(b.keys[0, f])} {int(b.keys[1, f])} " + " ".join(fmt(x) for x in nums))
    b = graph.block("point")
    iu2 = np.triu_indices(2)
    for f in range(b.size):
        nums = [*b.z[f], *b.sqrt_info[f][iu2]]
        out.append(f"LANDMARK {int(b.keys[0, f])} {int(b.keys[1, f])} " + " ".join(fmt(x) for x in nums))
    with atomic_write(path) as fh:
        fh.write("\n".join(out) + ("\n" if out else ""))
