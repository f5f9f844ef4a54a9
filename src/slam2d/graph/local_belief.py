"""The joint Gaussian over [newest pose, nearby landmarks] that online graph SLAM associates against.

Data association needs the innovation covariance ``S = H Sigma H^T + R`` of every candidate, and ``Sigma`` must be
the JOINT covariance of the pose and the candidates: far from the origin both marginals are large but strongly
correlated, and dropping the pose-landmark cross-covariance overestimates S many times over (gates grow until wrong
matches pass). A graph has no such matrix at hand, so :class:`LocalBelief` keeps one:

* at every optimisation it is set to the joint marginal of [newest pose, landmarks near it], recovered from the
  optimiser's factorisation (:func:`slam2d.graph.marginals.marginal_covariances`);
* between optimisations it is propagated exactly like an EKF-SLAM prediction (only the pose rows change:
  ``Sigma_pp <- G Sigma_pp G^T + V Q V^T``, ``Sigma_pl <- G Sigma_pl``, Probabilistic Robotics table 10.1) and
  extended with each landmark started since (``augment``, the inverse-sensor-model Jacobians, table 10.2 line 17);
* the measurements associated in between update it as an EKF update does (table 10.1 lines 12-16, all of a step's
  matches at once), and the caller moves the newest pose and the block's landmarks by the same correction. This is
  exact for the (linearised) block: the measurements involve only the block's variables, and the marginal of a
  Gaussian conditioned on such measurements depends only on the prior marginal of those variables. So between
  optimisations the online estimate is corrected every step, as an EKF's, instead of drifting on dead reckoning; the
  next optimisation relinearises everything (the same factors are in the graph) and replaces the block.

Cost per step: O(L) for the prediction and O(L^2 m) for an update with m matches, for L landmarks in the block;
nothing here touches the whole graph.
Shapes: keys (L,), cov (3+2L, 3+2L) ordered [x, y, theta, l1x, l1y, ...].
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class LocalBelief:
    """Joint covariance of the newest pose and a set of landmark keys (see module doc)."""

    def __init__(self, pose_cov: ArrayLike | None = None) -> None:
        self.keys: IntArray = np.zeros(0, np.int64)
        self.cov: Array = np.zeros((3, 3)) if pose_cov is None else np.array(pose_cov, dtype=np.float64)

    @property
    def pose_cov(self) -> Array:
        """The newest pose's marginal (a view, 3x3)."""
        return self.cov[:3, :3]

    def set(self, keys: ArrayLike, cov: ArrayLike) -> None:
        """Replace the block (e.g. by a fresh joint marginal). Shapes: keys (L,), cov (3+2L, 3+2L)."""
        k = np.asarray(keys, dtype=np.int64).reshape(-1)
        c = np.array(cov, dtype=np.float64)
        if c.shape != (3 + 2 * k.size,) * 2:
            raise ValueError(f"LocalBelief.set: cov must be {(3 + 2 * k.size,) * 2} for {k.size} keys, got {c.shape}")
        self.keys, self.cov = k, 0.5 * (c + c.T)

    def predict(self, G: ArrayLike, noise: ArrayLike) -> None:
        """The newest pose moved: x' = f(x, u) with df/dx = G (3,3) and added noise V Q V^T (3,3)."""
        G = np.asarray(G, dtype=np.float64)
        self.cov[:3, 3:] = G @ self.cov[:3, 3:]
        self.cov[3:, :3] = self.cov[:3, 3:].T
        self.cov[:3, :3] = G @ self.cov[:3, :3] @ G.T + np.asarray(noise, dtype=np.float64)

    def augment(self, keys: ArrayLike, Gp: ArrayLike, Gz: ArrayLike, R: ArrayLike) -> None:
        """Landmarks l_i = g(x, z_i) started from the newest pose x: Gp (n,2,3) = dg/dx, Gz (n,2,2) = dg/dz, R (2,2)
        the noise of each z_i (independent)."""
        k = np.asarray(keys, dtype=np.int64).reshape(-1)
        n = k.size
        if n == 0:
            return
        gp = np.asarray(Gp, dtype=np.float64).reshape(n * 2, 3)
        gz = np.asarray(Gz, dtype=np.float64).reshape(n, 2, 2)
        cross = gp @ self.cov[:3, :]  # (2n, 3+2L): Cov(l_new, [x, l_old])
        new = gp @ cross[:, :3].T
        own = gz @ np.asarray(R, dtype=np.float64) @ np.swapaxes(gz, 1, 2)
        new.reshape(n, 2, n, 2)[np.arange(n), :, np.arange(n), :] += own
        m = self.cov.shape[0]
        out = np.empty((m + 2 * n, m + 2 * n))
        out[:m, :m] = self.cov
        out[m:, :m] = cross
        out[:m, m:] = cross.T
        out[m:, m:] = 0.5 * (new + new.T)
        self.cov = out
        self.keys = np.concatenate([self.keys, k])

    def update(self, keys: ArrayLike, Hp: ArrayLike, Hl: ArrayLike, nu: ArrayLike, R: ArrayLike) -> Array:
        """Condition on m measurements z_i of landmarks ``keys`` (all in the block; none repeated) from the newest
        pose: Hp (m,2,3), Hl (m,2,2) the Jacobians, nu (m,2) the innovations (angles already wrapped), R (2,2).
        Returns the correction (3+2L,) of the block's mean [pose, landmarks]; the covariance is updated in place.
        """
        r = self.rows(keys)
        if np.any(r < 0):
            raise KeyError("LocalBelief.update: key not in the block")
        m = r.size
        P = self.cov
        hp = np.asarray(Hp, dtype=np.float64).reshape(m, 2, 3)
        hl = np.asarray(Hl, dtype=np.float64).reshape(m, 2, 2)
        idx = 3 + 2 * r[:, None] + np.arange(2)  # (m, 2) rows of each landmark
        # P H^T without forming H = [Hp | blockdiag(Hl) at the landmarks' columns]
        PHt = P[:, :3] @ hp.reshape(2 * m, 3).T + np.einsum("nmb,mab->nma", P[:, idx], hl).reshape(-1, 2 * m)
        rowsH = PHt[idx].reshape(m, 2, 2 * m)  # (H P)^T restricted to the landmark rows
        S = hp.reshape(2 * m, 3) @ PHt[:3] + np.einsum("mab,mbk->mak", hl, rowsH).reshape(2 * m, 2 * m)
        S.reshape(m, 2, m, 2)[np.arange(m), :, np.arange(m), :] += np.asarray(R, dtype=np.float64)
        S = 0.5 * (S + S.T)
        c = np.linalg.cholesky(S)
        W = np.linalg.solve(c, PHt.T)  # (2m, n): K = W^T c^-1, K S K^T = W^T W
        dx = W.T @ np.linalg.solve(c, np.asarray(nu, dtype=np.float64).reshape(2 * m))
        P -= W.T @ W
        self.cov = 0.5 * (P + P.T)
        return np.asarray(dx)

    def rows(self, keys: ArrayLike) -> IntArray:
        """Position of each key in ``self.keys`` (-1 where absent). Shapes: keys (n,) -> (n,)."""
        k = np.asarray(keys, dtype=np.int64).reshape(-1)
        if self.keys.size == 0:
            return np.full(k.size, -1, np.int64)
        order = np.argsort(self.keys, kind="stable")
        pos = np.minimum(np.searchsorted(self.keys[order], k), self.keys.size - 1)
        found = self.keys[order][pos] == k
        return np.where(found, order[pos], -1).astype(np.int64)

    def select(self, keys: ArrayLike) -> Array:
        """Joint covariance of [pose, keys...] (every key must be present). Shape (3+2n, 3+2n)."""
        r = self.rows(keys)
        if np.any(r < 0):
            raise KeyError(f"LocalBelief.select: keys {np.asarray(keys).reshape(-1)[r < 0].tolist()} not in the block")
        idx = np.concatenate([np.arange(3), (3 + 2 * r[:, None] + np.arange(2)).reshape(-1)])
        return self.cov[np.ix_(idx, idx)]

    def point_covs(self, keys: ArrayLike) -> Array:
        """Marginal 2x2 covariance of each key (must be present). Shape (n, 2, 2)."""
        r = self.rows(keys)
        if np.any(r < 0):
            raise KeyError("LocalBelief.point_covs: key not in the block")
        idx = 3 + 2 * r[:, None] + np.arange(2)
        return self.cov[idx[:, :, None], idx[:, None, :]]

    def remove(self, keys: ArrayLike) -> None:
        """Drop these landmarks (absent keys are ignored): marginalising a Gaussian is deleting its rows."""
        r = self.rows(keys)
        r = r[r >= 0]
        if r.size == 0:
            return
        keep = np.ones(self.keys.size, dtype=bool)
        keep[r] = False
        idx = np.concatenate([np.arange(3), (3 + 2 * np.flatnonzero(keep)[:, None] + np.arange(2)).reshape(-1)])
        self.cov = self.cov[np.ix_(idx, idx)]
        self.keys = self.keys[keep]
