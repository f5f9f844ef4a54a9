"""The landmark map: means, covariances, ids and observation counts, with a persistence rule for new landmarks.

:class:`LandmarkMap` is a plain container of stacked arrays (means (N,2), covariances (N,2,2), ids (N,), sighting
counts, first/last step seen, a ``confirmed`` flag) that any back end can fill and hand to the lab. Its
:meth:`LandmarkMap.estimate_view` returns the confirmed landmarks only, in the shapes of
:class:`~slam2d.estimator.Estimate`.

Persistence (dynamic-object filtering): a new landmark starts *tentative*; it is *confirmed* once it has been
sighted ``min_sightings`` times and its sightings agree with one fixed point: the weighted residual sum of squares
of the sightings about their weighted mean, ``chi2 = sum_i (z_i - m)^T R_i^-1 (z_i - m)`` (kept as running sums),
is below the chi-square quantile with ``2 (n - 1)`` degrees of freedom. A forklift re-observed every step drifts
away from its own mean by more than the sensor noise explains: it fails the test, is marked ``dynamic`` and is
never confirmed. Because a slow object drifts by about one noise sigma per step, the generic test is weak against
it; a second, sharper test fits a constant-velocity line ``z(t) = a + b t`` (t in steps) by weighted least squares
and flags the landmark when the velocity is significant, ``b^T Cov(b)^-1 b > chi2_2(velocity_probability)``.
Tentative landmarks not seen for ``max_unseen_steps`` steps are dropped (:meth:`LandmarkMap.prune`).

:class:`PersistentLandmarkMapper` is the simplest user of the map: given poses (true or estimated) and
range-bearing observations, it fuses each sighting into the nearest landmark within a Mahalanobis gate
(information-form update with the inverse-sensor-model covariance) or starts a new tentative landmark.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from slam2d.geometry.gaussian import chi2_gate
from slam2d.models.sensors import SensorConfig, range_bearing_inverse, range_bearing_inverse_jacobians

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, slots=True, kw_only=True)
class PersistenceConfig:
    """When a tentative landmark joins the map."""

    min_sightings: int = 10
    """k: sightings (at distinct steps) needed before a landmark is confirmed."""
    consistency_probability: float = 0.99
    """a landmark whose sightings' chi-square exceeds this quantile (2(n-1) dof) is dynamic."""
    max_unseen_steps: int = 10
    """tentative landmarks not sighted for this many steps are dropped."""
    velocity_probability: float = 0.999
    """a landmark whose fitted velocity exceeds this chi-square(2) quantile is dynamic."""
    gate_probability: float = 0.99
    """chi-square gate (2 dof) for fusing a sighting into an existing landmark."""

    def __post_init__(self) -> None:
        if self.min_sightings < 1:
            raise ValueError(f"PersistenceConfig.min_sightings must be >= 1 (got {self.min_sightings})")
        if self.max_unseen_steps < 1:
            raise ValueError(f"PersistenceConfig.max_unseen_steps must be >= 1 (got {self.max_unseen_steps})")
        if not 0 < self.consistency_probability < 1:
            raise ValueError("PersistenceConfig.consistency_probability must be in (0, 1) "
                             f"(got {self.consistency_probability})")
        if not 0 < self.velocity_probability < 1:
            raise ValueError("PersistenceConfig.velocity_probability must be in (0, 1) "
                             f"(got {self.velocity_probability})")
        if not 0 < self.gate_probability < 1:
            raise ValueError(f"PersistenceConfig.gate_probability must be in (0, 1) (got {self.gate_probability})")


class LandmarkMap:
    """Stacked landmark arrays. Shapes (N landmarks): ids (N,), means (N,2), covs (N,2,2), counts (N,), first_step
    (N,), last_step (N,), confirmed (N,) bool, dynamic (N,) bool; info_sum (N,2,2) = sum R_i^-1, info_z (N,2) =
    sum R_i^-1 z_i, z_info_z (N,) = sum z_i^T R_i^-1 z_i, info_t (N,2,2) = sum R_i^-1 t_i, info_tt (N,2,2) =
    sum R_i^-1 t_i^2, info_tz (N,2) = sum R_i^-1 t_i z_i are running sums over the sightings (t_i = step)."""

    def __init__(self, config: PersistenceConfig | None = None) -> None:
        self.config = config or PersistenceConfig()
        self.ids = np.zeros(0, dtype=np.int64)
        self.means = np.zeros((0, 2))
        self.covs = np.zeros((0, 2, 2))
        self.counts = np.zeros(0, dtype=np.int64)
        self.first_step = np.zeros(0, dtype=np.int64)
        self.last_step = np.zeros(0, dtype=np.int64)
        self.confirmed = np.zeros(0, dtype=bool)
        self.dynamic = np.zeros(0, dtype=bool)
        self.info_sum = np.zeros((0, 2, 2))
        self.info_z = np.zeros((0, 2))
        self.z_info_z = np.zeros(0)
        self.info_t = np.zeros((0, 2, 2))
        self.info_tt = np.zeros((0, 2, 2))
        self.info_tz = np.zeros((0, 2))
        self._next_id = 0

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def add(self, means: ArrayLike, covs: ArrayLike, step: int) -> IntArray:
        """Start tentative landmarks (one sighting each); returns their new ids. Shapes: (K,2),(K,2,2) -> (K,)."""
        m = np.asarray(means, dtype=np.float64).reshape(-1, 2)
        c = np.asarray(covs, dtype=np.float64).reshape(-1, 2, 2)
        k = len(m)
        new = np.arange(self._next_id, self._next_id + k, dtype=np.int64)
        self._next_id += k
        self.ids = np.concatenate([self.ids, new])
        self.means = np.vstack([self.means, m])
        self.covs = np.concatenate([self.covs, c])
        self.counts = np.concatenate([self.counts, np.ones(k, dtype=np.int64)])
        self.first_step = np.concatenate([self.first_step, np.full(k, step, dtype=np.int64)])
        self.last_step = np.concatenate([self.last_step, np.full(k, step, dtype=np.int64)])
        self.confirmed = np.concatenate([self.confirmed, np.zeros(k, dtype=bool)])
        self.dynamic = np.concatenate([self.dynamic, np.zeros(k, dtype=bool)])
        ri = np.linalg.inv(c)
        self.info_sum = np.concatenate([self.info_sum, ri])
        self.info_z = np.vstack([self.info_z, np.einsum("kij,kj->ki", ri, m)])
        self.z_info_z = np.concatenate([self.z_info_z, np.einsum("ki,kij,kj->k", m, ri, m)])
        self.info_t = np.concatenate([self.info_t, ri * step])
        self.info_tt = np.concatenate([self.info_tt, ri * step**2])
        self.info_tz = np.vstack([self.info_tz, np.einsum("kij,kj->ki", ri, m) * step])
        self._apply_rule()
        return new

    def fuse(self, index: ArrayLike, points: ArrayLike, covs: ArrayLike, step: int) -> None:
        """Fuse sightings ``points`` (K,2) with covariances (K,2,2) into landmarks at row ``index`` (K,) (distinct).

        Information-form update: ``P' = (P^-1 + R^-1)^-1``, ``m' = P' (P^-1 m + R^-1 z)``.
        """
        idx = np.asarray(index, dtype=np.int64).reshape(-1)
        if len(np.unique(idx)) != len(idx):
            raise ValueError("LandmarkMap.fuse: each landmark can take at most one sighting per call")
        z = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        r = np.asarray(covs, dtype=np.float64).reshape(-1, 2, 2)
        pi = np.linalg.inv(self.covs[idx])
        ri = np.linalg.inv(r)
        p_new = np.linalg.inv(pi + ri)
        self.means[idx] = np.einsum("kij,kj->ki", p_new, np.einsum("kij,kj->ki", pi, self.means[idx])
                                    + np.einsum("kij,kj->ki", ri, z))
        self.covs[idx] = 0.5 * (p_new + p_new.transpose(0, 2, 1))
        self.counts[idx] += 1
        self.last_step[idx] = step
        self.info_sum[idx] += ri
        self.info_z[idx] += np.einsum("kij,kj->ki", ri, z)
        self.z_info_z[idx] += np.einsum("ki,kij,kj->k", z, ri, z)
        self.info_t[idx] += ri * step
        self.info_tt[idx] += ri * step**2
        self.info_tz[idx] += np.einsum("kij,kj->ki", ri, z) * step
        self._apply_rule()

    def consistency_chi2(self) -> Array:
        """Weighted residual sum of squares of each landmark's sightings about their weighted mean. Shape (N,).

        ``sum z^T W z - (sum W z)^T (sum W)^-1 (sum W z)``: 0 for one sighting, ~chi2(2(n-1)) for a static point.
        """
        if len(self) == 0:
            return np.zeros(0)
        b = np.linalg.solve(self.info_sum, self.info_z[:, :, None])[:, :, 0]
        return np.maximum(self.z_info_z - np.einsum("ki,ki->k", self.info_z, b), 0.0)

    def velocity_chi2(self) -> Array:
        """``b^T Cov(b)^-1 b`` for the weighted constant-velocity fit of each landmark's sightings (0 when fewer than
        2 distinct steps). Shape (N,)."""
        n = len(self)
        if n == 0:
            return np.zeros(0)
        # shift time to the landmark's first sighting: same fit, far better conditioned than absolute step numbers
        ok = self.last_step > self.first_step
        out = np.zeros(n)
        if not ok.any():
            return out
        t0 = self.first_step[ok].astype(np.float64)[:, None, None]
        w, wt = self.info_sum[ok], self.info_t[ok] - t0 * self.info_sum[ok]
        wtt = self.info_tt[ok] - 2 * t0 * self.info_t[ok] + t0**2 * self.info_sum[ok]
        gz, gtz = self.info_z[ok], self.info_tz[ok] - t0[:, :, 0] * self.info_z[ok]
        h = np.block([[w, wt], [wt, wtt]])
        g = np.concatenate([gz, gtz], axis=1)
        sol = np.linalg.solve(h, g[:, :, None])[:, :, 0]
        b = sol[:, 2:]
        cov_b = np.linalg.inv(h)[:, 2:, 2:]
        out[ok] = np.einsum("ki,kij,kj->k", b, np.linalg.inv(cov_b), b)
        return out

    def _apply_rule(self) -> None:
        cfg = self.config
        dof = 2 * np.maximum(self.counts - 1, 1)
        limit = chi2.ppf(cfg.consistency_probability, dof)
        moving = (self.counts > 1) & (self.consistency_chi2() > limit)
        moving |= (self.counts > 2) & (self.velocity_chi2() > chi2.ppf(cfg.velocity_probability, 2))
        self.dynamic |= ~self.confirmed & moving
        self.confirmed |= ~self.dynamic & (self.counts >= cfg.min_sightings)

    def prune(self, step: int) -> int:
        """Drop tentative and dynamic landmarks unseen for ``max_unseen_steps``; returns how many were dropped."""
        stale = ~self.confirmed & (step - self.last_step >= self.config.max_unseen_steps)
        keep = ~stale
        for name in ("ids", "means", "covs", "counts", "first_step", "last_step", "confirmed", "dynamic", "info_sum",
                     "info_z", "z_info_z", "info_t", "info_tt", "info_tz"):
            setattr(self, name, getattr(self, name)[keep])
        return int(stale.sum())

    def estimate_view(self) -> tuple[Array, Array, IntArray]:
        """Confirmed landmarks only: means (L,2), covariances (L,2,2), ids (L,) (the Estimate fields)."""
        c = self.confirmed
        return self.means[c].copy(), self.covs[c].copy(), self.ids[c].copy()


def sighting_covariance(pose: ArrayLike, z: ArrayLike, sensor: SensorConfig) -> Array:
    """World-frame covariance of landmark positions from range-bearing measurements (pose taken as exact).

    Shapes: pose (3,), z (K,2) -> (K,2,2): ``G_z R G_z^T``.
    """
    zz = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    _, gz = range_bearing_inverse_jacobians(np.broadcast_to(np.asarray(pose, dtype=np.float64), (len(zz), 3)), zz)
    return gz @ sensor.covariance @ gz.transpose(0, 2, 1)


class PersistentLandmarkMapper:
    """Build a :class:`LandmarkMap` from poses and range-bearing observations with the persistence rule.

    Association is by optimal assignment (Hungarian) on Mahalanobis distance within the chi-square gate; it never
    reads the source's landmark ids, so moving objects (id -2) get no special treatment: the rule must catch them.
    """

    def __init__(self, sensor: SensorConfig | None = None, config: PersistenceConfig | None = None) -> None:
        self.sensor = sensor or SensorConfig()
        self.map = LandmarkMap(config)
        self._gate = chi2_gate(self.map.config.gate_probability, 2)

    def observe(self, pose: ArrayLike, z: ArrayLike, step: int) -> IntArray:
        """Integrate observations ``z`` (K,2) [range, bearing] taken at ``pose`` (3,); returns the landmark id given
        to each observation (K,)."""
        zz = np.asarray(z, dtype=np.float64).reshape(-1, 2)
        out = np.full(len(zz), -1, dtype=np.int64)
        if len(zz) == 0:
            self.map.prune(step)
            return out
        pts = range_bearing_inverse(np.broadcast_to(np.asarray(pose, dtype=np.float64), (len(zz), 3)), zz)
        r = sighting_covariance(pose, zz, self.sensor)
        m = self.map
        assigned = np.zeros(len(zz), dtype=bool)
        if len(m):
            d = pts[:, None, :] - m.means[None]
            s = r[:, None] + m.covs[None]
            d2 = np.einsum("kni,knij,knj->kn", d, np.linalg.inv(s), d)
            cost = np.where(d2 < self._gate, d2, 1e6)
            rows, cols = linear_sum_assignment(cost)
            ok = cost[rows, cols] < self._gate
            rows, cols = rows[ok], cols[ok]
            m.fuse(cols, pts[rows], r[rows], step)
            out[rows] = m.ids[cols]
            assigned[rows] = True
        if (~assigned).any():
            out[~assigned] = m.add(pts[~assigned], r[~assigned], step)
        m.prune(step)
        return out
