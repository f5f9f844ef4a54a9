"""Pluggable sparse symmetric positive-definite solvers for the normal equations ``H dx = b``.

Each solver receives the UPPER triangle of H in CSC form with a fixed pattern. The first ``factorize`` does the
symbolic work (fill-reducing ordering, elimination tree); later calls with the same pattern refill values only.

* ``qdldl`` (default; pip wheel): LDL^T with AMD ordering; ``Solver.update`` reuses the ordering and symbolic
  analysis. Measured fastest of the wheel-installable options here (see benchmarks/pose_graphs.py and the README).
* ``cholmod`` (optional extra, scikit-sparse, needs SuiteSparse): supernodal Cholesky; ``analyze`` once, then
  ``cholesky_inplace``.
* ``splu``: SciPy SuperLU with the MMD(A^T+A) ordering. Always available; SuperLU has no symbolic reuse, so every
  call refactors from scratch.
* ``dense``: numpy Cholesky of the dense matrix; for tests and tiny problems only.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

Array = NDArray[np.float64]


class SolverError(RuntimeError):
    """The factorisation failed (H singular or indefinite: unconstrained variables or a missing gauge)."""


class LinearSolver(Protocol):
    name: str

    def factorize(self, upper: sp.csc_matrix) -> None:
        """Factor H given its upper triangle (same pattern on every call)."""
        ...

    def solve(self, b: Array) -> Array:
        """Solve H x = b for b (n,) or (n, k)."""
        ...


def _full(upper: sp.csc_matrix) -> sp.csc_matrix:
    d = upper.diagonal()
    return (upper + upper.T - sp.diags(d)).tocsc()


class QdldlSolver:
    """QDLDL (AMD ordering inside); value updates reuse the symbolic factorisation."""

    name = "qdldl"

    def __init__(self) -> None:
        import qdldl

        self._mod = qdldl
        self._solver: Any = None
        self._nnz = -1

    def factorize(self, upper: sp.csc_matrix) -> None:
        try:
            if self._solver is None or upper.nnz != self._nnz:
                self._solver = self._mod.Solver(upper, upper=True)
                self._nnz = upper.nnz
            else:
                self._solver.update(upper, upper=True)
        except (ValueError, RuntimeError) as e:
            raise SolverError(f"qdldl factorisation failed: {e}") from e

    def solve(self, b: Array) -> Array:
        if b.ndim == 1:
            x = self._solver.solve(b)
        else:
            x = np.stack([self._solver.solve(np.ascontiguousarray(b[:, k])) for k in range(b.shape[1])], axis=1)
        return np.asarray(x)


class SpluSolver:
    """SciPy SuperLU on the full symmetric matrix (no symbolic reuse available)."""

    name = "splu"

    def __init__(self) -> None:
        self._lu: Any = None

    def factorize(self, upper: sp.csc_matrix) -> None:
        try:
            self._lu = spla.splu(_full(upper), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
        except RuntimeError as e:
            raise SolverError(f"splu factorisation failed: {e}") from e

    def solve(self, b: Array) -> Array:
        return np.asarray(self._lu.solve(b))


class CholmodSolver:
    """CHOLMOD through scikit-sparse (optional): symbolic analysis once, numeric refactorisation per call."""

    name = "cholmod"

    def __init__(self) -> None:
        from sksparse import cholmod  # type: ignore[import-not-found]

        self._mod = cholmod
        self._factor: Any = None
        self._nnz = -1

    def factorize(self, upper: sp.csc_matrix) -> None:
        full = _full(upper)
        try:
            if self._factor is None or upper.nnz != self._nnz:
                self._factor = self._mod.analyze(full)
                self._nnz = upper.nnz
            self._factor.cholesky_inplace(full)
        except Exception as e:  # CholmodNotPositiveDefiniteError and friends
            raise SolverError(f"cholmod factorisation failed: {e}") from e

    def solve(self, b: Array) -> Array:
        return np.asarray(self._factor(b))


class DenseSolver:
    """Dense Cholesky (tests and tiny graphs)."""

    name = "dense"

    def __init__(self) -> None:
        self._c: Any = None

    def factorize(self, upper: sp.csc_matrix) -> None:
        try:
            self._c = scipy.linalg.cho_factor(_full(upper).toarray())
        except np.linalg.LinAlgError as e:
            raise SolverError(f"dense Cholesky failed: {e}") from e

    def solve(self, b: Array) -> Array:
        return np.asarray(scipy.linalg.cho_solve(self._c, b))


SOLVERS: dict[str, type] = {"qdldl": QdldlSolver, "splu": SpluSolver, "cholmod": CholmodSolver, "dense": DenseSolver}


def available_solvers() -> list[str]:
    """Names of the solvers that can be constructed here."""
    out = []
    for name, cls in SOLVERS.items():
        try:
            cls()
        except ImportError:
            continue
        out.append(name)
    return out


def make_solver(name: str = "auto") -> LinearSolver:
    """A fresh solver; ``auto`` picks qdldl, else cholmod, else splu."""
    if name == "auto":
        for cand in ("qdldl", "cholmod", "splu"):
            try:
                s: LinearSolver = SOLVERS[cand]()
                return s
            except ImportError:
                continue
    if name not in SOLVERS:
        raise ValueError(f"unknown linear solver {name!r}; choose one of auto, {', '.join(SOLVERS)}")
    try:
        out: LinearSolver = SOLVERS[name]()
    except ImportError as e:
        raise ValueError(f"linear solver {name!r} is not installed ({e})") from e
    return out
