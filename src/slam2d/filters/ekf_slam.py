"""EKF-SLAM: one Gaussian over the robot pose and every landmark, with range-bearing updates and a GPS fix.

The maths lives in the pure kernels of :mod:`slam2d.filters.ekf_kernels` (state layout, costs, the covariance
guard; re-exported here); this module is the estimator shell. The shell either re-raises a
:class:`CovarianceError` (``covariance_guard="raise"``) or repairs P with :func:`repair_covariance` (counted in the
snapshot's ``covariance_repairs``) and retries the update once (``covariance_guard="repair"``, the default).

Landmark bookkeeping (tentative / confirmed / missed / pruned, the in-view rule, detection-probability scaling)
is the shared :class:`~slam2d.association.tracks.LandmarkTracks` with one map (M = 1), its slots in state order.

Bad observations (NaN/inf range or bearing, negative range) raise ``ValueError`` naming the step and observation
(``bad_observation="raise"``, the default), or are dropped and counted (``bad_observation="drop"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from slam2d.association import CLUTTER, NEW, AssociationConfig, AssociationResult, Candidates, resolve_method
from slam2d.association.gating import gate_thresholds, innovations, mahalanobis_matrix
from slam2d.association.tracks import LandmarkTracks, TrackConfig, in_view
from slam2d.config import check_nonnegative, check_positive
from slam2d.estimator import Diagnostics, Estimate, EstimatorLifecycle
from slam2d.filters.ekf_kernels import (
    POSE_DIM,
    CovarianceError,
    augment_linearized,
    augment_state,
    augment_state_batch,
    check_observations,
    ekf_predict,
    ekf_predict_linearized,
    ekf_update,
    ekf_update_position,
    ekf_update_range_bearing,
    ekf_update_range_bearing_batch,
    ekf_update_range_bearing_batches,
    odometry_covariance_scalar,
    odometry_scalar,
    predict_landmarks,
    range_bearing_scalar,
    remove_landmarks,
    repair_covariance,
    run_association,
)
from slam2d.log import Observations, Step
from slam2d.models.motion import MotionNoise
from slam2d.models.sensors import SensorConfig, range_bearing, range_bearing_inverse, range_bearing_inverse_jacobians

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = [
    "EKFSLAM",
    "POSE_DIM",
    "CovarianceError",
    "EKFConfig",
    "augment_linearized",
    "augment_state",
    "augment_state_batch",
    "check_observations",
    "ekf_predict",
    "ekf_predict_linearized",
    "ekf_update",
    "ekf_update_position",
    "ekf_update_range_bearing",
    "ekf_update_range_bearing_batch",
    "ekf_update_range_bearing_batches",
    "odometry_covariance_scalar",
    "odometry_scalar",
    "predict_landmarks",
    "range_bearing_scalar",
    "remove_landmarks",
    "repair_covariance",
    "run_association",
]
#: observations per joint update on steps with many of them (a few dozen is fastest: see the kernel's cost)
UPDATE_BATCH = 64


# ---------------------------------------------------------------------------------------------------- estimator
@dataclass(frozen=True, slots=True, kw_only=True)
class EKFConfig:
    """EKF-SLAM settings."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise assumed by the filter (filled from the log's metadata by the registry)."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """range-bearing sensor assumed by the filter (noise, range, field of view; filled from the log's metadata)."""
    association: AssociationConfig = field(default_factory=lambda: AssociationConfig(method="auto"))
    """data association. Default ``auto``: the source's ids when the data carry them, else
    ``association.AUTO_WITHOUT_IDS`` (see :func:`slam2d.association.resolve_method`)."""
    motion_noise_scale: float = 1.0
    """multiplies every motion-noise variance the filter assumes (< 1: an overconfident filter)."""
    confirm_after: int = 2
    """a landmark is tentative until it has been associated this many times (counting its first sighting)."""
    tentative_max_misses: int = 3
    """a tentative landmark predicted well inside the sensor's view this many consecutive steps without a match is
    removed (0: never)."""
    confirmed_max_misses: int = 5
    """the same rule for confirmed landmarks (0: never remove a confirmed landmark); removes e.g. landmarks made
    from moving objects. Both miss counts are divided by the sensor's ``detection_prob``; with ``known``
    association confirmed landmarks are never removed (their ids come from the source)."""
    view_margin_m: float = 0.5
    """"well inside the view" means predicted range <= max_range_m - view_margin_m (and inside the field of view)."""
    dynamic_test: bool = False
    """the persistence rule of :class:`~slam2d.association.tracks.TrackConfig`: a tentative landmark whose sightings
    do not agree with one fixed point (chi-square consistency or a significant constant velocity) is dropped."""
    candidate_margin_m: float = 1.0
    """landmarks predicted within max_range_m + this (m) of the robot are association candidates."""
    use_gps: bool = True
    """apply GPS fixes when a step carries one."""
    gps_std_m: float = 0.5
    """GPS noise standard deviation per axis assumed by the filter (m)."""
    bad_observation: Literal["raise", "drop"] = "raise"
    """NaN/inf or negative-range observations: raise ValueError naming the step, or drop them (counted)."""
    covariance_guard: Literal["raise", "repair"] = "repair"
    """when the covariance guard fires (see module docstring): re-raise, or repair P and retry once (counted)."""
    batch_from: int = 32
    """a step with at least this many matched observations applies them in joint updates of up to
    ``UPDATE_BATCH`` (in observation order, each linearised at the mean the previous one left;
    :func:`ekf_update_range_bearing_batches`): a few BLAS calls per batch instead of one pass over P per observation,
    many times faster with hundreds of landmarks in view. Smaller steps get one update per observation (0: always
    batch; a huge number: never)."""
    snapshot_full_cov: bool = False
    """put the full covariance P (a copy, O(N^2)) in the snapshot as ``full_cov``."""

    def __post_init__(self) -> None:
        from slam2d.config import _coerce

        _coerce(self.bad_observation, Literal["raise", "drop"], "EKFConfig.bad_observation")
        _coerce(self.covariance_guard, Literal["raise", "repair"], "EKFConfig.covariance_guard")
        check_positive(self, "motion_noise_scale", "gps_std_m")
        if self.batch_from < 0:
            raise ValueError(f"EKFConfig.batch_from must be >= 0 (got {self.batch_from})")
        check_nonnegative(self, "view_margin_m", "candidate_margin_m")
        try:
            self.tracks(known=False)
        except ValueError as e:
            raise ValueError(f"EKFConfig.{e}") from None

    def tracks(self, *, known: bool) -> TrackConfig:
        """The landmark-track rules these settings mean; with ``known`` ids a confirmed landmark is never pruned."""
        return TrackConfig(confirm_after=self.confirm_after, tentative_max_misses=self.tentative_max_misses,
                           confirmed_max_misses=0 if known else self.confirmed_max_misses,
                           view_margin_m=self.view_margin_m, misses_per_sighting=self.sensor.misses_per_sighting,
                           dynamic_test=self.dynamic_test)


class EKFSLAM(EstimatorLifecycle):
    """EKF-SLAM estimator (implements the estimator protocol); the math lives in the module's pure kernels.

    Per step: predict; GPS fix (if any); associate the observations against the landmarks near the robot;
    updates in observation order (joint updates of ``UPDATE_BATCH`` when there are many); then the new landmarks
    are added (in observation order); then landmarks missed too often while in view are removed.
    """

    def __init__(self, config: EKFConfig | None = None) -> None:
        self.config = config or EKFConfig()
        self._noise = self.config.motion if self.config.motion_noise_scale == 1.0 else \
            self.config.motion.scaled(self.config.motion_noise_scale)
        self._R = self.config.sensor.covariance
        self._R_gps = np.eye(2) * self.config.gps_std_m**2
        self._reset_state(np.zeros(3))
        self._rng = np.random.default_rng(0)

    def _reset_state(self, pose: Array) -> None:
        self._mu = np.asarray(pose, dtype=np.float64).copy()
        self._P = np.zeros((POSE_DIM, POSE_DIM))
        self._ids = np.zeros(0, dtype=np.int64)
        self._assoc = self.config.association
        self._tracks = LandmarkTracks(self.config.tracks(known=self._assoc.method == "known"))
        self._desc: Array | None = None
        self._next_id = 0
        self._last_assoc = np.zeros(0, dtype=np.int64)
        self._dropped = 0
        self._repairs = 0
        self._removed = 0

    # ------------------------------------------------------------------ protocol
    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        pose = np.asarray(initial_pose, dtype=np.float64)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"initial_pose must be 3 finite numbers, got {initial_pose!r}")
        self._reset_state(pose)
        self._rng = rng
        self._lifecycle_reset()

    def step(self, step: Step) -> None:
        self._check_step()
        u = np.asarray(step.odometry, dtype=np.float64)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise ValueError(f"step {step.index}: odometry must be 3 finite numbers, got {step.odometry!r}")
        self._mu, self._P = ekf_predict(self._mu, self._P, u, self._noise, inplace=True)
        if self.config.use_gps and step.gps is not None:
            gps = np.asarray(step.gps, dtype=np.float64)
            if gps.shape != (2,) or not np.all(np.isfinite(gps)):
                raise ValueError(f"step {step.index}: gps must be 2 finite numbers, got {step.gps!r}")
            self._guarded(lambda: ekf_update_position(self._mu, self._P, gps, self._R_gps, inplace=True))
        obs, keep = self._clean(step)
        if self._assoc.method == "auto" and len(obs):
            self._assoc = resolve_method(self._assoc, bool(np.any(obs.landmark_id >= 0)))
            self._tracks.config = self.config.tracks(known=self._assoc.method == "known")
        self._observe(obs, step.index)
        if keep is not None:  # report per original observation; dropped ones as CLUTTER
            full = np.full(keep.shape[0], CLUTTER, dtype=np.int64)
            full[keep] = self._last_assoc
            self._last_assoc = full

    def estimate(self) -> Estimate:
        self._check_ready()
        n_l = self._ids.shape[0]
        lm = self._mu[POSE_DIM:].reshape(n_l, 2)
        idx = (POSE_DIM + 2 * np.arange(n_l)[:, None] + np.arange(2)).reshape(n_l, 2)
        covs = self._P[idx[:, :, None], idx[:, None, :]] if n_l else np.zeros((0, 2, 2))
        conf = self._tracks.confirmed[0]
        return Estimate(pose=self._mu[:POSE_DIM].copy(), pose_cov=self._P[:POSE_DIM, :POSE_DIM].copy(),
                        landmarks=lm[conf].copy(), landmark_covs=np.ascontiguousarray(covs[conf]),
                        landmark_ids=self._ids[conf].copy(), state_dim=int(self._mu.shape[0]),
                        association=self._last_assoc.copy(), tentative_landmarks=lm[~conf].copy(),
                        tentative_ids=self._ids[~conf].copy(),
                        full_cov=self._P.copy() if self.config.snapshot_full_cov else None,
                        diagnostics=Diagnostics(dropped_observations=self._dropped, covariance_repairs=self._repairs,
                                                landmarks_removed=self._removed))

    def finalize(self) -> None:
        self._lifecycle_finalize()

    @property
    def association_method(self) -> str:
        """The association method in use (``auto`` until the first step with observations resolves it)."""
        return self._assoc.method

    @property
    def state(self) -> tuple[Array, Array, IntArray]:
        """Copies of (mu, P, landmark ids in state order), for tests and the lab."""
        return self._mu.copy(), self._P.copy(), self._ids.copy()

    # ------------------------------------------------------------------ internals
    def _guarded(self, update: Any) -> None:
        """Run an in-place update under the covariance guard (see module docstring)."""
        try:
            self._mu, self._P = update()
        except CovarianceError as e:
            if self.config.covariance_guard == "raise":
                raise
            self._P = repair_covariance(self._P)
            self._repairs += 1
            if not e.applied:
                self._mu, self._P = update()

    def _update_batches(self, js: IntArray, z: Array) -> None:
        """Joint updates of ``UPDATE_BATCH`` observations in order (:func:`ekf_update_range_bearing_batches`), each
        under the covariance guard exactly as :meth:`_guarded` runs one: repair, retry a batch not yet applied once,
        then go on with the next batch."""
        start = 0
        while start < js.size:
            try:
                self._mu, self._P = ekf_update_range_bearing_batches(self._mu, self._P, js[start:], z[start:], self._R,
                                                                     batch=UPDATE_BATCH)
                return
            except CovarianceError as e:
                if self.config.covariance_guard == "raise":
                    raise
                self._P = repair_covariance(self._P)
                self._repairs += 1
                failed = start + e.done
                start = failed + UPDATE_BATCH
                if not e.applied:
                    self._mu, self._P = ekf_update_range_bearing_batch(self._mu, self._P, js[failed:start],
                                                                       z[failed:start], self._R, inplace=True)

    def _clean(self, step: Step) -> tuple[Observations, NDArray[np.bool_] | None]:
        """The step's valid observations, and the mask of kept ones (None when all are valid)."""
        obs = step.observations
        r, b = np.asarray(obs.range_m, dtype=np.float64), np.asarray(obs.bearing_rad, dtype=np.float64)
        bad = ~np.isfinite(r) | ~np.isfinite(b) | (r < 0)
        if not np.any(bad):
            return obs, None
        if self.config.bad_observation == "raise":
            check_observations(r, b, where=f"step {step.index}: observation")
        self._dropped += int(np.sum(bad))
        return obs.subset(~bad), ~bad

    def _candidates(self, obs: Observations) -> tuple[Candidates, IntArray, NDArray[np.bool_]]:
        """Candidates for association, their state indices, and which landmarks are well inside the view."""
        sensor, n_l = self.config.sensor, self._ids.shape[0]
        lms = self._mu[POSE_DIM:].reshape(n_l, 2)
        z_all = range_bearing(self._mu[:POSE_DIM], lms).reshape(n_l, 2)
        half_fov = 0.5 * sensor.fov_rad
        view = in_view(z_all, sensor.max_range_m, sensor.fov_rad, self.config.view_margin_m)
        if not len(obs):  # nothing to associate: the step's misses need only the view, not the predictions
            return Candidates(self._ids[:0], np.zeros((0, 2)), np.zeros((0, 2, 2))), np.zeros(0, np.int64), view
        if self._assoc.method == "known":
            # known ids must see every landmark in the state, or a drifted one would be duplicated
            js = np.arange(n_l)
            z_pred, S, sj = predict_landmarks(self._mu, self._P, js, self._R)
        else:
            reach = sensor.max_range_m + self.config.candidate_margin_m
            ang_margin = self.config.candidate_margin_m / np.maximum(z_all[:, 0], 1e-9)
            near = (z_all[:, 0] <= reach) & (np.abs(z_all[:, 1]) <= half_fov + ang_margin)
            js = np.flatnonzero(near)
            z_pred, S, sj = predict_landmarks(self._mu, self._P, js, self._R, joint=True)
        desc = None if self._desc is None or obs.descriptor is None else self._desc[js]
        return Candidates(self._ids[js], z_pred, S, sj, desc), js, view

    def _observe(self, obs: Observations, index: int) -> None:
        k = len(obs)
        if k == 0 and self._ids.shape[0] == 0:
            self._last_assoc = np.zeros(0, dtype=np.int64)
            return
        cands, js, view = self._candidates(obs)
        try:
            result = run_association(obs, cands, self._assoc, self._rng) if k else \
                AssociationResult(np.zeros(0, dtype=np.int64), np.zeros(0))
        except CovarianceError:
            if self.config.covariance_guard == "raise":
                raise
            self._P = repair_covariance(self._P)
            self._repairs += 1
            cands, js, view = self._candidates(obs)
            result = run_association(obs, cands, self._assoc, self._rng)
        assign = np.asarray(result.assignment, dtype=np.int64)
        self._last_assoc = assign.copy()
        z = obs.z
        # --- updates, in observation order
        pos = {int(i): p for p, i in enumerate(self._ids)}
        used = np.flatnonzero(assign >= 0)
        sighted = np.array([pos[int(a)] for a in assign[used]], dtype=np.int64)
        if used.size >= max(self.config.batch_from, 2):
            self._update_batches(sighted, z[used])
        else:
            for o, j in zip(used, sighted, strict=True):  # one O(N^2) update per observation
                self._guarded(lambda j=j, o=o: ekf_update_range_bearing(self._mu, self._P, j, z[o], self._R,
                                                                         inplace=True))
        if obs.descriptor is not None and self._desc is not None:
            count = self._tracks.hits[0].copy()
            for o, j in zip(used, sighted, strict=True):  # running mean, in observation order
                count[j] += 1
                self._desc[j] += (obs.descriptor[o] - self._desc[j]) / count[j]
        self._tracks.sight(sighted, index, *self._sightings(z[used]))
        # a miss is negative information: nothing was seen where the landmark should be. An observation inside the
        # landmark's wide gate that was left unmatched (ambiguous) is not a miss, only an unused sighting
        seen = np.zeros(self._ids.shape[0], dtype=bool)
        if k and js.size and self._assoc.method != "known":
            near = mahalanobis_matrix(innovations(z, cands.z_pred), cands.S) <= gate_thresholds(self._assoc)[1]
            seen[js] = near.any(axis=0)
        self._tracks.miss((view & ~seen)[None], index)
        # --- new landmarks (a repeated id in one scan is added once)
        new = np.flatnonzero(assign == NEW)
        if self._assoc.method == "known" and new.size:
            _, first = np.unique(obs.landmark_id[new], return_index=True)
            new = new[np.sort(first)]
        if new.size:
            self._mu, self._P = augment_state_batch(self._mu, self._P, z[new], self._R)
            if self._assoc.method == "known":
                ids = obs.landmark_id[new].astype(np.int64)
            else:
                ids = self._next_id + np.arange(new.size, dtype=np.int64)
                self._next_id += new.size
            self._ids = np.concatenate([self._ids, ids])
            self._tracks.append(new.size, index, *self._sightings(z[new]))
            # descriptors are kept only when the source gives them from the first landmark on
            n_before = self._ids.shape[0] - new.size
            if obs.descriptor is not None and (self._desc is not None or n_before == 0):
                d = np.asarray(obs.descriptor[new], dtype=np.float64)
                self._desc = d.copy() if self._desc is None else np.vstack([self._desc, d])
            elif self._desc is not None:
                self._desc = np.vstack([self._desc, np.full((new.size, self._desc.shape[1]), np.nan)])
        self._prune()

    def _sightings(self, z: Array) -> tuple[Array | None, Array | None]:
        """World points of observations z (k,2) from the current pose and their covariances G_z R G_z^T (pose taken
        as exact), for the tracks' persistence rule; (None, None) when the rule is off."""
        if not self.config.dynamic_test:
            return None, None
        pose = np.broadcast_to(self._mu[:POSE_DIM], (len(z), POSE_DIM))
        _, gz = range_bearing_inverse_jacobians(pose, z)
        return range_bearing_inverse(pose, z), gz @ self._R @ np.swapaxes(gz, 1, 2)

    def _prune(self) -> None:
        """Remove the landmarks the tracks say are over their miss limit (or dynamic). With known association a
        confirmed landmark stays (its id comes from the source, see :meth:`EKFConfig.tracks`)."""
        drop = self._tracks.prune_mask()[0]
        if not np.any(drop):
            return
        self._mu, self._P = remove_landmarks(self._mu, self._P, np.flatnonzero(drop))
        keep = ~drop
        self._ids = self._ids[keep]
        self._tracks.keep(keep)
        if self._desc is not None:
            self._desc = self._desc[keep]
        self._removed += int(np.sum(drop))
