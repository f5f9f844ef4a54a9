"""Landmark tracks: the one bookkeeping of which landmarks are tentative, confirmed, missed, dynamic or pruned.

Every back end (EKF-SLAM, FastSLAM per particle, online graph SLAM) and the persistent landmark map keep their
landmarks' life cycle in a :class:`LandmarkTracks`: stacked arrays with a batch axis first, shape (M, K) -- M
independent maps (FastSLAM's particles; 1 for the others), K landmark slots each. A slot with ``hits == 0`` is empty.

The rules (:class:`TrackConfig`), all element-wise over (M, K):

* a new landmark is *tentative*; it is *confirmed* once it has been sighted ``confirm_after`` times (its first
  sighting included) and is not *dynamic*;
* a *miss* is a step in which the landmark is predicted well inside the sensor's view (:func:`in_view`) and was not
  sighted; ``misses`` counts consecutive misses (a sighting resets it). A sensor that reports a visible landmark
  only with probability p_d needs 1/p_d times more misses to say as much, so both limits are multiplied by
  ``misses_per_sighting`` (the sensor's 1/p_d). A tentative landmark is pruned after ``tentative_max_misses`` such
  steps, a confirmed one after ``confirmed_max_misses`` (0: never);
* ``miss_rule="evidence"`` replaces "consecutive" by an existence counter (the map management of Probabilistic
  Robotics ch. 13; the rule FastSLAM had before this tracker): a sighting does not reset ``misses`` but cancels
  ``round(1/p_d)`` of them (at least one), so ``misses`` is the net count
  ``misses_total - (hits - 1) round(1/p_d)`` and may go negative. A landmark sighted n times then survives about
  (n - 1)/p_d more misses than a new one: long-lived landmarks are not dropped by a run of misses (a detector that
  skips a tree for a while), while clutter sighted a few times still goes;
* persistence (``dynamic_test``, the rule that keeps moving objects out): every sighting also gives a world-frame
  point z_i with covariance R_i (pose taken as exact). The weighted residual sum of squares of a landmark's
  sightings about their weighted mean, ``sum_i (z_i - m)^T R_i^-1 (z_i - m)`` (kept as running sums), must stay
  below the chi-square quantile with ``2 (n - 1)`` degrees of freedom, and a constant-velocity fit
  ``z(t) = a + b t`` (t in steps since the first sighting) must not find a significant velocity,
  ``b^T Cov(b)^-1 b <= chi2_2(velocity_probability)``. A tentative landmark failing either test is *dynamic*: never
  confirmed, and pruned at once. A forklift drifts by about one noise sigma per step: the generic test is weak
  against it, the velocity test is not.

Costs: every operation is O(M K) array work (the persistence test solves stacked 4x4 systems for the sighted
slots only); no Python loop over particles or landmarks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, slots=True, kw_only=True)
class TrackConfig:
    """When a landmark is confirmed, when it is pruned, and what counts as a moving object."""

    confirm_after: int = 2
    """sightings (the first included) after which a landmark is confirmed (1: confirmed at once)."""
    tentative_max_misses: int = 3
    """a tentative landmark missed (predicted well in view, not sighted) this many consecutive steps is pruned
    (0: never). Multiplied by ``misses_per_sighting``."""
    confirmed_max_misses: int = 5
    """the same for confirmed landmarks (0: never prune a confirmed landmark)."""
    view_margin_m: float = 0.5
    """"well inside the view": predicted range <= max_range_m - margin, bearing inside the field of view by
    margin / range (the angle the margin subtends)."""
    misses_per_sighting: float = 1.0
    """1 / detection probability of the sensor (``SensorConfig.misses_per_sighting``); scales both miss limits."""
    miss_rule: str = "consecutive"
    """"consecutive": a sighting resets ``misses``; "evidence": a sighting cancels round(1/p_d) misses (an
    existence counter, see the module docstring). The limits apply to the (net) ``misses`` either way."""
    dynamic_test: bool = False
    """apply the persistence rule (consistency and constant-velocity tests) to tentative landmarks."""
    consistency_probability: float = 0.99
    """the sightings' residual chi-square above this quantile (2(n-1) dof) marks a landmark dynamic."""
    velocity_probability: float = 0.999
    """a fitted velocity above this chi-square(2) quantile marks a landmark dynamic."""

    def __post_init__(self) -> None:
        for name, low in (("confirm_after", 1), ("tentative_max_misses", 0), ("confirmed_max_misses", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low:
                raise ValueError(f"{name} must be an integer >= {low} (got {v!r})")
        if not (self.view_margin_m >= 0 and math.isfinite(self.view_margin_m)):
            raise ValueError(f"view_margin_m must be finite and >= 0 (got {self.view_margin_m!r})")
        if not (self.misses_per_sighting >= 1 and math.isfinite(self.misses_per_sighting)):
            raise ValueError(f"misses_per_sighting must be finite and >= 1 (got {self.misses_per_sighting!r})")
        if self.miss_rule not in ("consecutive", "evidence"):
            raise ValueError(f"miss_rule must be 'consecutive' or 'evidence' (got {self.miss_rule!r})")
        for name in ("consistency_probability", "velocity_probability"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"{name} must be in (0, 1) (got {getattr(self, name)!r})")

    @property
    def tentative_limit(self) -> int:
        """Consecutive misses that prune a tentative landmark (0: never), detection probability included."""
        return math.ceil(self.tentative_max_misses * self.misses_per_sighting)

    @property
    def misses_cancelled_by_sighting(self) -> int:
        """Misses a sighting cancels under ``miss_rule="evidence"``: round(1/p_d), at least one."""
        return max(1, round(self.misses_per_sighting))

    @property
    def confirmed_limit(self) -> int:
        """Consecutive misses that prune a confirmed landmark (0: never), detection probability included."""
        return math.ceil(self.confirmed_max_misses * self.misses_per_sighting)


def in_view(z_pred: ArrayLike, max_range_m: float, fov_rad: float, margin_m: float) -> BoolArray:
    """The in-view rule: predicted [range, bearing] (..., 2) well inside the sensor's range and field of view.

    ``range <= max_range_m - margin_m`` and ``|bearing| <= fov_rad / 2 - margin_m / range``. Shape (...,).
    """
    z = np.asarray(z_pred, dtype=np.float64)
    r, b = z[..., 0], z[..., 1]
    return (r <= max_range_m - margin_m) & (np.abs(b) <= 0.5 * fov_rad - margin_m / np.maximum(r, 1e-9))


_INT_FIELDS = ("hits", "misses", "first_step", "last_step")
_SUM_FIELDS = ("w", "wz", "zwz", "wt", "wtt", "wtz")


class LandmarkTracks:
    """Stacked track arrays, batch axis first. Shapes: hits, misses, first_step, last_step (M,K) int; dynamic (M,K)
    bool; with ``dynamic_test`` the running sums over sightings (t = step - first_step): w (M,K,2,2) = sum R^-1,
    wz (M,K,2) = sum R^-1 z, zwz (M,K) = sum z^T R^-1 z, wt = sum R^-1 t, wtt = sum R^-1 t^2, wtz = sum R^-1 t z
    (without it they have K = 0 and cost nothing).

    Slots are addressed by (row, col) index arrays; ``rows`` may be omitted when M = 1.
    """

    def __init__(self, config: TrackConfig | None = None, batch: int = 1, capacity: int = 0) -> None:
        self.config = config or TrackConfig()
        m, k = int(batch), int(capacity)
        if m < 1 or k < 0:
            raise ValueError(f"LandmarkTracks needs batch >= 1 and capacity >= 0 (got {batch}, {capacity})")
        for name in _INT_FIELDS:
            setattr(self, name, np.zeros((m, k), dtype=np.int64))
        self.dynamic = np.zeros((m, k), dtype=bool)
        ks = k if self.config.dynamic_test else 0
        self.w, self.wt, self.wtt = (np.zeros((m, ks, 2, 2)) for _ in range(3))
        self.wz, self.wtz = np.zeros((m, ks, 2)), np.zeros((m, ks, 2))
        self.zwz = np.zeros((m, ks))

    hits: IntArray
    misses: IntArray
    first_step: IntArray
    last_step: IntArray
    dynamic: BoolArray
    w: Array
    wz: Array
    zwz: Array
    wt: Array
    wtt: Array
    wtz: Array

    # ------------------------------------------------------------------ shape
    @property
    def batch(self) -> int:
        return int(self.hits.shape[0])

    @property
    def capacity(self) -> int:
        return int(self.hits.shape[1])

    def _fields(self) -> tuple[str, ...]:
        return (*_INT_FIELDS, "dynamic", *_SUM_FIELDS)

    def copy(self) -> LandmarkTracks:
        return self.select(np.arange(self.batch))

    def select(self, index: ArrayLike) -> LandmarkTracks:
        """Rows ``index`` (M',) as a new, independent set (fancy indexing copies): FastSLAM's resampling."""
        idx = np.asarray(index, dtype=np.int64)
        out = LandmarkTracks.__new__(LandmarkTracks)
        out.config = self.config
        for name in self._fields():
            setattr(out, name, getattr(self, name)[idx])
        return out

    def grow(self, capacity: int) -> None:
        """Empty slots appended up to ``capacity`` (never shrinks)."""
        k = self.capacity
        if capacity <= k:
            return
        for name in self._fields():
            a = getattr(self, name)
            if name in _SUM_FIELDS and not self.config.dynamic_test:
                continue
            out = np.zeros((a.shape[0], capacity, *a.shape[2:]), dtype=a.dtype)
            out[:, :k] = a
            setattr(self, name, out)

    def keep(self, mask: ArrayLike) -> None:
        """Keep only the slots (columns) where ``mask`` (K,) is True: for M = 1 maps stored in slot order."""
        keep = np.asarray(mask, dtype=bool)
        for name in self._fields():
            a = getattr(self, name)
            if a.shape[1]:
                setattr(self, name, a[:, keep])

    # ------------------------------------------------------------------ state
    @property
    def occupied(self) -> BoolArray:
        return self.hits > 0

    @property
    def confirmed(self) -> BoolArray:
        """(M,K) occupied, sighted ``confirm_after`` times and not dynamic."""
        return (self.hits >= self.config.confirm_after) & ~self.dynamic

    @property
    def tentative(self) -> BoolArray:
        return self.occupied & ~self.confirmed

    def _index(self, rows: ArrayLike | None, cols: ArrayLike) -> tuple[IntArray, IntArray]:
        c = np.asarray(cols, dtype=np.int64).reshape(-1)
        if rows is None:
            if self.batch != 1:
                raise ValueError("LandmarkTracks: rows are required when the batch has more than one map")
            return np.zeros_like(c), c
        return np.broadcast_to(np.asarray(rows, dtype=np.int64).reshape(-1), c.shape).copy(), c

    # ------------------------------------------------------------------ events
    def start(self, cols: ArrayLike, step: int, points: ArrayLike | None = None, covs: ArrayLike | None = None, *,
              rows: ArrayLike | None = None) -> None:
        """Start a landmark (one sighting) in each slot (rows, cols) (n,); ``points`` (n,2) / ``covs`` (n,2,2) are
        the sightings for the persistence rule (required with ``dynamic_test``)."""
        r, c = self._index(rows, cols)
        self.hits[r, c] = 1
        self.misses[r, c] = 0
        self.first_step[r, c] = step
        self.last_step[r, c] = step
        self.dynamic[r, c] = False
        if self.config.dynamic_test:
            for name in _SUM_FIELDS:
                getattr(self, name)[r, c] = 0.0
            self._accumulate(r, c, step, points, covs)

    def append(self, count: int, step: int, points: ArrayLike | None = None, covs: ArrayLike | None = None) -> None:
        """M = 1: ``count`` new landmarks in new slots at the end (shapes as :meth:`start`)."""
        k = self.capacity
        self.grow(k + int(count))
        self.start(np.arange(k, k + int(count)), step, points, covs)

    def sight(self, cols: ArrayLike, step: int, points: ArrayLike | None = None, covs: ArrayLike | None = None, *,
              rows: ArrayLike | None = None) -> None:
        """Landmarks (rows, cols) (n,) were sighted at ``step``: one more hit each (a slot listed twice counts
        twice), misses reset (``miss_rule="evidence"``: reduced by round(1/p_d) per sighting); then the persistence
        rule for the tentative ones."""
        r, c = self._index(rows, cols)
        was_tentative = self.hits[r, c] < self.config.confirm_after  # a confirmed landmark stays confirmed
        np.add.at(self.hits, (r, c), 1)
        if self.config.miss_rule == "evidence":
            np.subtract.at(self.misses, (r, c), self.config.misses_cancelled_by_sighting)
        else:
            self.misses[r, c] = 0
        self.last_step[r, c] = step
        if self.config.dynamic_test:
            self._accumulate(r, c, step, points, covs)
            self._apply_persistence(r[was_tentative], c[was_tentative])

    def miss(self, in_view_mask: ArrayLike, step: int) -> None:
        """One more miss (consecutive, or net with ``miss_rule="evidence"``) for every occupied slot where
        ``in_view_mask`` (M,K) holds and that was not sighted (or started) at ``step``."""
        v = np.asarray(in_view_mask, dtype=bool) & self.occupied & (self.last_step < step)
        self.misses += v

    def prune_mask(self) -> BoolArray:
        """(M,K) slots to prune: tentative or confirmed landmarks over their miss limit, and dynamic ones."""
        cfg = self.config
        conf = self.confirmed
        drop = self.occupied & self.dynamic
        if cfg.tentative_limit:
            drop |= self.occupied & ~conf & (self.misses >= cfg.tentative_limit)
        if cfg.confirmed_limit:
            drop |= conf & (self.misses >= cfg.confirmed_limit)
        return drop

    def free(self, mask: ArrayLike) -> None:
        """Empty the slots where ``mask`` (M,K) holds (their data stay; ``hits == 0`` marks them free)."""
        m = np.asarray(mask, dtype=bool)
        self.hits[m] = 0
        self.misses[m] = 0
        self.dynamic[m] = False

    # ------------------------------------------------------------------ persistence
    def _accumulate(self, r: IntArray, c: IntArray, step: int, points: ArrayLike | None,
                    covs: ArrayLike | None) -> None:
        if points is None or covs is None:
            raise ValueError("LandmarkTracks: dynamic_test needs the sightings' points and covariances")
        z = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        ri = np.linalg.inv(np.asarray(covs, dtype=np.float64).reshape(-1, 2, 2))
        t = (step - self.first_step[r, c]).astype(np.float64)
        rz = np.einsum("kij,kj->ki", ri, z)
        np.add.at(self.w, (r, c), ri)
        np.add.at(self.wz, (r, c), rz)
        np.add.at(self.zwz, (r, c), np.einsum("ki,ki->k", z, rz))
        np.add.at(self.wt, (r, c), ri * t[:, None, None])
        np.add.at(self.wtt, (r, c), ri * (t * t)[:, None, None])
        np.add.at(self.wtz, (r, c), rz * t[:, None])

    def consistency_chi2(self, rows: ArrayLike | None = None, cols: ArrayLike | None = None) -> Array:
        """Weighted residual sum of squares of each landmark's sightings about their weighted mean, for the slots
        (rows, cols) (all slots, flattened row-major, when omitted): ``sum z^T W z - (sum W z)^T (sum W)^-1 (sum W
        z)``; 0 for one sighting, ~chi2(2(n-1)) for a static point."""
        r, c = self._all(rows, cols)
        if not r.size:
            return np.zeros(0)
        b = np.linalg.solve(self.w[r, c], self.wz[r, c][:, :, None])[:, :, 0]
        return np.maximum(self.zwz[r, c] - np.einsum("ki,ki->k", self.wz[r, c], b), 0.0)

    def velocity_chi2(self, rows: ArrayLike | None = None, cols: ArrayLike | None = None) -> Array:
        """``b^T Cov(b)^-1 b`` of the weighted constant-velocity fit of each landmark's sightings (0 when they span
        a single step). Slots as :meth:`consistency_chi2`."""
        r, c = self._all(rows, cols)
        out = np.zeros(r.size)
        ok = self.last_step[r, c] > self.first_step[r, c]
        if not ok.any():
            return out
        r, c = r[ok], c[ok]
        h = np.block([[self.w[r, c], self.wt[r, c]], [self.wt[r, c], self.wtt[r, c]]])
        g = np.concatenate([self.wz[r, c], self.wtz[r, c]], axis=1)
        h_inv = np.linalg.inv(h)
        b = np.einsum("kij,kj->ki", h_inv, g)[:, 2:]
        out[ok] = np.einsum("ki,kij,kj->k", b, np.linalg.inv(h_inv[:, 2:, 2:]), b)
        return out

    def _all(self, rows: ArrayLike | None, cols: ArrayLike | None) -> tuple[IntArray, IntArray]:
        if cols is None:
            r, c = np.nonzero(np.ones(self.hits.shape, dtype=bool))
            return r.astype(np.int64), c.astype(np.int64)
        return self._index(rows, cols)

    def _apply_persistence(self, r: IntArray, c: IntArray) -> None:
        """Mark dynamic the landmarks (r, c) (tentative before this sighting) whose sightings fail either test."""
        cfg = self.config
        if not r.size:
            return
        n = self.hits[r, c]
        limit = chi2.ppf(cfg.consistency_probability, 2 * np.maximum(n - 1, 1))
        moving = (n > 1) & (self.consistency_chi2(r, c) > limit)
        moving |= (n > 2) & (self.velocity_chi2(r, c) > chi2.ppf(cfg.velocity_probability, 2))
        self.dynamic[r[moving], c[moving]] = True
