"""Innovation covariances of landmark measurements, and :class:`Candidates` built from a Gaussian belief over
[pose, landmarks] (what an EKF holds, or a pose belief plus a landmark map).

:func:`innovation_covariance` is the one builder of ``S = H P H^T + R`` (per landmark) and of the joint
``S_joint = H P H^T + I (x) R`` (all candidates together, with their cross-covariances) used by EKF-SLAM, the online
graph's candidates, the association experiments and the web lab.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.association.base import Candidates
from slam2d.models.sensors import range_bearing, range_bearing_jacobians

Array = NDArray[np.float64]


def candidates_from_belief(
    pose: ArrayLike,
    landmarks: ArrayLike,
    ids: ArrayLike,
    cov: ArrayLike,
    sensor_cov: ArrayLike,
    descriptors: ArrayLike | None = None,
) -> Candidates:
    """Predicted measurements of ``landmarks`` from ``pose`` with the joint covariance of the state.

    ``cov`` is the covariance of the stacked state ``[x, y, theta, l1x, l1y, ..., lLx, lLy]`` (pose-landmark and
    landmark-landmark correlations included, as in EKF-SLAM). ``sensor_cov`` is R (2,2) for one measurement.
    Shapes: pose (3,), landmarks (L,2), ids (L,), cov (3+2L, 3+2L), sensor_cov (2,2), descriptors (L,D) or None.
    """
    pose = np.asarray(pose, dtype=np.float64)
    lm = np.asarray(landmarks, dtype=np.float64).reshape(-1, 2)
    n = lm.shape[0]
    cov = np.asarray(cov, dtype=np.float64)
    r = np.asarray(sensor_cov, dtype=np.float64)
    if pose.shape != (3,):
        raise ValueError(f"pose must have shape (3,), got {pose.shape}")
    if cov.shape != (3 + 2 * n, 3 + 2 * n):
        raise ValueError(f"cov must have shape ({3 + 2 * n}, {3 + 2 * n}) for {n} landmarks, got {cov.shape}")
    if r.shape != (2, 2):
        raise ValueError(f"sensor_cov must have shape (2, 2), got {r.shape}")
    z_pred = range_bearing(pose, lm)
    hp, hl = range_bearing_jacobians(np.broadcast_to(pose, (n, 3)), lm)  # (L,2,3), (L,2,2)
    s, s_joint = joint_innovation_covariance(hp, hl, cov, 3 + 2 * np.arange(n)[:, None] + np.arange(2), r)
    return Candidates(
        ids=np.asarray(ids, dtype=np.int64).reshape(n),
        z_pred=z_pred.reshape(n, 2),
        S=s,
        S_joint=s_joint,
        descriptors=None if descriptors is None else np.asarray(descriptors, dtype=np.float64).reshape(n, -1),
    )


def innovation_covariance(hp: ArrayLike, hl: ArrayLike, cov: ArrayLike, rows: ArrayLike | None,
                          r: ArrayLike) -> Array:
    """Innovation covariance ``S_i = H_i P H_i^T + r`` of each of L measurements ``z_i = h(pose, l_i) + v_i``.

    ``hp`` (L,m,3) and ``hl`` (L,m,2) are dh/dpose and dh/dl_i; ``cov`` (n,n) is any covariance whose rows 0..2 are
    the pose and whose rows ``rows[i]`` (L,2) are landmark i (an EKF's whole P, or a joint block); ``r`` (m,m) the
    measurement noise. ``rows=None`` means the landmarks are known exactly (only the pose is uncertain). Reads O(L)
    entries of ``cov``. Returns (L,m,m).
    """
    hp, hl, cov, r = (np.asarray(a, dtype=np.float64) for a in (hp, hl, cov, r))
    s = np.einsum("iab,bc,idc->iad", hp, cov[:3, :3], hp) + r
    if rows is not None:
        idx = np.asarray(rows, dtype=np.int64).reshape(hp.shape[0], 2)
        t_pl = np.einsum("iab,bic,idc->iad", hp, cov[:3][:, idx], hl)
        p_ll = cov[idx[:, :, None], idx[:, None, :]]  # (L,2,2) diagonal blocks
        s = s + t_pl + np.swapaxes(t_pl, 1, 2) + np.einsum("iab,ibc,idc->iad", hl, p_ll, hl)
    return 0.5 * (s + np.swapaxes(s, 1, 2))


def joint_innovation_covariance(hp: ArrayLike, hl: ArrayLike, cov: ArrayLike, rows: ArrayLike | None,
                                r: ArrayLike) -> tuple[Array, Array]:
    """``(S, S_joint)``: :func:`innovation_covariance` and the joint ``S_joint = H P H^T + I (x) r`` (Lm,Lm) of all L
    measurements together (their cross-covariances through the shared pose and correlated landmarks), with
    H = [hp | blockdiag(hl)] never formed. Same arguments; reads O(L^2) entries of ``cov``.
    """
    hp, hl, cov = (np.asarray(a, dtype=np.float64) for a in (hp, hl, cov))
    n, m = hp.shape[0], hp.shape[1]
    s = innovation_covariance(hp, hl, cov, rows, r)
    p_pp = cov[:3, :3]
    sj = np.einsum("iab,bc,jdc->iajd", hp, p_pp, hp)
    if rows is not None:
        idx = np.asarray(rows, dtype=np.int64).reshape(n, 2)
        flat = idx.reshape(-1)
        cross = np.einsum("iab,bjc,jdc->iajd", hp, cov[:3][:, idx], hl)
        p_ll = cov[np.ix_(flat, flat)].reshape(n, 2, n, 2)
        sj = sj + cross + cross.transpose(2, 3, 0, 1) + np.einsum("iab,ibjc,jdc->iajd", hl, p_ll, hl)
    ar = np.arange(n)
    sj[ar, :, ar, :] = s  # diagonal blocks: the per-measurement S, which carry the noise r
    sj = sj.reshape(n * m, n * m)
    return s, 0.5 * (sj + sj.T)
