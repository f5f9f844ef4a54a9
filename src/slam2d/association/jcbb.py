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
the joint NIS never decreases when a pair is added (a Schur-complement identity), which gives three bounds:

* count: a branch whose pairs plus the remaining observations that still have an unused compatible candidate cannot
  reach the best pair count so far is cut (the usual JCBB bound);
* NIS: a branch that can at most tie the best count is cut once its NIS exceeds the best NIS;
* joint gate: a branch is cut once its NIS exceeds the chi-square threshold of the largest hypothesis it can grow to.

Each node keeps the inverse Cholesky factor of ``C_H`` so a child costs O(n^2) matrix products; all children of a
node are evaluated together in one batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.association.gating import Problem, joint_thresholds

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass
class _Search:
    """Mutable state of one branch-and-bound run (kept out of the recursion's arguments)."""

    ic: BoolArray  # (K', L) rows in search order
    nu: Array  # (K', L, 2)
    cb: Array  # (L, 2, L, 2) joint covariance blocks
    S: Array  # (L, 2, 2)
    thr: Array  # (K'+1,) joint gates
    order: IntArray  # (K',) original observation index of each search row
    num_candidates: int
    max_nodes: int
    nodes: int = 0
    truncated: bool = False
    best_n: int = 0
    best_nis: float = 0.0
    best_key: tuple[int, ...] = ()
    best_pairs: list[tuple[int, int]] = field(default_factory=list)

    def key(self, pairs: list[tuple[int, int]], num_obs: int) -> tuple[int, ...]:
        a = [self.num_candidates] * num_obs
        for row, j in pairs:
            a[int(self.order[row])] = j
        return tuple(a)

    def potential(self, row: int, used: BoolArray) -> int:
        """Upper bound on how many more pairs rows ``row..`` can add: rows with an unused compatible candidate."""
        if row >= self.ic.shape[0]:
            return 0
        return int(np.count_nonzero((self.ic[row:] & ~used).any(axis=1)))


def _children(st: _Search, row: int, js: IntArray, cols: IntArray, linv: Array, y: Array) -> tuple[Array, Array]:
    """Evaluate adding pair (row, j) for every j in ``js`` to the hypothesis whose candidates are ``cols``.

    ``linv`` is the inverse Cholesky factor of C_H and ``y = linv nu_H`` (so NIS_H = |y|^2). For each child the
    joint factor grows by one 2x2 block row: with W = linv C_Hj, the Schur complement is S_j - W^T W and the
    whitened new innovation is its Cholesky factor applied to nu_j - W^T y. Only matrix products are used: LAPACK
    triangular solves on tiny matrices are slow when OpenBLAS threads compete for the cores.
    Returns (inc (m,) NIS increments, +inf where round-off broke definiteness; packed (m,2,2n+3): the child's new
    block row of ``linv`` (columns :-1) and its two new entries of ``y`` (last column)).
    Shapes: js (m,), cols (n,), linv (2n,2n), y (2n,).
    """
    m, n = len(js), len(cols)
    nu = st.nu[row, js]  # (m, 2)
    schur = st.S[js].copy()
    if n:
        blk = st.cb[js[:, None], :, cols[None, :], :]  # (m, n, 2, 2): C[(j,a),(k,b)]
        rhs = blk.transpose(1, 3, 0, 2).reshape(2 * n, 2 * m)
        w = (linv @ rhs).reshape(2 * n, m, 2).transpose(1, 0, 2)  # (m, 2n, 2)
        schur -= np.einsum("mpa,mpb->mab", w, w)
        nu = nu - np.einsum("mpa,p->ma", w, y)
    else:
        w = np.zeros((m, 0, 2))
    a, b, d = schur[:, 0, 0], schur[:, 1, 0], schur[:, 1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        l11 = np.sqrt(a)
        l21 = b / l11
        l22 = np.sqrt(d - l21 * l21)
        # inverse of [[l11, 0], [l21, l22]]
        i11, i22 = 1.0 / l11, 1.0 / l22
        i21 = -l21 * i11 * i22
    z1 = i11 * nu[:, 0]
    z2 = i21 * nu[:, 0] + i22 * nu[:, 1]
    inc = z1 * z1 + z2 * z2
    # round-off can make a Schur complement of a (checked) positive definite matrix lose definiteness: cut it
    inc = np.where(np.isfinite(inc) & (a > 0), inc, np.inf)
    linv22 = np.zeros((m, 2, 2))
    linv22[:, 0, 0], linv22[:, 1, 0], linv22[:, 1, 1] = i11, i21, i22
    # new block row of the inverse factor: [-L22^-1 W^T linv, L22^-1]
    left = -np.einsum("mab,mpb,pq->maq", linv22, w, linv) if n else np.zeros((m, 2, 0))
    new_rows = np.concatenate([left, linv22], axis=2)  # (m, 2, 2n+2)
    return inc, np.concatenate([new_rows, np.stack([z1, z2], axis=-1)[:, :, None]], axis=2)


def _visit(st: _Search, row: int, pairs: list[tuple[int, int]], used: BoolArray, linv: Array, y: Array,
           nis: float) -> None:
    st.nodes += 1
    if st.nodes > st.max_nodes:
        st.truncated = True
        return
    n = len(pairs)
    here = st.potential(row, used)
    if here == 0:
        _leaf(st, pairs, nis)
        return
    # skip rows with nothing left to choose: they can only be "unmatched"
    while not (st.ic[row] & ~used).any():
        row += 1
    after = st.potential(row + 1, used)
    js = np.flatnonzero(st.ic[row] & ~used)
    bound = n + 1 + after
    if bound >= st.best_n:
        cols = np.array([j for _, j in pairs], dtype=np.int64)
        inc, packed = _children(st, row, js, cols, linv, y)
        child_nis = nis + inc
        for t in np.argsort(child_nis, kind="stable"):
            cn = float(child_nis[t])
            if st.truncated:
                return
            # re-test: the best may have improved while an earlier sibling was searched
            if cn > st.thr[bound] or bound < st.best_n or (bound == st.best_n and cn > st.best_nis):
                continue
            j = int(js[t])
            k2 = 2 * n
            child = np.zeros((k2 + 2, k2 + 2))
            child[:k2, :k2] = linv
            child[k2:, :] = packed[t, :, :-1]
            used[j] = True
            _visit(st, row + 1, [*pairs, (row, j)], used, child, np.concatenate([y, packed[t, :, -1]]), cn)
            used[j] = False
    if st.truncated:
        return
    # star branch: this observation stays unmatched
    bound = n + after
    if bound > st.best_n or (bound == st.best_n and nis <= st.best_nis):
        if nis <= st.thr[bound]:
            _visit(st, row + 1, pairs, used, linv, y, nis)


def _leaf(st: _Search, pairs: list[tuple[int, int]], nis: float) -> None:
    n = len(pairs)
    if nis > st.thr[n]:
        return
    if n < st.best_n or (n == st.best_n and nis > st.best_nis):
        return
    key = st.key(pairs, len(st.best_key))
    if n == st.best_n and nis == st.best_nis and key >= st.best_key:
        return
    st.best_n, st.best_nis, st.best_key, st.best_pairs = n, nis, key, list(pairs)


def jcbb(problem: Problem, probability: float, max_nodes: int) -> tuple[IntArray, IntArray, float, int, bool]:
    """Run the exact branch and bound on ``problem``.

    Returns (obs (n,), cand (n,), joint NIS, nodes visited, truncated). Shapes: pairs sorted by observation.
    """
    k, n_cand = problem.num_obs, problem.num_candidates
    counts = problem.ic.sum(axis=1)
    # most constrained observations first (fewest compatible candidates): deep branches close early
    order = np.array(sorted(np.flatnonzero(counts > 0), key=lambda i: (counts[i], i)), dtype=np.int64)
    empty = np.zeros(0, dtype=np.int64)
    if len(order) == 0:
        return empty, empty, 0.0, 1, False
    if problem.S_joint is not None:
        cb = problem.S_joint.reshape(n_cand, 2, n_cand, 2)
        active = np.flatnonzero(problem.ic.any(axis=0))
        try:  # the branch and bound assumes S_joint is positive definite where it is used
            np.linalg.cholesky(problem.joint_block(active, active))
        except np.linalg.LinAlgError:
            raise ValueError("Candidates.S_joint is not positive definite on the individually compatible "
                             f"candidates {problem.ids[active].tolist()}") from None
    else:
        cb = np.zeros((n_cand, 2, n_cand, 2))
        cb[np.arange(n_cand), :, np.arange(n_cand), :] = problem.S
    st = _Search(ic=problem.ic[order], nu=problem.nu[order], cb=cb, S=problem.S,
                 thr=joint_thresholds(probability, len(order)), order=order, num_candidates=n_cand,
                 max_nodes=max_nodes)
    st.best_key = tuple([n_cand] * k)
    _visit(st, 0, [], np.zeros(n_cand, dtype=bool), np.zeros((0, 0)), np.zeros(0), 0.0)
    obs = np.array([order[r] for r, _ in st.best_pairs], dtype=np.int64)
    cand = np.array([j for _, j in st.best_pairs], dtype=np.int64)
    srt = np.argsort(obs)
    return obs[srt], cand[srt], st.best_nis, st.nodes, st.truncated
