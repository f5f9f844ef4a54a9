"""The landmark map: means, covariances, ids and observation counts, with a persistence rule for new landmarks.

:class:`LandmarkMap` holds fused means (N,2), covariances (N,2,2) and ids (N,); their life cycle (sighting counts,
first/last step seen, confirmed, dynamic) is the same :class:`~slam2d.association.tracks.LandmarkTracks` every
back end uses (one map, M = 1). Its :meth:`LandmarkMap.estimate_view` returns the confirmed landmarks only, in the
shapes of :class:`~slam2d.estimator.Estimate`.

Persistence (dynamic-object filtering) is the tracks' rule (see :mod:`slam2d.association.tracks`): a new landmark
starts *tentative* and is *confirmed* once it has been sighted ``min_sightings`` times while its sightings agree
with one fixed point (chi-square consistency) and show no significant constant velocity; a landmark failing either
test is *dynamic* and never confirmed. A forklift re-observed every step fails the velocity test. Tentative
landmarks not seen for ``max_unseen_steps`` steps are dropped (:meth:`LandmarkMap.prune`); the map has no notion
of "in view", so it never prunes by misses.

:class:`PersistentLandmarkMapper` is the simplest user of the map: given poses (true or estimated) and
range-bearing observations, it fuses each sighting into the nearest landmark within a Mahalanobis gate
(information-form update with the inverse-sensor-model covariance) or starts a new tentative landmark.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from slam2d.association.tracks import LandmarkTracks, TrackConfig
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
    """Stacked landmark arrays: ids (N,), means (N,2), covs (N,2,2), and their :class:`LandmarkTracks` (one map,
    slots in the same order) holding the sighting counts, first/last step, the ``dynamic`` flag and the running sums
    of the persistence rule. ``counts``, ``first_step``, ``last_step``, ``confirmed`` and ``dynamic`` (N,) are views of
    the tracks."""

    def __init__(self, config: PersistenceConfig | None = None) -> None:
        self.config = config or PersistenceConfig()
        cfg = self.config
        # the map never prunes by misses in view: stale tentative landmarks go by max_unseen_steps (prune)
        self.tracks = LandmarkTracks(TrackConfig(confirm_after=cfg.min_sightings, tentative_max_misses=0,
                                                 confirmed_max_misses=0, dynamic_test=True,
                                                 consistency_probability=cfg.consistency_probability,
                                                 velocity_probability=cfg.velocity_probability))
        self.ids = np.zeros(0, dtype=np.int64)
        self.means = np.zeros((0, 2))
        self.covs = np.zeros((0, 2, 2))
        self._next_id = 0

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def counts(self) -> IntArray:
        return self.tracks.hits[0]

    @property
    def first_step(self) -> IntArray:
        return self.tracks.first_step[0]

    @property
    def last_step(self) -> IntArray:
        return self.tracks.last_step[0]

    @property
    def confirmed(self) -> NDArray[np.bool_]:
        return self.tracks.confirmed[0]

    @property
    def dynamic(self) -> NDArray[np.bool_]:
        return self.tracks.dynamic[0]

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
        self.tracks.append(k, step, m, c)
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
        self.tracks.sight(idx, step, z, r)

    def consistency_chi2(self) -> Array:
        """Weighted residual sum of squares of each landmark's sightings about their weighted mean. Shape (N,).

        ``sum z^T W z - (sum W z)^T (sum W)^-1 (sum W z)``: 0 for one sighting, ~chi2(2(n-1)) for a static point.
        """
        return self.tracks.consistency_chi2()

    def velocity_chi2(self) -> Array:
        """``b^T Cov(b)^-1 b`` for the weighted constant-velocity fit of each landmark's sightings (0 when fewer than
        2 distinct steps). Shape (N,)."""
        return self.tracks.velocity_chi2()

    def prune(self, step: int) -> int:
        """Drop tentative and dynamic landmarks unseen for ``max_unseen_steps``; returns how many were dropped."""
        stale = ~self.confirmed & (step - self.last_step >= self.config.max_unseen_steps)
        keep = ~stale
        self.ids, self.means, self.covs = self.ids[keep], self.means[keep], self.covs[keep]
        self.tracks.keep(keep)
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
