"""Problem analysis (done once per structure) and linearisation (done every iteration).

:class:`Analysis` resolves factor keys to variable indices, finds connected components and fixes the gauge, lays
out the state vector, builds the CSC pattern of the UPPER triangle of ``H = J^T Omega J`` and precomputes, for every
factor type, the position in H's data array of each upper-triangle entry (a <= b) of that factor's local ``D x D``
block product (mapped to the global upper entry; entries touching a held variable go to a dump slot). The pattern is
built from the variable-block structure and expanded to scalars. The fill-reducing ordering is the linear solver's
(AMD inside qdldl / CHOLMOD, MMD in SuperLU), computed once on the first factorisation. An iteration then only
evaluates residuals/Jacobians in one vectorised call per factor type (batch-last arrays) and scatters the block
products with ``np.bincount``.

Gauge rule: a connected component of the factor graph is *anchored* if it contains a pose prior factor or a pose
the caller holds fixed; otherwise its lowest-key pose is held fixed (the convention of the reference numbers:
"first pose held fixed, no prior"). Variables that appear in no factor are held fixed and reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.sparse.csgraph import connected_components

from slam2d.geometry import se2
from slam2d.graph.factors import KINDS
from slam2d.graph.graph import FactorBlock, FactorGraph, GraphError, Values
from slam2d.graph.robust import robustify

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _lookup(keys: IntArray, wanted: IntArray, what: str, kind: str) -> IntArray:
    """Indices of ``wanted`` in ``keys``; GraphError naming the first missing key."""
    if wanted.size == 0:
        return np.zeros(0, np.int64)
    if keys.size == 0:
        raise GraphError(f"{kind} factor 0 refers to {what} {int(wanted[0])}, which has no value")
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    pos = np.searchsorted(sk, wanted)
    pos_c = np.minimum(pos, sk.size - 1)
    bad = sk[pos_c] != wanted
    if np.any(bad):
        f = int(np.flatnonzero(bad)[0])
        raise GraphError(f"{kind} factor {f} refers to {what} {int(wanted[f])}, which has no value")
    return order[pos_c].astype(np.int64)


@dataclass
class _TypePlan:
    block: FactorBlock
    var_idx: list[IntArray]  # per argument: index into poses or points arrays
    cols: IntArray  # (N, D) global columns, -1 for held variables
    h_pos: IntArray  # (Pp*N,) positions in H data of the local upper pairs, pair-major (nnz = dump)
    g_pos: IntArray  # (D*N,) positions in the gradient, column-major (n = dump)
    pa: IntArray  # (Pp,) local row of each upper pair
    pb: IntArray  # (Pp,) local column of each upper pair
    zT: Array  # (meas_dim, N) measurements, batch-last
    LT: Array  # (m, m, N) sqrt information, batch-last


class Analysis:
    """Symbolic analysis of a (graph, values) pair; valid while the structure and the variable sets are unchanged.

    Shapes: ``indptr`` (n+1,), ``indices`` (nnz,) describe the upper triangle of H in CSC; ``diag_pos`` (n,).
    """

    def __init__(self, graph: FactorGraph, values: Values, *, fixed_pose_keys: ArrayLike = (),
                 gauge: str = "first_pose") -> None:
        if gauge not in ("first_pose", "none"):
            raise ValueError(f"gauge must be 'first_pose' or 'none' (got {gauge!r})")
        self.structure_version = graph.structure_version
        self.pose_keys = values.pose_keys.copy()
        self.point_keys = values.point_keys.copy()
        P, L = self.pose_keys.size, self.point_keys.size
        blocks = graph.blocks()
        var_idx: list[list[IntArray]] = []
        for b in blocks:
            idx = []
            for a, vk in enumerate(KINDS[b.kind].var_kinds):
                keys = self.pose_keys if vk == "pose" else self.point_keys
                idx.append(_lookup(keys, b.keys[a], vk, b.kind))
            var_idx.append(idx)

        # --- connectivity over variables: node = pose index, or P + point index
        def node(vk: str, ix: IntArray) -> IntArray:
            return ix if vk == "pose" else ix + P

        rows, cols, used = [], [], np.zeros(P + L, bool)
        anchored_nodes = []
        fixed_idx = _lookup(self.pose_keys, np.asarray(fixed_pose_keys, np.int64).reshape(-1), "pose", "FIX")
        for b, idx in zip(blocks, var_idx, strict=True):
            vks = KINDS[b.kind].var_kinds
            nodes = [node(vk, ix) for vk, ix in zip(vks, idx, strict=True)]
            for nd in nodes:
                used[nd] = True
            if len(nodes) == 2:
                rows.append(nodes[0])
                cols.append(nodes[1])
            if b.kind == "prior":
                anchored_nodes.append(nodes[0])
        if rows:
            r, c = np.concatenate(rows), np.concatenate(cols)
        else:
            r = c = np.zeros(0, np.int64)
        adj = sp.coo_matrix((np.ones(r.size), (r, c)), shape=(P + L, P + L))
        ncomp, labels = connected_components(adj, directed=False)
        held = np.zeros(P + L, bool)
        held[fixed_idx] = True
        held[~used] = True
        self.unconstrained_pose_keys = self.pose_keys[~used[:P]]
        self.unconstrained_point_keys = self.point_keys[~used[P:]]
        anchored = np.zeros(ncomp, bool)
        if anchored_nodes:
            anchored[labels[np.concatenate(anchored_nodes)]] = True
        anchored[labels[fixed_idx]] = True
        anchored[labels[~used]] = True  # isolated variables are held themselves
        comp_ids = np.unique(labels[used]) if used.any() else np.zeros(0, np.int64)
        self.num_components = int(comp_ids.size)
        gauge_held = []
        if gauge == "first_pose":
            for comp in comp_ids[~anchored[comp_ids]]:
                members = np.flatnonzero(labels[:P] == comp)
                if members.size == 0:
                    continue  # points only: constrained by point priors / positions, or singular (reported later)
                first = members[np.argmin(self.pose_keys[members])]
                held[first] = True
                gauge_held.append(int(self.pose_keys[first]))
        self.gauge_pose_keys = np.array(sorted(gauge_held), np.int64)
        self.held_pose = held[:P]
        self.held_point = held[P:]

        # --- state layout: free poses (3 each) then free points (2 each)
        self.free_pose = np.flatnonzero(~self.held_pose)
        self.free_point = np.flatnonzero(~self.held_point)
        n = 3 * self.free_pose.size + 2 * self.free_point.size
        self.n = n

        # --- pattern at the level of variable blocks (far fewer keys than scalar entries), expanded to scalars.
        # Free variables are numbered in state order: v has offset voff[v] and dimension vdim[v].
        Fp, Fl = self.free_pose.size, self.free_point.size
        V = Fp + Fl
        if V == 0:
            if not blocks:
                raise GraphError("nothing to optimise: the graph has no factors")
            raise GraphError("nothing to optimise: every pose is held fixed (FIX / fixed_pose_keys) and there are "
                             "no landmarks")
        pose_var = np.full(P, -1, np.int64)
        pose_var[self.free_pose] = np.arange(Fp)
        point_var = np.full(L, -1, np.int64)
        point_var[self.free_point] = Fp + np.arange(Fl)
        vdim = np.concatenate([np.full(Fp, 3, np.int64), np.full(Fl, 2, np.int64)])
        voff = (np.cumsum(vdim) - vdim).astype(np.int64)
        bkeys, infos = [], []
        for b, idx in zip(blocks, var_idx, strict=True):
            kinds = KINDS[b.kind].var_kinds
            U = np.stack([pose_var[ix] if vk == "pose" else point_var[ix] for vk, ix in zip(kinds, idx, strict=True)])
            ka, kb = np.triu_indices(len(kinds))
            ua, ub = U[ka], U[kb]  # (Kp, N) argument pairs A <= B
            bk = np.where((ua >= 0) & (ub >= 0), np.maximum(ua, ub) * V + np.minimum(ua, ub), -1)
            bkeys.append(bk.reshape(-1))
            infos.append((U, ka, kb))
        cat = np.concatenate(bkeys) if bkeys else np.zeros(0, np.int64)
        valid = cat >= 0
        ublk, binv_valid = np.unique(cat[valid], return_inverse=True)
        binv = np.full(cat.size, -1, np.int64)
        binv[valid] = binv_valid
        bcol, brow = ublk // max(V, 1), ublk % max(V, 1)  # sorted by (column var, row var): diagonal block last
        dr = vdim[brow]
        offdiag = brow < bcol
        excl = np.cumsum(dr) - dr
        rowoff = excl - excl[np.searchsorted(bcol, bcol)]  # rows of the earlier blocks in the same block column
        above = np.bincount(bcol[offdiag], weights=dr[offdiag], minlength=V).astype(np.int64)
        col_var = np.repeat(np.arange(V), vdim)
        col_comp = np.arange(n) - voff[col_var]
        indptr = np.concatenate([[0], np.cumsum(above[col_var] + col_comp + 1)]).astype(np.int64)
        colstart = indptr[:-1]
        self.nnz = int(indptr[-1])
        self.indptr = indptr.astype(np.int32)
        indices = np.full(self.nnz, -1, np.int64)
        dc = vdim[bcol]
        for i in range(3):
            for j in range(3):
                m = (i < dr) & (j < dc) & (offdiag | (i <= j))
                indices[colstart[voff[bcol[m]] + j] + rowoff[m] + i] = voff[brow[m]] + i
        if np.any(indices < 0) or (V and not np.array_equal(np.unique(ublk[~offdiag] // max(V, 1)), np.arange(V))):
            raise GraphError("internal: inconsistent Hessian pattern")  # pragma: no cover
        self.indices = indices.astype(np.int32)
        self.diag_pos = colstart + above[col_var] + col_comp
        # --- per factor type: the data position of each local upper pair (pa <= pb) of the D x D block product.
        # H is symmetric, so the pair goes to the global upper entry whatever the order of the factor's variables.
        self.plans: list[_TypePlan] = []
        start = 0
        for b, idx, (U, ka, kb) in zip(blocks, var_idx, infos, strict=True):
            kinds = KINDS[b.kind].var_kinds
            N = b.size
            dims = [3 if vk == "pose" else 2 for vk in kinds]
            arg_of = np.repeat(np.arange(len(kinds)), dims)
            comp_of = np.concatenate([np.arange(d) for d in dims])
            pa, pb = np.triu_indices(int(sum(dims)))
            kp_of = {(int(a), int(c)): k for k, (a, c) in enumerate(zip(ka, kb, strict=True))}
            blk = binv[start : start + ka.size * N].reshape(ka.size, N)
            start += ka.size * N
            A, B = arg_of[pa], arg_of[pb]
            kp = np.array([kp_of[(int(a), int(c))] for a, c in zip(A, B, strict=True)])
            uA, uB = U[A], U[B]  # (Pp, N)
            ia, ib = comp_of[pa][:, None], comp_of[pb][:, None]
            swap = uA > uB
            ii = np.where(swap, ib, ia)
            jj = np.where(swap, ia, ib)
            cvar = np.maximum(uA, uB)
            bb = blk[kp]
            ok = bb >= 0
            h_pos = np.full((pa.size, N), self.nnz, np.int64)
            h_pos[ok] = colstart[voff[cvar[ok]] + jj[ok]] + rowoff[bb[ok]] + ii[ok]
            gcols = np.where(U[arg_of] >= 0, voff[np.maximum(U[arg_of], 0)] + comp_of[:, None], -1)  # (D, N)
            gp = np.where(gcols >= 0, gcols, n).reshape(-1)
            LT = np.ascontiguousarray(np.moveaxis(b.sqrt_info, 0, -1))
            self.plans.append(_TypePlan(b, idx, gcols.T, h_pos.reshape(-1), gp, pa.astype(np.int64),
                                        pb.astype(np.int64), np.ascontiguousarray(b.z.T), LT))

    def compatible(self, graph: FactorGraph, values: Values) -> bool:
        """True when this analysis can be reused for (graph, values)."""
        return (graph.structure_version == self.structure_version
                and np.array_equal(values.pose_keys, self.pose_keys)
                and np.array_equal(values.point_keys, self.point_keys))

    # ------------------------------------------------------------------------------------------ evaluation
    def _gather(self, plan: _TypePlan, posesT: Array, pointsT: Array) -> list[Array]:
        out = []
        for vk, ix in zip(KINDS[plan.block.kind].var_kinds, plan.var_idx, strict=True):
            out.append(posesT[:, ix] if vk == "pose" else pointsT[:, ix])
        return out

    @staticmethod
    def _whiten(LT: Array, x: Array) -> Array:
        """L x per factor for upper-triangular L (LT[i, k] is an (N,) row; it broadcasts over x's middle axis).
        Shapes: (m,m,N),(m,N) -> (m,N) or (m,m,N),(m,D,N) -> (m,D,N)."""
        out = np.empty_like(x)
        for i in range(LT.shape[0]):
            acc = LT[i, i] * x[i]
            for k in range(i + 1, LT.shape[0]):
                acc += LT[i, k] * x[k]
            out[i] = acc
        return out

    def _residuals(self, plan: _TypePlan, posesT: Array, pointsT: Array) -> tuple[Array, Array]:
        """Whitened residual r (m, N) and whitened Jacobian A (m, D, N)."""
        e, J = KINDS[plan.block.kind].evaluate(*self._gather(plan, posesT, pointsT), plan.zT)
        return self._whiten(plan.LT, e), self._whiten(plan.LT, J)

    def errors(self, poses: Array, points: Array) -> list[tuple[str, Array, Array, Array]]:
        """Per type: (kind, whitened squared error s (N,), robust cost rho (N,), IRLS weight w (N,))."""
        out = []
        posesT, pointsT = np.ascontiguousarray(poses.T), np.ascontiguousarray(points.T)
        for plan in self.plans:
            b = plan.block
            e, _ = KINDS[b.kind].evaluate(*self._gather(plan, posesT, pointsT), plan.zT)
            r = self._whiten(plan.LT, e)
            s = np.einsum("in,in->n", r, r)
            rho, w = robustify(s, b.kernel, b.kernel_param)
            out.append((b.kind, s, rho, w))
        return out

    def linearize(self, poses: Array, points: Array) -> tuple[float, float, Array, Array]:
        """Robust cost, raw chi2, upper-H data (nnz,) and gradient g = J^T Omega e (n,) at the given values."""
        data = np.zeros(self.nnz + 1)
        grad = np.zeros(self.n + 1)
        cost = chi2 = 0.0
        posesT, pointsT = np.ascontiguousarray(poses.T), np.ascontiguousarray(points.T)
        for plan in self.plans:
            b = plan.block
            r, A = self._residuals(plan, posesT, pointsT)
            s = np.einsum("in,in->n", r, r)
            rho, w = robustify(s, b.kernel, b.kernel_param)
            cost += float(rho.sum())
            chi2 += float(s.sum())
            if np.any(w != 1.0):
                sw = np.sqrt(w)
                A = A * sw
                r = r * sw
            # upper pairs of A^T A: sum over residual rows of products of two Jacobian columns
            hf = A[0, plan.pa] * A[0, plan.pb]
            gf = A[0] * r[0]
            for i in range(1, A.shape[0]):
                hf += A[i, plan.pa] * A[i, plan.pb]
                gf += A[i] * r[i]
            data += np.bincount(plan.h_pos, weights=hf.reshape(-1), minlength=self.nnz + 1)
            grad += np.bincount(plan.g_pos, weights=gf.reshape(-1), minlength=self.n + 1)
        return cost, chi2, data[: self.nnz], grad[: self.n]

    def cost(self, poses: Array, points: Array) -> tuple[float, float]:
        """(robust cost, raw chi2) at the given values."""
        cost = chi2 = 0.0
        for _, s, rho, _ in self.errors(poses, points):
            cost += float(rho.sum())
            chi2 += float(s.sum())
        return cost, chi2

    def upper(self, data: Array) -> sp.csc_matrix:
        """Upper triangle of H as CSC with this analysis' pattern."""
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))

    def retract(self, poses: Array, points: Array, dx: Array) -> tuple[Array, Array]:
        """Apply a step to the free variables (additive with heading wrap); returns new arrays."""
        p, q = poses.copy(), points.copy()
        k = 3 * self.free_pose.size
        p[self.free_pose] = se2.retract(p[self.free_pose], dx[:k].reshape(-1, 3))
        q[self.free_point] += dx[k:].reshape(-1, 2)
        return p, q

    def variable_slices(self, pose_keys: ArrayLike = (), point_keys: ArrayLike = ()) -> tuple[IntArray, list]:
        """State-vector columns of the selected variables (-1 for held ones) and a label per variable."""
        pk = np.asarray(pose_keys, np.int64).reshape(-1)
        lk = np.asarray(point_keys, np.int64).reshape(-1)
        pi = _lookup(self.pose_keys, pk, "pose", "marginal")
        li = _lookup(self.point_keys, lk, "point", "marginal")
        cols, labels = [], []
        k3 = 3 * self.free_pose.size
        rank_pose = np.full(self.pose_keys.size, -1)
        rank_pose[self.free_pose] = np.arange(self.free_pose.size)
        rank_point = np.full(self.point_keys.size, -1)
        rank_point[self.free_point] = np.arange(self.free_point.size)
        for key, i in zip(pk, pi, strict=True):
            rk = rank_pose[i]
            cols.append(np.arange(3) + 3 * rk if rk >= 0 else np.full(3, -1))
            labels.append(("pose", int(key)))
        for key, i in zip(lk, li, strict=True):
            rk = rank_point[i]
            cols.append(np.arange(2) + k3 + 2 * rk if rk >= 0 else np.full(2, -1))
            labels.append(("point", int(key)))
        return (np.concatenate(cols).astype(np.int64) if cols else np.zeros(0, np.int64)), labels


def chi2(graph: FactorGraph, values: Values) -> float:
    """g2o chi2 = sum over factors of e^T Omega e (no 1/2, no robust kernel)."""
    return chi2_by_kind(graph, values)["total"]


def chi2_by_kind(graph: FactorGraph, values: Values, analysis: Analysis | None = None) -> dict[str, float]:
    """chi2 per factor type plus ``total``."""
    an = analysis if analysis is not None else Analysis(graph, values, gauge="none")
    out = {k: float(s.sum()) for k, s, _, _ in an.errors(values.poses, values.points)}
    out["total"] = float(sum(out.values()))
    return out


def factor_chi2(graph: FactorGraph, values: Values, kind: str) -> Array:
    """Per-factor e^T Omega e of one type, in the order the factors were added. Shapes: -> (N,)."""
    an = Analysis(graph, values, gauge="none")
    for k, s, _, _ in an.errors(values.poses, values.points):
        if k == kind:
            return s
    return np.zeros(0)


def chi2_per_dof(graph: FactorGraph, values: Values) -> dict[str, float]:
    """Mean whitened squared error per measurement dimension: odometry (between factors of consecutive keys), loop
    (other between factors) and each other factor type separately (about 1 each when the noise models are right; far
    above 1 flags the factors that are being violated)."""
    out: dict[str, float] = {}
    for b in graph.blocks():
        if not b.size:
            continue
        chi = factor_chi2(graph, values, b.kind)
        if b.kind == "between":
            odo = b.keys[1] == b.keys[0] + 1
            groups = {"odometry": odo, "loop": ~odo}
        else:
            groups = {b.kind: np.ones(b.size, dtype=bool)}
        for name, mask in groups.items():
            if np.any(mask):
                out[name] = float(chi[mask].sum()) / (int(mask.sum()) * b.z.shape[1])
    return out
