"""Joint Compatibility Branch and Bound (Neira & Tardós, IEEE T-RA 17(6), 2001), made exact.

What it returns (the definition the tests check against brute force): among all hypotheses H, i.e. sets of
(observation, candidate) pairs that are

1. individually compatible (each pair passes the 2-dof chi-square gate and the descriptor gate),
2. mutually exclusive (each observation and each candidate used at most once), and
3. jointly compatible: ``NIS_H = nu_H^T C_H^-1 nu_H <= chi2.ppf(gate_probability, 2|H|)`` with ``C_H`` taken from
   ``S_joint`` (the empty hypothesis has NIS 0 and is always compatible),

the one with the most pairs; ties broken by the lowest joint NIS; exact NIS ties broken by the lexicographically
smallest assignment vector (in observation order, candidate index, "unmatched" ranked after every candidate).

Unlike the textbook recursion this does not require every *prefix* of H (in observation order) to be jointly
compatible, so the answer does not depend on the order of the observations. The pruning is still strong because
the joint NIS never decreases when a pair is added (a Schur-complement identity). With NIS(H + P) >= NIS(H) +
NIS({p} | H) for any p in P, each node derives:

* feasibility: a pair p whose NIS(H) + NIS({p} | H) already exceeds the largest gate a completion could face (or the
  incumbent's NIS when the count can at best tie) is removed from the subtree; iterated to a fixed point, since
  fewer usable pairs lower the reachable count and hence the gate;
* count: the usual JCBB bound, tightened: per connected component of the compatibility graph at most
  min(open observations, open candidates) more pairs; a branch that cannot reach the incumbent's count is cut;
* NIS floor: with slack s = (reachable count - incumbent count), at most s "tight" rows may stay unmatched, so the
  (s+1)-th largest of their smallest single-pair increments is a floor on what the completion adds; the branch is
  cut when the floor exceeds the gate, or the incumbent's NIS when s = 0.

Search order (which never changes the answer): branch on the most constrained observation (fewest usable pairs);
try children that are jointly compatible at their own size first, lowest NIS first (the textbook dive, which finds
a strong incumbent early), then "unmatched", then the remaining children.

Each node keeps the predictions of every candidate conditioned on its hypothesis (see ``_Node``), so all children
of a node are scored in one vectorised step and a child costs one (2 x 2n)(2n x 2A) product. Only matrix products
are used in the search: LAPACK solves on tiny matrices are slow when OpenBLAS threads compete for the cores.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from slam2d.association.gating import Problem, check_joint_positive_definite, joint_thresholds, max_matching

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass
class _Search:
    """Mutable state of one branch-and-bound run (kept out of the recursion's arguments).

    Candidates are renumbered to the A "active" ones (individually compatible with some observation); rows are
    the observations with at least one compatible candidate, in search order.
    """

    ic: BoolArray  # (K', A)
    nu: Array  # (K', A, 2) innovations
    cov: Array  # (2A, 2A) joint innovation covariance of the active candidates
    thr: Array  # (K'+1,) joint gates
    row_comp: IntArray  # (K',) connected component (of the compatibility graph) of each row
    col_comp: IntArray  # (A,) ... of each candidate
    num_comp: int
    max_nodes: int
    deadline: float | None = None  # time.monotonic() after which the search stops with its best so far
    nodes: int = 0
    truncated: bool = False
    best_n: int = 0
    best_nis: float = 0.0
    best_key: tuple[int, ...] = ()
    best_pairs: list[tuple[int, int]] = field(default_factory=list)
    key_of: Callable[[list[tuple[int, int]]], tuple[int, ...]] | None = None

    def potential(self, open_pairs: BoolArray, rows: IntArray) -> tuple[int, BoolArray]:
        """Upper bound on how many more pairs can be made from ``open_pairs`` (rows ``rows`` x all candidates): per
        connected component of the compatibility graph, the smaller of its open rows and open candidates. Also
        returns which rows are "tight" (in a component with no more open rows than open candidates, so leaving one
        of them unmatched lowers the bound by one). Shapes: open_pairs (R, A), rows (R,) -> int, (R,) bool."""
        rows_ok = open_pairs.any(axis=1)
        if not rows_ok.any():
            return 0, np.asarray(rows_ok, dtype=bool)
        cols_ok = open_pairs.any(axis=0)
        comp = self.row_comp[rows]
        r = np.bincount(comp[rows_ok], minlength=self.num_comp)
        c = np.bincount(self.col_comp[cols_ok], minlength=self.num_comp)
        return int(np.minimum(r, c).sum()), rows_ok & (r[comp] <= c[comp])


@dataclass
class _Node:
    """A hypothesis H and everything needed to extend it cheaply.

    With ``Lc`` the Cholesky factor of C_H: ``w = Lc^-1 C_H,all`` (2n, 2A) and ``y = Lc^-1 nu_H`` (2n,), so
    NIS_H = |y|^2; for every active candidate j the prediction conditioned on H has ``shift[j] = w_j^T y`` and
    covariance ``schur[j] = S_j - w_j^T w_j``. Adding a pair appends one 2-row block to w and y and applies a
    rank-2 update to shift and schur; no matrix is ever factorised again.
    """

    pairs: list[tuple[int, int]]
    w: Array
    y: Array
    schur: Array  # (A, 2, 2)
    shift: Array  # (A, 2)
    nis: float


def _chol2(s: Array) -> tuple[Array, Array, Array, BoolArray]:
    """Inverse Cholesky factors of 2x2 SPD matrices: (i11, i21, i22) with L^-1 = [[i11, 0], [i21, i22]], and ok.

    Shapes: (m,2,2) -> four (m,) arrays; ``ok`` is False where round-off broke positive definiteness."""
    a, b, d = s[:, 0, 0], s[:, 1, 0], s[:, 1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        l11 = np.sqrt(a)
        l21 = b / l11
        l22 = np.sqrt(d - l21 * l21)
        i11, i22 = 1.0 / l11, 1.0 / l22
        i21 = -l21 * i11 * i22
    ok = (a > 0) & np.isfinite(i11) & np.isfinite(i21) & np.isfinite(i22)
    return i11, i21, i22, ok


def _extend(st: _Search, node: _Node, row: int, j: int, linv22: Array, z: Array, nis: float) -> _Node:
    """The child hypothesis H + (row, j), given the 2x2 inverse factor of its Schur block and whitened innovation."""
    n2 = node.w.shape[0]
    block = st.cov[2 * j:2 * j + 2]  # (2, 2A): C_j,all
    if n2:
        block = block - node.w[:, 2 * j:2 * j + 2].T @ node.w
    w_new = linv22 @ block  # (2, 2A)
    wn = w_new.reshape(2, -1, 2)
    schur = node.schur - np.einsum("ajb,ajc->jbc", wn, wn)
    shift = node.shift + np.einsum("ajb,a->jb", wn, z)
    return _Node([*node.pairs, (row, j)], np.vstack([node.w, w_new]), np.concatenate([node.y, z]), schur, shift,
                 nis)


def _visit(st: _Search, node: _Node, used: BoolArray, decided: BoolArray) -> None:
    """Search every completion of ``node``'s hypothesis: rows not ``decided`` may still be paired with candidates
    not ``used``."""
    st.nodes += 1
    if st.nodes > st.max_nodes or (st.deadline is not None and time.monotonic() > st.deadline):
        st.truncated = True
        return
    n = len(node.pairs)
    rows = np.flatnonzero(~decided)
    open_pairs = st.ic[rows] & ~used
    # NIS increment of every open pair, conditioned on H (vectorised over rows x candidates)
    i11, i21, i22, ok = _chol2(node.schur)
    res = st.nu[rows] - node.shift[None]  # (R, A, 2)
    with np.errstate(invalid="ignore"):  # used candidates have a zero Schur block: their values are masked below
        z1 = i11 * res[..., 0]
        z2 = i21 * res[..., 0] + i22 * res[..., 1]
    open_pairs &= ok
    inc = np.where(open_pairs, z1 * z1 + z2 * z2, np.inf)
    # a pair can only join a completion if H plus that pair alone stays under the largest gate the completion could
    # face (the NIS of a superset is never smaller), and under the incumbent's NIS when the count can only tie;
    # removing pairs lowers the bound on the count, which lowers the gate: iterate to a fixed point
    pot, tight = st.potential(open_pairs, rows)
    while pot:
        limit = st.thr[n + pot] - node.nis
        if n + pot == st.best_n:
            limit = min(limit, st.best_nis - node.nis)
        feasible = open_pairs & (inc <= limit)
        new_pot, new_tight = st.potential(feasible, rows)
        open_pairs = feasible
        if new_pot == pot:
            tight = new_tight
            break
        pot, tight = new_pot, new_tight
    if pot == 0:
        _leaf(st, node)
        return
    slack = n + pot - st.best_n
    if slack < 0:
        return
    # lower bound on the final NIS: at most `slack` tight rows may stay unmatched, and each matched row adds at
    # least its smallest single-pair increment given H, so the (slack+1)-th largest of the tight rows' minima is a
    # floor on the increment
    inc = np.where(open_pairs, inc, np.inf)
    tight_min = np.sort(inc.min(axis=1)[tight])[::-1]
    floor = node.nis + (float(tight_min[slack]) if slack < len(tight_min) else 0.0)
    if floor > st.thr[n + pot] or (slack == 0 and floor > st.best_nis):
        return
    # branch on the most constrained row (fewest usable pairs; ties: search order)
    counts = open_pairs.sum(axis=1)
    k = int(np.argmin(np.where(counts > 0, counts, np.iinfo(np.int64).max)))
    row = int(rows[k])
    rest = np.arange(len(rows)) != k
    after, _ = st.potential(open_pairs[rest], rows[rest])
    js = np.flatnonzero(open_pairs[k])
    child_nis = node.nis + inc[k, js]
    srt = np.argsort(child_nis, kind="stable")
    # branch order (it never changes the answer, only how soon a strong incumbent prunes the rest): children that
    # are jointly compatible at their own size first (the textbook JCBB dive), then "unmatched", then the others
    n_jc = int(np.count_nonzero(child_nis[srt] <= st.thr[n + 1]))
    decided[row] = True
    for pos, t in enumerate(srt):
        if pos == n_jc:
            _star(st, node, used, decided, n + after)
        if st.truncated:
            break
        bound = n + 1 + after
        cn = float(child_nis[t])
        # re-test: the incumbent may have improved while an earlier branch was searched
        if cn > st.thr[bound] or bound < st.best_n or (bound == st.best_n and cn > st.best_nis):
            continue
        j = int(js[t])
        linv22 = np.array([[i11[j], 0.0], [i21[j], i22[j]]])
        child = _extend(st, node, row, j, linv22, np.array([z1[k, j], z2[k, j]]), cn)
        used[j] = True
        _visit(st, child, used, decided)
        used[j] = False
    if n_jc == len(srt) and not st.truncated:
        _star(st, node, used, decided, n + after)
    decided[row] = False


def _star(st: _Search, node: _Node, used: BoolArray, decided: BoolArray, bound: int) -> None:
    """The branch where the row just marked decided stays unmatched."""
    if (bound > st.best_n or (bound == st.best_n and node.nis <= st.best_nis)) and node.nis <= st.thr[bound]:
        _visit(st, node, used, decided)


def _leaf(st: _Search, node: _Node) -> None:
    n, nis = len(node.pairs), node.nis
    if nis > st.thr[n] or n < st.best_n or (n == st.best_n and nis > st.best_nis):
        return
    assert st.key_of is not None
    key = st.key_of(node.pairs)
    if n == st.best_n and nis == st.best_nis and key >= st.best_key:
        return
    st.best_n, st.best_nis, st.best_key, st.best_pairs = n, nis, key, list(node.pairs)


def _seed_incumbent(st: _Search, d2: Array) -> None:
    """Start from a good feasible hypothesis so the bounds bite from the first node: the individually compatible
    assignment with the most pairs and least total d2, thinned until jointly compatible (drop the pair with the
    largest leave-one-out conditional d2). Any feasible start is fine: the search still proves optimality."""
    rows, cols = max_matching(d2, st.ic)
    while len(rows):
        idx = (2 * cols[:, None] + np.arange(2)).ravel()
        ci = np.linalg.inv(st.cov[np.ix_(idx, idx)])
        nu = st.nu[rows, cols].ravel()
        v = ci @ nu
        nis = float(nu @ v)
        if nis <= st.thr[len(rows)]:
            break
        n = len(rows)
        blocks = ci.reshape(n, 2, n, 2)[np.arange(n), :, np.arange(n), :]
        vb = v.reshape(n, 2)
        loo = np.einsum("ni,nij,nj->n", vb, np.linalg.inv(blocks), vb)
        keep = np.arange(n) != int(np.argmax(loo))
        rows, cols = rows[keep], cols[keep]
    if len(rows):
        pairs = [(int(r), int(c)) for r, c in zip(rows, cols, strict=True)]
        assert st.key_of is not None
        st.best_n, st.best_nis, st.best_key, st.best_pairs = len(pairs), nis, st.key_of(pairs), pairs


def jcbb(problem: Problem, probability: float, max_nodes: int, deadline: float | None = None
         ) -> tuple[IntArray, IntArray, float, int, bool]:
    """Run the exact branch and bound on ``problem``.

    The search stops after ``max_nodes`` nodes or once ``time.monotonic()`` passes ``deadline`` (None: no time
    limit), and then returns the best jointly compatible hypothesis found so far with ``truncated`` True; the
    starting incumbent is feasible, so a truncated answer is always a valid (if possibly smaller) hypothesis.

    Returns (obs (n,), cand (n,), joint NIS, nodes visited, truncated). Shapes: pairs sorted by observation.
    """
    k, n_cand = problem.num_obs, problem.num_candidates
    counts = problem.ic.sum(axis=1)
    # most constrained observations first (fewest compatible candidates): deep branches close early
    order = np.array(sorted(np.flatnonzero(counts > 0), key=lambda i: (counts[i], i)), dtype=np.int64)
    empty = np.zeros(0, dtype=np.int64)
    if len(order) == 0:
        return empty, empty, 0.0, 1, False
    act = np.flatnonzero(problem.ic.any(axis=0))
    cov = check_joint_positive_definite(problem, act)  # the search relies on it where it is used
    ic = problem.ic[np.ix_(order, act)]
    # connected components of the bipartite compatibility graph (rows first, then candidates)
    kk, a = ic.shape
    graph = csr_matrix((np.ones(int(ic.sum())), np.nonzero(ic)), shape=(kk, a))
    full = csr_matrix(np.block([[np.zeros((kk, kk)), graph.toarray()], [graph.toarray().T, np.zeros((a, a))]]))
    num_comp, labels = connected_components(full, directed=False)

    def key_of(pairs: list[tuple[int, int]]) -> tuple[int, ...]:
        out = [n_cand] * k
        for r, j in pairs:
            out[int(order[r])] = int(act[j])
        return tuple(out)

    st = _Search(ic=ic, nu=problem.nu[np.ix_(order, act)], cov=cov, thr=joint_thresholds(probability, kk),
                 row_comp=labels[:kk].astype(np.int64), col_comp=labels[kk:].astype(np.int64), num_comp=num_comp,
                 max_nodes=max_nodes, deadline=deadline, best_key=tuple([n_cand] * k), key_of=key_of)
    _seed_incumbent(st, problem.d2[np.ix_(order, act)])
    s_act = cov.reshape(a, 2, a, 2)[np.arange(a), :, np.arange(a), :]
    root = _Node([], np.zeros((0, 2 * a)), np.zeros(0), s_act.copy(), np.zeros((a, 2)), 0.0)
    _visit(st, root, np.zeros(a, dtype=bool), np.zeros(kk, dtype=bool))
    obs = np.array([order[r] for r, _ in st.best_pairs], dtype=np.int64)
    cand = np.array([act[j] for _, j in st.best_pairs], dtype=np.int64)
    srt = np.argsort(obs)
    return obs[srt], cand[srt], st.best_nis, st.nodes, st.truncated
