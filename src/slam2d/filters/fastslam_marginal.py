"""The linearised pose marginal FastSLAM can report: EKF-SLAM's covariance recursion run at FastSLAM's own estimate.

Why: FastSLAM's particle cloud is the whole of its pose belief, and resampling makes the particles' paths (hence
their maps) coalesce onto a few ancestors, so the cloud's spread stops growing with the map's drift while the
error does (Bailey, Nieto & Nebot, "Consistency of the FastSLAM algorithm", ICRA 2006). The spread cannot report
what the particles no longer represent.

What: the covariance half of EKF-SLAM over ``[pose, landmarks]`` -- predict ``P_rr <- G P_rr G^T + V Q V^T``,
``P_rm <- G P_rm``; observation update ``P <- P - P H^T S^-1 H P`` (``S = H P H^T + R``); augmentation with
``G_r``, ``G_z`` -- with every Jacobian evaluated at FastSLAM's estimate (its mean pose and its landmark means)
instead of at an EKF's own mean. No state is propagated here: only the covariance, which the noise models the
filter assumes determine together with the linearisation points. Its pose block is the Gaussian (Laplace)
approximation of the posterior marginal of the current pose around FastSLAM's own path and map. Landmarks keep
their first linearisation point and the motion Jacobian uses the displacement between consecutive estimates
(first-estimate Jacobians), so no spurious information about the global frame appears. What FastSLAM reports is
``L + (L - C)_+`` (:meth:`LinearisedMarginal.reported_pose_cov`, C: the particle covariance).

Cost: O(n^2) per observation with n = 3 + 2N (EKF-SLAM's cost), so it is an option, not FastSLAM's default. Landmarks
are keyed by the filter's slot number, which names the same landmark in every particle only with known association.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam2d.filters.ekf_kernels import augment_linearized, ekf_predict_linearized, ekf_update
from slam2d.models.motion import MotionNoise, odometry_covariance_scalar, odometry_scalar
from slam2d.models.sensors import range_bearing_inverse_jacobians, range_bearing_scalar

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

POSE_DIM = 3


class LinearisedMarginal:
    """Covariance-only EKF-SLAM recursion, linearised at externally given poses and landmark positions.

    Per step: :meth:`predict` with the previous estimate, then :meth:`observe` once per observation (in the order
    the filter used them), then :meth:`pose_cov`. ``slot`` identifies a landmark (it gets a state block at its first
    observation).
    """

    def __init__(self, initial_pose: Array, r: Array) -> None:
        self._mu = np.asarray(initial_pose, dtype=np.float64).copy()
        self._P = np.zeros((POSE_DIM, POSE_DIM))
        self._r = np.asarray(r, dtype=np.float64)
        self._index: dict[int, int] = {}  # slot -> landmark index in the state

    @property
    def slots(self) -> list[int]:
        """The landmarks in the state, in state order."""
        return list(self._index)

    def predict(self, pose: Array, u: Array, noise: MotionNoise) -> None:
        """Odometry ``u`` (3,) that took the robot from the previous linearisation pose to ``pose`` (3,).

        The Jacobian uses the two linearisation poses themselves (``G = d(x (+) u)/dx`` with the displacement
        ``pose - previous``), so that the chain of Jacobians keeps global translation and rotation unobservable."""
        prev = self._mu[:POSE_DIM]
        _, _, v = odometry_scalar(prev, u)
        g = np.eye(POSE_DIM)
        g[0, 2], g[1, 2] = -(pose[1] - prev[1]), pose[0] - prev[0]
        q = v @ odometry_covariance_scalar(u, noise) @ v.T
        self._mu, self._P = ekf_predict_linearized(self._mu, self._P, pose, g, q, inplace=True)

    def observe(self, slot: int, landmark: Array, z: Array) -> None:
        """One range-bearing observation ``z`` (2,) of landmark ``slot`` from the current linearisation pose.

        ``landmark`` (2,) is the landmark's position estimate; only its first value is used (first-estimate
        Jacobians: re-linearising a landmark at a moved estimate would invent information about the unobservable
        global frame; Huang, Mourikis & Roumeliotis, "Analysis and improvement of the consistency of extended
        Kalman filter based SLAM", ICRA 2008)."""
        pose = self._mu[:POSE_DIM]
        j = self._index.get(slot)
        if j is None:
            lm = np.asarray(landmark, dtype=np.float64)
            _, g_z = range_bearing_inverse_jacobians(pose, z)
            g_r = np.array([[1.0, 0.0, -(lm[1] - pose[1])], [0.0, 1.0, lm[0] - pose[0]]])
            self._index[slot] = len(self._index)
            self._mu, self._P = augment_linearized(self._mu, self._P, lm[None], g_r[None], g_z[None], self._r)
            return
        a = POSE_DIM + 2 * j
        _, h = range_bearing_scalar(pose, self._mu[a:a + 2])
        idx = np.array([0, 1, 2, a, a + 1], dtype=np.int64)
        # covariance only: a zero innovation leaves the linearisation point where FastSLAM put it
        self._mu, self._P = ekf_update(self._mu, self._P, idx, h, np.zeros(2), self._r, inplace=True, check=False)

    def step(self, pose: Array, u: Array, noise: MotionNoise, slots: IntArray, landmarks: Array, z: Array) -> None:
        """One filter step: odometry ``u`` to the estimate ``pose`` (3,), then observations ``z`` (k,2) of landmarks
        ``slots`` (k,) whose current estimates are ``landmarks`` (k,2), in the order the filter used them."""
        self.predict(pose, u, noise)
        for slot, landmark, zj in zip(slots, landmarks, z, strict=True):
            self.observe(int(slot), landmark, zj)

    def pose_cov(self) -> Array:
        """The current pose's linearised marginal covariance ``L`` (3,3)."""
        return self._P[:POSE_DIM, :POSE_DIM].copy()

    def reported_pose_cov(self, particle_cov: Array) -> Array:
        """``L + (L - C)_+``: the marginal plus the part of it that the particle covariance ``C`` (3,3) misses.

        Why the second term: after the particles' paths coalesce, their cloud is the posterior *given* the few
        surviving ancestors, which are themselves one random draw; by the law of total covariance that draw moves the
        cloud's mean off the posterior mean with covariance about ``L - C``, independently of the posterior's own
        error ``L``. Measured (benchmarks/fastslam_nees.py, 30 seeds x 200 steps, room and loop, per quarter of the
        run): with d = FastSLAM's mean pose minus EKF-SLAM's, the diagonal of E[d d^T] is 0.65-1.36 times that of
        E[P_ekf - C], and within 26 % for the largest entry of every quarter. Early on, when the cloud still spans
        the posterior, ``(L - C)_+`` is ~0. ``(.)_+`` keeps the non-negative eigenvalues.
        """
        lin = self.pose_cov()
        d = lin - np.asarray(particle_cov, dtype=np.float64)
        w, v = np.linalg.eigh(0.5 * (d + d.T))
        out = lin + (v * np.maximum(w, 0.0)) @ v.T
        return 0.5 * (out + out.T)
