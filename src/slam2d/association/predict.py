"""Build :class:`Candidates` from a Gaussian belief over [pose, landmarks] (what an EKF holds, or a pose belief plus
a landmark map): predicted range-bearing measurements and their joint innovation covariance
``S_joint = H P H^T + I (x) R``, with the Jacobians of :func:`slam2d.models.sensors.range_bearing`.
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
    pxx = cov[:3, :3]
    pxl = cov[:3, 3:].reshape(3, n, 2)
    pll = cov[3:, 3:].reshape(n, 2, n, 2)
    # H = [Hp | blockdiag(Hl)], so every term is a block product; einsum keeps it O(L^2) without forming H
    a = np.einsum("iap,pq,jbq->iajb", hp, pxx, hp)
    b = np.einsum("iap,pjq,jbq->iajb", hp, pxl, hl)
    c = np.einsum("iap,ipjq,jbq->iajb", hl, pll, hl)
    s_joint = (a + b + b.transpose(2, 3, 0, 1) + c).reshape(2 * n, 2 * n)
    s_joint[np.arange(2 * n), np.arange(2 * n)] += np.tile(np.diag(r), n)
    s_joint[np.arange(0, 2 * n, 2), np.arange(1, 2 * n, 2)] += r[0, 1]
    s_joint[np.arange(1, 2 * n, 2), np.arange(0, 2 * n, 2)] += r[1, 0]
    s_joint = 0.5 * (s_joint + s_joint.T)
    s = s_joint.reshape(n, 2, n, 2)[np.arange(n), :, np.arange(n), :].copy()
    return Candidates(
        ids=np.asarray(ids, dtype=np.int64).reshape(n),
        z_pred=z_pred.reshape(n, 2),
        S=s,
        S_joint=s_joint,
        descriptors=None if descriptors is None else np.asarray(descriptors, dtype=np.float64).reshape(n, -1),
    )


def candidates_from_pose_belief(pose: ArrayLike, pose_cov: ArrayLike, landmarks: ArrayLike, ids: ArrayLike,
                                sensor_cov: ArrayLike) -> Candidates:
    """Candidates for a known map seen from an uncertain pose: landmarks exact, pose ~ N(pose, pose_cov).

    The only correlation between predictions is the shared pose error, so ``S_joint = Hp P Hp^T + I (x) R``.
    Shapes: pose (3,), pose_cov (3,3), landmarks (L,2), ids (L,), sensor_cov (2,2).
    """
    lm = np.asarray(landmarks, dtype=np.float64).reshape(-1, 2)
    cov = np.zeros((3 + 2 * len(lm), 3 + 2 * len(lm)))
    cov[:3, :3] = np.asarray(pose_cov, dtype=np.float64)
    return candidates_from_belief(pose, lm, ids, cov, sensor_cov)
