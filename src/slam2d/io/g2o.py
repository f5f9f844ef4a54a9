"""g2o 2D text format: read and write.

Tags read: ``VERTEX_SE2 id x y th``, ``VERTEX_XY id x y``, ``EDGE_SE2 i j dx dy dth I11 I12 I13 I22 I23 I33``
(relative pose, information upper triangle row-major; g2o EdgeSE2 error, see graph/factors.py),
``EDGE_SE2_XY i j x y I11 I12 I22`` (landmark j in the frame of pose i), ``EDGE_SE2_PRIOR i x y th I11..I33``
(pose prior) and ``FIX id ...`` (held poses). VERTEX_SE2 ids become pose keys and VERTEX_XY ids point keys (g2o
uses one id space; slam2d keeps the two namespaces, so the ids are kept as they are). Error handling: see
``slam2d.io._text``.

Writing: poses as VERTEX_SE2, points as VERTEX_XY. Because g2o has one id space, point ids that collide with a
pose id are shifted by ``max(pose id) + 1`` (all points, so the mapping is one offset; below the poses when that
would leave int64; see :func:`point_id_shift`; ``write_g2o`` returns the offset); factors without a g2o
tag (range-bearing, bearing, range, position, point prior) raise ValueError.
"""

from __future__ import annotations

import os

import numpy as np

from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.initialization import initial_points, spanning_tree_poses
from slam2d.io._text import (
    GraphFile,
    GraphFormatError,
    check_duplicates,
    check_known,
    check_pd,
    fmt,
    read_lines,
    tokenize,
    upper3_to_matrix,
    upper6_to_matrix,
)
from slam2d.io.atomic import atomic_write

_INT64_MAX = 2**63 - 1  # the readers' id range is [-_INT64_MAX, _INT64_MAX]

SPEC = {
    "VERTEX_SE2": (1, 3),
    "VERTEX_XY": (1, 2),
    "EDGE_SE2": (2, 9),
    "EDGE_SE2_XY": (2, 5),
    "EDGE_SE2_PRIOR": (1, 9),
}


def read_g2o(path: str | os.PathLike[str], *, on_unknown: str = "warn") -> GraphFile:
    """Read a 2D g2o file (see module doc). Raises GraphFormatError naming file:line and the token."""
    name = os.fspath(path)
    rows, skipped = tokenize(path, read_lines(path), SPEC, on_unknown, variable={"FIX": 1})
    if not any(r.lines.size for r in rows.values()):  # empty, blank or only comments: no graph to optimise
        raise GraphFormatError(f"{name}: no g2o lines (the file is empty or holds only comments)")
    vs, vx = rows["VERTEX_SE2"], rows["VERTEX_XY"]
    es, ex, ep = rows["EDGE_SE2"], rows["EDGE_SE2_XY"], rows["EDGE_SE2_PRIOR"]
    check_duplicates(name, "VERTEX_SE2", vs.ints[:, 0], vs.lines)
    check_duplicates(name, "VERTEX_XY", vx.ints[:, 0], vx.lines)
    both = np.intersect1d(vs.ints[:, 0], vx.ints[:, 0])
    if both.size:
        k = int(np.flatnonzero(vx.ints[:, 0] == both[0])[0])
        raise GraphFormatError(f"{name}:{int(vx.lines[k])}: VERTEX_XY id {int(both[0])} is also a VERTEX_SE2 id")
    self_loop = es.ints[:, 0] == es.ints[:, 1]
    if np.any(self_loop):
        k = int(np.flatnonzero(self_loop)[0])
        raise GraphFormatError(f"{name}:{int(es.lines[k])}: EDGE_SE2 connects vertex {int(es.ints[k, 0])} to itself")
    om_s = upper6_to_matrix(es.floats[:, 3:])
    om_x = upper3_to_matrix(ex.floats[:, 2:])
    om_p = upper6_to_matrix(ep.floats[:, 3:])
    check_pd(name, "EDGE_SE2", om_s, es.lines)
    check_pd(name, "EDGE_SE2_XY", om_x, ex.lines)
    check_pd(name, "EDGE_SE2_PRIOR", om_p, ep.lines)
    has_vertices = vs.ints.shape[0] + vx.ints.shape[0] > 0
    fixed = rows["FIX"].ints
    if has_vertices:
        pose_keys, point_keys = vs.ints[:, 0], vx.ints[:, 0]
        check_known(name, "EDGE_SE2", "VERTEX_SE2", es.ints[:, 0], pose_keys, es.lines)
        check_known(name, "EDGE_SE2", "VERTEX_SE2", es.ints[:, 1], pose_keys, es.lines)
        check_known(name, "EDGE_SE2_XY", "VERTEX_SE2", ex.ints[:, 0], pose_keys, ex.lines)
        check_known(name, "EDGE_SE2_XY", "VERTEX_XY", ex.ints[:, 1], point_keys, ex.lines)
        check_known(name, "EDGE_SE2_PRIOR", "VERTEX_SE2", ep.ints[:, 0], pose_keys, ep.lines)
        check_known(name, "FIX", "VERTEX_SE2", fixed, pose_keys, rows["FIX"].lines)
    else:
        pose_keys = np.unique(np.concatenate([es.ints[:, :2].reshape(-1), ex.ints[:, 0], ep.ints[:, 0]]))
        point_keys = np.unique(ex.ints[:, 1])
        clash = np.intersect1d(pose_keys, point_keys)
        if clash.size:
            k = int(np.flatnonzero(ex.ints[:, 1] == clash[0])[0])
            raise GraphFormatError(f"{name}:{int(ex.lines[k])}: EDGE_SE2_XY landmark id {int(clash[0])} is also "
                                   "used as a pose id")
        check_known(name, "FIX", "pose", fixed, pose_keys, rows["FIX"].lines)
    g = FactorGraph()
    if es.ints.shape[0]:
        g.add_between(es.ints[:, 0], es.ints[:, 1], es.floats[:, :3], om_s)
    if ex.ints.shape[0]:
        g.add_point(ex.ints[:, 0], ex.ints[:, 1], ex.floats[:, :2], om_x)
    if ep.ints.shape[0]:
        g.add_prior(ep.ints[:, 0], ep.floats[:, :3], om_p)
    if has_vertices:
        values = Values(pose_keys, vs.floats, point_keys, vx.floats)
        guess = "vertices"
    else:
        poses = spanning_tree_poses(g, pose_keys)
        pts = initial_points(g, pose_keys, poses, point_keys)
        values = Values(pose_keys, poses, point_keys, pts)
        guess = "spanning tree"
    return GraphFile(g, values, "g2o", np.unique(fixed), guess, skipped)


def point_id_shift(pose_keys: np.ndarray, point_keys: np.ndarray) -> int:
    """The offset :func:`write_g2o` adds to every point id: 0 unless a point id is also a pose id, else
    ``max(pose id) + 1 - min(0, min(point id))``; when that would leave int64 (which the readers refuse), the points
    go below the poses instead (``min(pose id) - 1 - max(point id)``); ValueError when neither fits."""
    if not (point_keys.size and pose_keys.size and np.intersect1d(pose_keys, point_keys).size):
        return 0
    lo, hi = int(point_keys.min()), int(point_keys.max())
    up = int(pose_keys.max()) + 1 - min(0, lo)
    if hi + up <= _INT64_MAX:
        return up
    down = int(pose_keys.min()) - 1 - hi
    if lo + down >= -_INT64_MAX:
        return down
    raise ValueError("write_g2o: the point ids cannot be moved clear of the pose ids within int64 (g2o has one id "
                     "space); renumber the landmarks")


def write_g2o(path: str | os.PathLike[str], graph: FactorGraph, values: Values, *,
              fixed_pose_keys: np.ndarray | None = None) -> int:
    """Write poses, points and between / point / prior factors as a g2o file (see module doc); returns the offset
    added to the point ids (:func:`point_id_shift`, 0 when they were kept)."""
    unsupported = [k for k in graph.kinds() if k not in ("between", "point", "prior")]
    if unsupported:
        raise ValueError(f"write_g2o: factor types {unsupported} have no g2o 2D tag")
    shift = point_id_shift(values.pose_keys, values.point_keys)
    out: list[str] = []
    for k, p in zip(values.pose_keys, values.poses, strict=True):
        out.append(f"VERTEX_SE2 {int(k)} {fmt(p[0])} {fmt(p[1])} {fmt(p[2])}")
    for k, p in zip(values.point_keys, values.points, strict=True):
        out.append(f"VERTEX_XY {int(k) + shift} {fmt(p[0])} {fmt(p[1])}")
    if fixed_pose_keys is not None:
        for k in np.asarray(fixed_pose_keys).reshape(-1):
            out.append(f"FIX {int(k)}")
    iu3 = np.triu_indices(3)
    iu2 = np.triu_indices(2)
    b = graph.block("between")
    om = b.information
    for f in range(b.size):
        nums = " ".join(fmt(v) for v in np.concatenate([b.z[f], om[f][iu3]]))
        out.append(f"EDGE_SE2 {int(b.keys[0, f])} {int(b.keys[1, f])} {nums}")
    b = graph.block("point")
    om = b.information
    for f in range(b.size):
        nums = " ".join(fmt(v) for v in np.concatenate([b.z[f], om[f][iu2]]))
        out.append(f"EDGE_SE2_XY {int(b.keys[0, f])} {int(b.keys[1, f]) + shift} {nums}")
    b = graph.block("prior")
    om = b.information
    for f in range(b.size):
        nums = " ".join(fmt(v) for v in np.concatenate([b.z[f], om[f][iu3]]))
        out.append(f"EDGE_SE2_PRIOR {int(b.keys[0, f])} {nums}")
    with atomic_write(path) as fh:
        fh.write("\n".join(out) + ("\n" if out else ""))
    return shift
