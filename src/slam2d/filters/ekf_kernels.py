"""EKF-SLAM kernels: pure functions over ``mu = [x, y, theta, l0x, l0y, ...]`` (3 + 2N,) and ``P`` (3+2N, 3+2N).

Landmark ``j`` lives at rows ``3+2j, 4+2j``. The heading ``mu[2]`` is kept wrapped to [-pi, pi). The estimator shell
(:class:`slam2d.filters.ekf_slam.EKFSLAM`) calls these; they are re-exported from ``slam2d.filters.ekf_slam``.

Costs (n = 3 + 2N):

* predict touches only the three robot rows/columns: O(N) (Probabilistic Robotics, table 10.1, lines 3-5);
* one observation update reads the 5 rows of P its sparse 2x5 Jacobian touches (P is symmetric, so rows are the
  columns ``P H^T`` needs), builds ``B = H P[idx, :]`` (m, n), ``S = B[:, idx] H^T + R`` and applies the rank-m
  symmetric update ``P <- P - A A^T`` with ``A = B^T L^-T`` (``S = L L^T``). With the optimal gain this equals the
  Joseph form ``(I-KH) P (I-KH)^T + K R K^T`` exactly (a test checks it against the dense Joseph form) and keeps
  P symmetric (bit-for-bit in the tests: entry (i,j) and (j,i) are the same products). It is O(n^2): one BLAS
  ``dgemm`` pass over P in place; never a dense n x n product;
* a step with many observations (:func:`ekf_update_range_bearing_batches`) applies joint updates of a few dozen
  in turn, keeping only P's upper triangle current in between: each downdate is one ``dsyrk`` (half the flops of
  the ``dgemm``), the triangle is mirrored once at the end; the same maths as chaining the single joint update;
* augmentation (:func:`augment_state`) and removal copy P once: O(n^2).

Numerical guard (documented rule, see :class:`CovarianceError`): before an update the rows that the update reads
are compared with the matching columns (symmetry, O(n)) and the touched block must be positive semi-definite (an
eigenvalue check of at most 5 x 5); after it, every diagonal entry must be finite and >= 0 (O(n)). A violation
raises :class:`CovarianceError`; :func:`repair_covariance` is the documented repair (symmetrise, clip eigenvalues
to a floor; O(n^3)).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import blas, lapack, solve_triangular

from slam2d.association import AssociationConfig, AssociationResult, Candidates, associate
from slam2d.association.predict import innovation_covariance, joint_innovation_covariance
from slam2d.geometry.angles import wrap_angle, wrap_angle_scalar
from slam2d.log import Observations
from slam2d.models.motion import MotionNoise, odometry_covariance_scalar, odometry_scalar
from slam2d.models.sensors import (
    absolute_position,
    absolute_position_jacobians,
    range_bearing,
    range_bearing_inverse,
    range_bearing_inverse_jacobians,
    range_bearing_jacobians,
    range_bearing_scalar,
)

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

POSE_DIM = 3


class CovarianceError(ValueError):
    """The covariance lost symmetry or positive semi-definiteness (or became non-finite).

    ``applied`` tells whether the failing operation had already modified the state (post-update check) or not
    (pre-update check), so a caller that repairs P knows whether to retry.
    """

    def __init__(self, message: str, *, applied: bool = False, done: int = 0) -> None:
        super().__init__(message)
        self.applied = applied
        self.done = done
        """observations applied before the failing update (set by :func:`ekf_update_range_bearing_batches`)."""


# ---------------------------------------------------------------------------------------------------- validation
def _check_state(mu: Array, P: Array) -> int:
    n = mu.shape[0]
    if mu.ndim != 1 or n < POSE_DIM or (n - POSE_DIM) % 2:
        raise ValueError(f"mu must have shape (3+2N,), got {mu.shape}")
    if P.shape != (n, n):
        raise ValueError(f"P must have shape ({n}, {n}) to match mu, got {P.shape}")
    return n


def check_observations(z_range: ArrayLike, z_bearing: ArrayLike, *, where: str = "observation") -> None:
    """Raise ``ValueError`` naming the first bad entry: non-finite range/bearing or a negative range."""
    r = np.atleast_1d(np.asarray(z_range, dtype=np.float64))
    b = np.atleast_1d(np.asarray(z_bearing, dtype=np.float64))
    bad = ~np.isfinite(r) | ~np.isfinite(b) | (r < 0)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{where} {k}: range_m={r[k]!r}, bearing_rad={b[k]!r} (must be finite, range >= 0)")


def _check_noise(R: Array, name: str, m: int) -> Array:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (m, m) or not np.all(np.isfinite(R)):
        raise ValueError(f"{name} must be a finite ({m}, {m}) matrix, got shape {R.shape}")
    if not np.allclose(R, R.T, rtol=1e-12, atol=1e-15) or np.any(np.linalg.eigvalsh(R) <= 0):
        raise ValueError(f"{name} must be symmetric positive definite")
    return R


def repair_covariance(P: Array, *, min_eig: float | None = None) -> Array:
    """The documented repair rule: symmetrise, then clip eigenvalues to ``min_eig``. O(n^3); returns a new array.

    ``min_eig`` defaults to ``1e-12 * max(1, max |diag|)``. Shapes: (n,n) -> (n,n).
    """
    P = np.asarray(P, dtype=np.float64)
    if not np.all(np.isfinite(P)):
        raise CovarianceError("covariance has non-finite entries; it cannot be repaired")
    sym = 0.5 * (P + P.T)
    floor = 1e-12 * max(1.0, float(np.max(np.abs(np.diag(sym))))) if min_eig is None else float(min_eig)
    w, v = np.linalg.eigh(sym)
    out = (v * np.maximum(w, floor)) @ v.T
    return np.ascontiguousarray(0.5 * (out + out.T))


# ---------------------------------------------------------------------------------------------------- predict
def ekf_predict_linearized(mu: Array, P: Array, pose_new: Array, G: Array, Q_pose: Array, *,
                           inplace: bool = False) -> tuple[Array, Array]:
    """Prediction with a given robot Jacobian ``G`` (3,3) and pose-space noise ``Q_pose`` (3,3).

    Only the robot rows/columns change: ``P_rr <- G P_rr G^T + Q``, ``P_rm <- G P_rm``; O(N) with ``inplace``
    (without it the copy of P costs O(N^2)). Shapes: (n,),(n,n),(3,),(3,3),(3,3) -> (n,),(n,n).
    """
    mu, P = np.asarray(mu, dtype=np.float64), np.asarray(P, dtype=np.float64)
    _check_state(mu, P)
    if not inplace:
        mu, P = mu.copy(), P.copy()
    cross = G @ P[:POSE_DIM, POSE_DIM:]
    P[:POSE_DIM, POSE_DIM:] = cross
    P[POSE_DIM:, :POSE_DIM] = cross.T
    prr = G @ P[:POSE_DIM, :POSE_DIM] @ G.T + Q_pose
    P[:POSE_DIM, :POSE_DIM] = 0.5 * (prr + prr.T)
    mu[:POSE_DIM] = pose_new
    mu[2] = wrap_angle(mu[2])
    return mu, P


def ekf_predict(mu: Array, P: Array, u: Array, noise: MotionNoise, *, inplace: bool = False) -> tuple[Array, Array]:
    """Odometry prediction ``x <- x (+) u`` with ``Q = V Q_u V^T`` (Probabilistic Robotics sec. 10.2).

    Shapes: (n,),(n,n),(3,) -> (n,),(n,n).
    """
    mu = np.asarray(mu, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if u.shape != (3,) or not np.all(np.isfinite(u)):
        raise ValueError(f"odometry must be 3 finite numbers [dx, dy, dtheta], got {u!r}")
    new, g, v = odometry_scalar(mu[:POSE_DIM], u)
    q = v @ odometry_covariance_scalar(u, noise) @ v.T
    return ekf_predict_linearized(mu, P, new, g, q, inplace=inplace)


# ---------------------------------------------------------------------------------------------------- update
def _low_rank_downdate(P: Array, At: Array) -> None:
    """``P -= At^T At`` in place (At is (m, n)) for a symmetric P: one ``dsyrk`` on the upper triangle (half the
    flops of a ``dgemm``), then the upper triangle copied onto the lower one. Exactly symmetric on every CPU: a
    ``dgemm`` product ``At^T At`` is not (OpenBLAS's AMD Zen kernels round entry (i, j) and (j, i) differently)."""
    if not P.flags.c_contiguous:
        tmp = np.ascontiguousarray(P)
        _low_rank_downdate(tmp, At)
        P[...] = tmp
        return
    # P.T is P's memory in Fortran order (no copy); its lower triangle is P's upper one
    out = blas.dsyrk(-1.0, At, 1.0, P.T, trans=1, lower=1, overwrite_c=1)
    if not np.shares_memory(out, P):  # pragma: no cover - BLAS wrapper declined to work in place
        P[...] = out.T
    _mirror_upper(P)


def _inverse_cholesky(S: Array) -> Array:
    """``L^-1`` for ``S = L L^T`` (m x m); closed form for m = 2 (the per-observation case). Raises CovarianceError."""
    if S.shape == (2, 2):
        a, b, d = float(S[0, 0]), float(S[1, 0]), float(S[1, 1])
        if a > 0.0:
            l11 = math.sqrt(a)
            l21 = b / l11
            rest = d - l21 * l21
            if rest > 0.0:
                l22 = math.sqrt(rest)
                return np.array([[1.0 / l11, 0.0], [-l21 / (l11 * l22), 1.0 / l22]])
    else:
        try:
            return np.asarray(np.linalg.inv(np.linalg.cholesky(S)))
        except np.linalg.LinAlgError:
            pass
    raise CovarianceError(f"innovation covariance S is not positive definite: {S.tolist()}")


def ekf_update(mu: Array, P: Array, idx: ArrayLike, H: Array, nu: Array, R: Array, *,
               inplace: bool = False, check: bool = True) -> tuple[Array, Array]:
    """Kalman update with a Jacobian that is nonzero only on the state entries ``idx`` (k,).

    ``H`` (m,k) is the nonzero block, ``nu`` (m,) the innovation (angles already wrapped), ``R`` (m,m). Cost
    O(m n + m^2 n): rows ``P[idx, :]`` give ``B = H P[idx,:] = (P H^T)^T``; ``S = B[:, idx] H^T + R``;
    ``mu += B^T S^-1 nu``; ``P -= A A^T`` with ``A = B^T L^-T`` (``S = L L^T``) which is the Joseph form with the
    optimal gain. ``check`` runs the guard described in the module docstring (raises :class:`CovarianceError`).
    Shapes: (n,),(n,n),(k,),(m,k),(m,),(m,m) -> (n,),(n,n).
    """
    mu, P = np.asarray(mu, dtype=np.float64), np.asarray(P, dtype=np.float64)
    idx = np.asarray(idx, dtype=np.intp)
    rows = P[idx, :]
    if check:
        if not math.isfinite(float(np.sum(rows))):
            raise CovarianceError(f"covariance rows {idx.tolist()} are not finite")
        scale = max(1.0, float(np.max(np.abs(rows))))
        asym = float(np.max(np.abs(rows - P[:, idx].T)))
        if asym > 1e-9 * scale:
            raise CovarianceError(f"covariance is not symmetric in rows {idx.tolist()} (max |P - P^T| = {asym:.3g})")
        block = rows[:, idx]
        eig_min = float(np.linalg.eigvalsh(0.5 * (block + block.T))[0])
        if eig_min < -1e-9 * scale:
            raise CovarianceError(f"covariance block {idx.tolist()} is not positive semi-definite "
                                  f"(smallest eigenvalue {eig_min:.3g})")
    B = H @ rows
    S = B[:, idx] @ H.T + R
    l_inv = _inverse_cholesky(0.5 * (S + S.T))
    At = l_inv @ B
    w = l_inv @ np.asarray(nu, dtype=np.float64)
    if not inplace:
        mu, P = mu.copy(), P.copy()
    mu += At.T @ w
    mu[2] = wrap_angle_scalar(mu[2])
    _low_rank_downdate(P, At)
    if check:
        d = np.diagonal(P)
        if not (np.all(np.isfinite(d)) and float(np.min(d)) >= 0.0):
            k = int(np.argmin(np.where(np.isfinite(d), d, -np.inf)))
            raise CovarianceError(f"update left P[{k},{k}] = {d[k]!r} (must be finite and >= 0)", applied=True)
    return mu, P


def range_bearing_block(mu: Array, j: int) -> tuple[Array, Array, IntArray]:
    """Predicted measurement of landmark ``j``, its nonzero Jacobian block (2,5) and the state indices it touches."""
    a = POSE_DIM + 2 * int(j)
    z_pred, H = range_bearing_scalar(mu[:POSE_DIM], mu[a:a + 2])
    return z_pred, H, np.array([0, 1, 2, a, a + 1], dtype=np.int64)


def ekf_update_range_bearing(mu: Array, P: Array, j: int, z: ArrayLike, R: Array, *,
                             inplace: bool = False, check: bool = True) -> tuple[Array, Array]:
    """Update with one [range, bearing] observation ``z`` of landmark ``j`` (noise ``R`` (2,2)). O(N^2)."""
    mu = np.asarray(mu, dtype=np.float64)
    n = mu.shape[0]
    if P.shape != (n, n) or n < POSE_DIM or (n - POSE_DIM) % 2:
        _check_state(mu, np.asarray(P))
    if not 0 <= j < (n - POSE_DIM) // 2:
        raise IndexError(f"landmark index {j} out of range 0..{(n - POSE_DIM) // 2 - 1}")
    zz = np.asarray(z, dtype=np.float64)
    zr, zb = float(zz[0]), float(zz[1])
    if not (math.isfinite(zr) and math.isfinite(zb) and zr >= 0):
        check_observations(zr, zb)
    z_pred, H, idx = range_bearing_block(mu, j)
    nu = np.array([zr - z_pred[0], wrap_angle_scalar(zb - z_pred[1])])
    return ekf_update(mu, P, idx, H, nu, R, inplace=inplace, check=check)


def ekf_update_range_bearing_batch(mu: Array, P: Array, js: ArrayLike, z: ArrayLike, R: Array, *,
                                   inplace: bool = False, check: bool = True) -> tuple[Array, Array]:
    """One joint Kalman update with K [range, bearing] observations ``z`` (K,2) of landmarks ``js`` (K,), all
    linearised at the current mean (the stacked observation model; a landmark may appear more than once).

    With m = 2K: ``B = H P`` (m,n) from the 5 touched rows per observation, ``S = B H^T + R`` (m,m), ``S = L L^T``,
    ``C = L^-1 B``; ``mu += C^T L^-1 nu``, ``P -= C^T C`` (one dgemm pass, as in :func:`ekf_update`). Cost
    O(m n^2 + m^2 n) in a few BLAS calls, against K separate passes over P for sequential updates; batches of a few
    dozen observations are fastest (the m^2 n term grows with the batch). Sequential updates re-linearise after each
    observation, so the two agree only to first order; a test checks this one against the dense Joseph form.
    Shapes: (n,),(n,n),(K,),(K,2),(2,2) -> (n,),(n,n).
    """
    mu, P = np.asarray(mu, dtype=np.float64), np.asarray(P, dtype=np.float64)
    n = _check_state(mu, P)
    js = np.asarray(js, dtype=np.int64).reshape(-1)
    z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    k = js.size
    if z.shape[0] != k:
        raise ValueError(f"need one observation per landmark index (got {z.shape[0]} observations, {k} indices)")
    if k and (js.min() < 0 or js.max() >= (n - POSE_DIM) // 2):
        raise IndexError(f"landmark index out of range 0..{(n - POSE_DIM) // 2 - 1}: {js.tolist()}")
    check_observations(z[:, 0], z[:, 1])
    if k == 0:
        return (mu, P) if inplace else (mu.copy(), P.copy())
    lm_rows = POSE_DIM + 2 * js[:, None] + np.arange(2)  # (K,2)
    lms = mu[lm_rows]
    pose = mu[:POSE_DIM]
    z_pred = range_bearing(pose, lms).reshape(k, 2)
    hp, hl = range_bearing_jacobians(np.broadcast_to(pose, (k, POSE_DIM)), lms)  # (K,2,3), (K,2,2)
    nu = np.column_stack([z[:, 0] - z_pred[:, 0], wrap_angle(z[:, 1] - z_pred[:, 1])]).reshape(-1)
    if check and not math.isfinite(float(np.sum(P[lm_rows.reshape(-1)])) + float(np.sum(P[:POSE_DIM]))):
        raise CovarianceError("covariance rows of the observed landmarks are not finite")
    hp2 = hp.reshape(2 * k, POSE_DIM)
    B = hp2 @ P[:POSE_DIM, :] + np.einsum("kab,kbn->kan", hl, P[lm_rows]).reshape(2 * k, n)  # H P, (m, n)
    S = B[:, :POSE_DIM] @ hp2.T + np.einsum("mkb,kab->mka", B[:, lm_rows], hl).reshape(2 * k, 2 * k)
    S.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :] += R
    try:
        L = np.linalg.cholesky(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        raise CovarianceError("joint innovation covariance S is not positive definite") from None
    C = solve_triangular(L, B, lower=True, check_finite=False)
    w = solve_triangular(L, nu, lower=True, check_finite=False)
    if not inplace:
        mu, P = mu.copy(), P.copy()
    mu += C.T @ w
    mu[2] = wrap_angle_scalar(mu[2])
    _low_rank_downdate(P, np.ascontiguousarray(C))
    if check:
        d = np.diagonal(P)
        if not (np.all(np.isfinite(d)) and float(np.min(d)) >= 0.0):
            i = int(np.argmin(np.where(np.isfinite(d), d, -np.inf)))
            raise CovarianceError(f"update left P[{i},{i}] = {d[i]!r} (must be finite and >= 0)", applied=True)
    return mu, P


def _mirror_upper(P: Array, block: int = 64) -> None:
    """Copy the upper triangle of the C-ordered P onto its lower one, in place (square blocks: cache-friendly)."""
    n = P.shape[0]
    for i in range(0, n, block):
        P[i:i + block, :i] = P[:i, i:i + block].T
        d = P[i:i + block, i:i + block]
        low = _strict_lower(d.shape[0])
        d[low] = d.T[low]


@functools.lru_cache(maxsize=8)
def _strict_lower(m: int) -> tuple[IntArray, IntArray]:
    """``np.tril_indices(m, -1)``, built once per size: every EKF update mirrors its covariance, and building
    them took as long as the mirror itself. Read-only: every caller shares them."""
    rows, cols = np.tril_indices(m, -1)
    rows.flags.writeable = cols.flags.writeable = False
    return rows, cols


def _symmetric_rows(P: Array, idx: IntArray, cols: IntArray) -> Array:
    """Full rows ``idx`` of a symmetric P of which only the upper triangle is current: ``P[r, c]`` for ``c >= r``,
    ``P[c, r]`` (the column) for ``c < r``. Shapes: (n,n),(r,),(n,) -> (r,n)."""
    return np.where(cols[None, :] >= idx[:, None], P[idx, :], P[:, idx].T)


def _joint_update_upper(mu: Array, P: Array, js: IntArray, z: Array, R: Array, check: bool) -> None:
    """:func:`ekf_update_range_bearing_batch` in place on a C-ordered P whose upper triangle only is current (and
    stays so): the rows the update reads come from :func:`_symmetric_rows`, the downdate ``P -= C^T C`` is one
    ``dsyrk`` on the upper triangle (half the flops of the full ``dgemm``)."""
    n, k = mu.shape[0], js.size
    lm_rows = POSE_DIM + 2 * js[:, None] + np.arange(2)  # (K,2)
    idx = np.concatenate([np.arange(POSE_DIM), lm_rows.reshape(-1)])
    rows = _symmetric_rows(P, idx, np.arange(n))
    if check and not math.isfinite(float(np.sum(rows))):
        raise CovarianceError("covariance rows of the observed landmarks are not finite")
    lms = mu[lm_rows]
    pose = mu[:POSE_DIM]
    z_pred = range_bearing(pose, lms).reshape(k, 2)
    hp, hl = range_bearing_jacobians(np.broadcast_to(pose, (k, POSE_DIM)), lms)  # (K,2,3), (K,2,2)
    nu = np.column_stack([z[:, 0] - z_pred[:, 0], wrap_angle(z[:, 1] - z_pred[:, 1])]).reshape(-1)
    hp2 = hp.reshape(2 * k, POSE_DIM)
    B = hp2 @ rows[:POSE_DIM] + np.matmul(hl, rows[POSE_DIM:].reshape(k, 2, n)).reshape(2 * k, n)  # H P, (m, n)
    S = B[:, :POSE_DIM] @ hp2.T + np.einsum("mkb,kab->mka", B[:, lm_rows], hl).reshape(2 * k, 2 * k)
    S.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :] += R
    L, info = lapack.dpotrf(0.5 * (S + S.T), lower=1, clean=1, overwrite_a=1)
    if info != 0:
        raise CovarianceError("joint innovation covariance S is not positive definite")
    l_inv, info = lapack.dtrtri(L, lower=1, overwrite_c=1)
    if info != 0:  # pragma: no cover - a Cholesky factor has a positive diagonal
        raise CovarianceError("joint innovation covariance S is singular")
    # C^T = B^T L^-T from BLAS on the Fortran view B.T (no copies): C = L^-1 B as in the single batch
    ct = blas.dtrmm(1.0, l_inv, B.T, side=1, lower=1, trans_a=1, overwrite_b=1)
    mu += ct @ (l_inv @ nu)
    mu[2] = wrap_angle_scalar(mu[2])
    # P.T is P's memory in Fortran order; its lower triangle is P's upper one
    out = blas.dsyrk(-1.0, ct, 1.0, P.T, trans=0, lower=1, overwrite_c=1)
    if not np.shares_memory(out, P):  # pragma: no cover - BLAS wrapper declined to work in place
        P[...] = out.T
    if check:
        d = np.diagonal(P)
        if not (np.all(np.isfinite(d)) and float(np.min(d)) >= 0.0):
            i = int(np.argmin(np.where(np.isfinite(d), d, -np.inf)))
            raise CovarianceError(f"update left P[{i},{i}] = {d[i]!r} (must be finite and >= 0)", applied=True)


def ekf_update_range_bearing_batches(mu: Array, P: Array, js: ArrayLike, z: ArrayLike, R: Array, *,
                                     batch: int, check: bool = True) -> tuple[Array, Array]:
    """Joint updates of ``batch`` observations at a time, in order, in place: exactly the maths of calling
    :func:`ekf_update_range_bearing_batch` on ``js[0:batch]``, ``js[batch:2 batch]``, ... (each chunk linearised
    at the mean the previous one left), in about half the time for big P.

    Between chunks only P's upper triangle is kept current: each downdate is one ``dsyrk`` (half the flops of a
    ``dgemm``), the rows a chunk reads are gathered from the triangle and its columns, and the lower triangle is
    mirrored once at the end (also before a :class:`CovarianceError` leaves, whose ``done`` is then the number of
    observations applied before the failing chunk). ``mu`` and P must be float64, P C-contiguous (else the
    chunks go through :func:`ekf_update_range_bearing_batch`). Shapes: (n,),(n,n),(K,),(K,2),(2,2) -> (n,),(n,n).
    """
    mu, P = np.asarray(mu), np.asarray(P)
    n = _check_state(mu, P)
    js = np.asarray(js, dtype=np.int64).reshape(-1)
    z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    if z.shape[0] != js.size:
        raise ValueError(f"need one observation per landmark index (got {z.shape[0]} observations, {js.size} indices)")
    if batch < 1:
        raise ValueError(f"batch must be >= 1 (got {batch})")
    if js.size and (js.min() < 0 or js.max() >= (n - POSE_DIM) // 2):
        raise IndexError(f"landmark index out of range 0..{(n - POSE_DIM) // 2 - 1}: {js.tolist()}")
    check_observations(z[:, 0], z[:, 1])
    if mu.dtype != np.float64 or P.dtype != np.float64 or not P.flags.c_contiguous or not P.flags.writeable \
            or not mu.flags.writeable:
        for c in range(0, js.size, batch):
            try:
                mu, P = ekf_update_range_bearing_batch(mu, P, js[c:c + batch], z[c:c + batch], R, inplace=True,
                                                       check=check)
            except CovarianceError as e:
                e.done = c
                raise
        return mu, P
    try:
        for c in range(0, js.size, batch):
            try:
                _joint_update_upper(mu, P, js[c:c + batch], z[c:c + batch], R, check)
            except CovarianceError as e:
                e.done = c
                raise
    finally:
        _mirror_upper(P)
    return mu, P


def ekf_update_position(mu: Array, P: Array, z_xy: ArrayLike, R_gps: Array, *,
                        inplace: bool = False, check: bool = True) -> tuple[Array, Array]:
    """Absolute position (GPS) update: ``z = [x, y] + noise``; corrects every landmark through the correlations."""
    mu = np.asarray(mu, dtype=np.float64)
    _check_state(mu, np.asarray(P))
    z = np.asarray(z_xy, dtype=np.float64)
    if z.shape != (2,) or not np.all(np.isfinite(z)):
        raise ValueError(f"GPS fix must be 2 finite numbers [x, y], got {z!r}")
    (h,) = absolute_position_jacobians(mu[:POSE_DIM])
    nu = z - absolute_position(mu[:POSE_DIM])
    return ekf_update(mu, P, np.arange(POSE_DIM), h, nu, R_gps, inplace=inplace, check=check)


# ---------------------------------------------------------------------------------------------------- augment/remove
def augment_linearized(mu: Array, P: Array, l_new: Array, G_r: Array, G_z: Array, R: Array) -> tuple[Array, Array]:
    """Append landmarks ``l_new`` (k,2) initialised from the robot with Jacobians ``G_r`` (k,2,3), ``G_z`` (k,2,2).

    New cross-covariance rows ``G_r P[:3, :]``; new block ``G_r P_rr G_r^T + G_z R G_z^T`` (with the landmarks'
    mutual correlation ``G_ri P_rr G_rj^T`` when several are added at once). O(n^2): P is copied once.
    Shapes: (n,),(n,n) -> (n+2k,),(n+2k,n+2k).
    """
    n = _check_state(mu, P)
    k = l_new.shape[0]
    gr = G_r.reshape(2 * k, POSE_DIM)
    cross = gr @ P[:POSE_DIM, :]  # (2k, n)
    new = gr @ P[:POSE_DIM, :POSE_DIM] @ gr.T
    ar = np.arange(k)
    new.reshape(k, 2, k, 2)[ar, :, ar, :] += G_z @ R @ np.swapaxes(G_z, -1, -2)  # measurement noise: own blocks
    P_new = np.empty((n + 2 * k, n + 2 * k))
    P_new[:n, :n] = P
    P_new[n:, :n] = cross
    P_new[:n, n:] = cross.T
    P_new[n:, n:] = 0.5 * (new + new.T)
    return np.concatenate([mu, l_new.reshape(-1)]), P_new


def augment_state_batch(mu: Array, P: Array, z: ArrayLike, R_obs: Array) -> tuple[Array, Array]:
    """Append one landmark per [range, bearing] row of ``z`` (k,2), all seen from the current pose. O(n^2)."""
    mu, P = np.asarray(mu, dtype=np.float64), np.asarray(P, dtype=np.float64)
    _check_state(mu, P)
    z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    check_observations(z[:, 0], z[:, 1])
    R_obs = _check_noise(R_obs, "R_obs", 2)
    pose = np.broadcast_to(mu[:POSE_DIM], (z.shape[0], POSE_DIM))
    g_r, g_z = range_bearing_inverse_jacobians(pose, z)
    return augment_linearized(mu, P, range_bearing_inverse(pose, z), g_r, g_z, R_obs)


def augment_state(mu: Array, P: Array, z_range: float, z_bearing: float, R_obs: Array) -> tuple[Array, Array]:
    """Add a landmark seen at ``(z_range, z_bearing)`` from the robot pose ``mu[:3]`` to the state.

    The landmark is the inverse observation model ``l = [x + r cos(theta + b), y + r sin(theta + b)]``; its
    cross-covariance with everything already in the state is ``G_r P[:3, :]`` and its own block is
    ``G_r P_rr G_r^T + G_z R G_z^T`` (``G_r``, ``G_z``: Jacobians of the inverse model w.r.t. pose and measurement).
    Shapes: mu (n,), P (n,n), R_obs (2,2) -> (n+2,), (n+2,n+2).
    """
    return augment_state_batch(mu, P, np.array([[z_range, z_bearing]], dtype=np.float64), R_obs)


def remove_landmarks(mu: Array, P: Array, js: ArrayLike) -> tuple[Array, Array]:
    """Drop landmarks ``js`` (marginalise them out: delete their rows and columns). O(n^2)."""
    n = _check_state(mu, P)
    js = np.asarray(js, dtype=np.int64).reshape(-1)
    keep = np.ones(n, dtype=bool)
    for off in (0, 1):
        keep[POSE_DIM + 2 * js + off] = False
    k = np.flatnonzero(keep)
    return mu[k].copy(), np.ascontiguousarray(P[np.ix_(k, k)])


# ---------------------------------------------------------------------------------------------------- candidates
def predict_landmarks(mu: Array, P: Array, js: ArrayLike, R: Array, *,
                      joint: bool = False) -> tuple[Array, Array, Array | None]:
    """Predicted measurements of landmarks ``js`` (L,) with innovation covariances, vectorised.

    Returns ``z_pred`` (L,2), ``S`` (L,2,2) and, with ``joint``, ``S_joint`` (2L,2L): the joint innovation
    covariance built from the pose + candidate sub-block of P only (O(L^2) entries of P, never the whole P).
    """
    js = np.asarray(js, dtype=np.int64).reshape(-1)
    n_l = js.shape[0]
    pose = mu[:POSE_DIM]
    lm_idx = (POSE_DIM + 2 * js[:, None] + np.arange(2)).reshape(-1)  # (2L,)
    lms = mu[lm_idx].reshape(n_l, 2)
    z_pred = range_bearing(pose, lms).reshape(n_l, 2)
    hp, hl = range_bearing_jacobians(np.broadcast_to(pose, (n_l, POSE_DIM)), lms)
    rows = lm_idx.reshape(n_l, 2)
    if not joint:
        return z_pred, innovation_covariance(hp, hl, P, rows, R), None
    return (z_pred, *joint_innovation_covariance(hp, hl, P, rows, R))


def run_association(observations: Observations, candidates: Candidates, config: AssociationConfig,
                    rng: np.random.Generator) -> AssociationResult:
    """Associate through ``slam2d.association.associate``; an invalid innovation covariance (which can only come
    from a corrupted P) is reported as a :class:`CovarianceError` so the covariance guard handles it."""
    try:
        return associate(observations, candidates, config, rng=rng)
    except ValueError as e:
        if "Candidates.S" in str(e):
            raise CovarianceError(f"association: {e}", applied=False) from None
        raise
