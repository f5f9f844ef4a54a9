"""Initial guesses for graph optimisation: spanning-tree (odometry) composition and chordal relaxation.

* :func:`spanning_tree_poses`: compose relative-pose measurements along a minimum spanning tree whose edge weight is
  ``|i - j|`` (so a complete odometry chain ``i -> i+1`` is always the tree: the "odometry chain" initialisation of
  the reference numbers), rooted at the lowest key of each component, which is placed at the origin (or at its value
  in ``anchor``). Duplicate measurements of a pair: the first one wins.
* :func:`chordal_poses`: rotations from the linear chordal relaxation (Carlone et al., ICRA 2015: solve
  ``min sum w_ij |q_j - q_i e^{i dth}|^2`` over unit-free complex numbers q with q_root = 1, then normalise),
  translations from the linear least squares ``t_j - t_i = R_i dt_ij`` with those rotations fixed; weights from the
  information diagonal.
* :func:`initial_points`: each landmark from its first point / range-bearing observation by an initialised pose.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from slam2d.geometry import se2
from slam2d.graph.graph import FactorGraph, GraphError

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _between_edges(graph: FactorGraph, pose_keys: IntArray) -> tuple[IntArray, IntArray, Array, Array]:
    b = graph.block("between")
    order = np.argsort(pose_keys)
    sk = pose_keys[order]
    ii = order[np.searchsorted(sk, b.keys[0])]
    jj = order[np.searchsorted(sk, b.keys[1])]
    return ii, jj, b.z, b.information


def spanning_tree_poses(graph: FactorGraph, pose_keys: ArrayLike, anchor: Array | None = None) -> Array:
    """Poses composed along the |i-j|-weighted minimum spanning tree of the between factors.

    Shapes: pose_keys (P,) -> (P, 3). Poses not connected by between factors stay at the origin (or ``anchor``).
    """
    keys = np.asarray(pose_keys, np.int64)
    P = keys.size
    out = np.zeros((P, 3)) if anchor is None else np.array(anchor, dtype=np.float64, copy=True)
    if P == 0 or graph.block("between").size == 0:
        return out
    ii, jj, z, _ = _between_edges(graph, keys)
    # first measurement of each unordered pair wins; weight |key_i - key_j| (+ tiny order tie-break)
    a, b = np.minimum(ii, jj), np.maximum(ii, jj)
    _, first = np.unique(a * P + b, return_index=True)
    w = np.abs(keys[ii[first]] - keys[jj[first]]).astype(np.float64) + 1e-9 * np.arange(first.size) / first.size
    w = np.maximum(w, 1e-12)
    mst = minimum_spanning_tree(sp.coo_matrix((w, (a[first], b[first])), shape=(P, P)).tocsr())
    tree = mst + mst.T
    # map tree edges back to measurements (directed i -> j as measured)
    lookup = {}
    for e in first:
        lookup[(int(ii[e]), int(jj[e]))] = (e, False)
        lookup[(int(jj[e]), int(ii[e]))] = (e, True)
    ncomp, labels = connected_components(tree, directed=False)
    for comp in range(ncomp):
        members = np.flatnonzero(labels == comp)
        root = int(members[np.argmin(keys[members])])
        order, pred = breadth_first_order(tree, root, directed=False, return_predecessors=True)
        for node in order[1:]:
            par = int(pred[node])
            e, rev = lookup[(par, int(node))]
            rel = se2.inverse(z[e]) if rev else z[e]
            out[node] = se2.compose(out[par], rel)
    return out


def chordal_poses(graph: FactorGraph, pose_keys: ArrayLike, fixed: ArrayLike = ()) -> Array:
    """Chordal-relaxation initial guess from the between factors (see module doc). Shapes: (P,) -> (P, 3).

    The lowest-key pose of each component (plus any in ``fixed``) is held at the origin orientation/position.
    """
    keys = np.asarray(pose_keys, np.int64)
    P = keys.size
    if P == 0 or graph.block("between").size == 0:
        return np.zeros((P, 3))
    ii, jj, z, om = _between_edges(graph, keys)
    E = ii.size
    adj = sp.coo_matrix((np.ones(E), (ii, jj)), shape=(P, P))
    ncomp, labels = connected_components(adj, directed=False)
    roots = [int(np.flatnonzero(labels == c)[np.argmin(keys[labels == c])]) for c in range(ncomp)]
    held = np.zeros(P, bool)
    held[roots] = True
    fixed_arr = np.asarray(fixed, np.int64).reshape(-1)
    if fixed_arr.size:
        held[np.searchsorted(np.sort(keys), fixed_arr)] = True
    free = np.flatnonzero(~held)
    col = np.full(P, -1)
    col[free] = np.arange(free.size)

    def solve(rows_blocks: list[tuple[IntArray, IntArray, Array]], rhs: Array, nvar: int) -> Array:
        r = np.concatenate([b[0] for b in rows_blocks])
        c = np.concatenate([b[1] for b in rows_blocks])
        v = np.concatenate([b[2] for b in rows_blocks])
        keep = c >= 0
        A = sp.csr_matrix((v[keep], (r[keep], c[keep])), shape=(rhs.size, nvar))
        N = (A.T @ A).tocsc()
        N = N + sp.eye(nvar) * 1e-12 * max(1.0, float(N.diagonal().max()) if nvar else 1.0)
        return np.asarray(spla.spsolve(N, A.T @ rhs)) if nvar else np.zeros(0)

    # --- rotations: unknowns (c_k, s_k) for free poses; held poses have q = 1
    wr = np.sqrt(np.maximum(om[:, 2, 2], 1e-12))
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    er = np.arange(E)
    # q_j - q_i * e^{i z} = 0 ; real: c_j - (c_i cz - s_i sz), imag: s_j - (c_i sz + s_i cz)
    ci, cj = col[ii], col[jj]

    def var(cidx: IntArray, part: int) -> IntArray:
        return np.where(cidx >= 0, 2 * cidx + part, -1)

    rows, rhs = [], np.zeros(2 * E)
    rows.append((2 * er, var(cj, 0), wr))
    rows.append((2 * er, var(ci, 0), -wr * cz))
    rows.append((2 * er, var(ci, 1), wr * sz))
    rows.append((2 * er + 1, var(cj, 1), wr))
    rows.append((2 * er + 1, var(ci, 0), -wr * sz))
    rows.append((2 * er + 1, var(ci, 1), -wr * cz))
    # held poses contribute constants (q = 1): move them to the right-hand side
    hi, hj = ci < 0, cj < 0
    rhs[2 * er] += np.where(hi, wr * cz, 0.0) - np.where(hj, wr, 0.0)
    rhs[2 * er + 1] += np.where(hi, wr * sz, 0.0)
    q = solve(rows, rhs, 2 * free.size).reshape(-1, 2)
    theta = np.zeros(P)
    theta[free] = np.arctan2(q[:, 1], q[:, 0])

    # --- translations: t_j - t_i = R_i dt
    wt = np.sqrt(np.maximum(0.5 * (om[:, 0, 0] + om[:, 1, 1]), 1e-12))
    c, s = np.cos(theta[ii]), np.sin(theta[ii])
    rx = c * z[:, 0] - s * z[:, 1]
    ry = s * z[:, 0] + c * z[:, 1]
    rows = []
    for part, _rr in ((0, rx), (1, ry)):
        rows.append((2 * er + part, var(cj, part), wt))
        rows.append((2 * er + part, var(ci, part), -wt))
    rhs_t = np.empty(2 * E)
    rhs_t[0::2], rhs_t[1::2] = wt * rx, wt * ry
    t = solve(rows, rhs_t, 2 * free.size).reshape(-1, 2)
    out = np.zeros((P, 3))
    out[free, :2] = t
    out[:, 2] = se2.wrap_angle(theta)
    return out


def initial_points(graph: FactorGraph, pose_keys: ArrayLike, poses: Array, point_keys: ArrayLike) -> Array:
    """Landmarks from their first observation (point, then range-bearing factors). Shapes: -> (L, 2).

    Raises GraphError for a landmark that has neither kind of observation.
    """
    pk = np.asarray(pose_keys, np.int64)
    lk = np.asarray(point_keys, np.int64)
    out = np.full((lk.size, 2), np.nan)
    if lk.size == 0:
        return np.zeros((0, 2))
    porder, lorder = np.argsort(pk), np.argsort(lk)
    for kind in ("point", "range_bearing"):
        b = graph.block(kind)
        if b.size == 0:
            continue
        li = lorder[np.searchsorted(lk[lorder], b.keys[1])]
        pi = porder[np.searchsorted(pk[porder], b.keys[0])]
        uniq, first = np.unique(li, return_index=True)
        todo = np.isnan(out[uniq, 0])
        f = first[todo]
        pose = poses[pi[f]]
        if kind == "point":
            out[uniq[todo]] = se2.transform_points(pose, b.z[f])
        else:
            ang = pose[:, 2] + b.z[f, 1]
            out[uniq[todo]] = pose[:, :2] + b.z[f, :1] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    missing = np.isnan(out[:, 0])
    if np.any(missing):
        raise GraphError(f"landmark {int(lk[np.flatnonzero(missing)[0]])} has no point or range-bearing observation "
                         "to initialise it from")
    return out
