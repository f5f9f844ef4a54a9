"""FastSLAM 1.0 and 2.0: a particle filter over robot paths with one small EKF per landmark per particle.

Every particle carries a pose, a log-weight and its own landmark map; all of them live in stacked arrays
(:class:`ParticleSet`) and every update below acts on all particles at once. The only Python loop in a step runs
over that step's few observations; each iteration is vectorised over particles (and, for maximum-likelihood
association, over each particle's candidate landmarks).

Versions (``FastSLAMConfig.version``):

* **1.0** (Montemerlo et al. 2002; Probabilistic Robotics sec. 13.3): the pose is sampled from the motion model
  (rot1-trans-rot2 noise, as the simulator draws it); the importance weight of a matched observation is
  ``N(z; h(x, mu), H_m Sigma H_m^T + R)``.
* **2.0** (Montemerlo et al. 2003; Probabilistic Robotics sec. 13.4): the pose is sampled from a Gaussian
  proposal that also conditions on the step's observations. Starting from the linearised motion model
  ``N(x_hat, V Q V^T)``, each matched observation updates the proposal with ``Q_z = H_m Sigma H_m^T + R`` as the
  measurement noise (a Kalman update, algebraically equal to the information form given in both references); the
  observation multiplies the weight by its predictive likelihood ``N(z; h(x_hat, mu), H_x P H_x^T + Q_z)``
  (the textbook's ``L`` matrix), taken under the proposal *before* that observation, so the product over a
  step's observations is the joint predictive likelihood. Then the pose is drawn from the final proposal and the
  landmark EKFs are updated at the drawn pose.

A new landmark multiplies the weight by ``new_landmark_likelihood`` (the textbook's ``p0``).

Association (``FastSLAMConfig.association.method``): ``"known"`` uses the source's ids (``Observations.landmark_id``;
negative ids -- clutter, moving objects -- are ignored) with one slot per id shared by all particles. **Any other
method means per-particle maximum likelihood**: each particle takes, for each observation, the landmark of
highest likelihood (the same likelihood that enters the weight), or starts a new landmark when that likelihood is
below ``new_landmark_likelihood``. The gate probabilities of :class:`AssociationConfig` are not used here:
per-particle ML is the textbook rule, and the threshold is the weight given to "new landmark".

Landmark bookkeeping (per-particle ML only): each particle's landmarks are tracks of one batched
:class:`~slam2d.association.tracks.LandmarkTracks` (M particles x K slots), the tracker EKF-SLAM and graph SLAM use:
tentative until sighted ``confirm_after`` times, pruned (slot freed) once its misses (steps predicted well inside
the view without a sighting) reach ``tentative_max_misses`` / ``confirmed_max_misses``, both limits scaled by 1/p_d.
FastSLAM's default ``miss_rule="evidence"`` is its existence counter (the map management of Probabilistic Robotics
ch. 13): a sighting cancels 1/p_d misses instead of resetting them, so a landmark sighted often survives long runs
of misses.
With known association every landmark is confirmed at its first sighting and nothing is pruned.

Cost: FastSLAM 1.0 with known ids updates a scan's landmarks in one (M, k) batch; otherwise one vectorised
iteration per observation. Per-particle ML looks once per step at every particle's whole map (a cheap O(M N)
distance pass that keeps the landmarks within sensor range + ``candidate_margin_m``), then scores each observation
exactly against the ``association_candidates`` nearest of them: O(M k) per step beyond that pass. Resampling
copies all maps: O(M N).

Weights are kept as logs, normalised by log-sum-exp; low-variance (systematic) resampling runs when
``N_eff = 1 / sum(w^2)`` falls below ``resample_threshold * particles``; it copies every per-particle array by
fancy indexing, so no two particles ever share memory. When every weight is zero (all log-weights -inf or NaN,
e.g. after an absurd outlier), the filter resets to uniform weights and counts it in ``diagnostics.weight_resets``.

Snapshot: ``pose`` is the weighted mean of the particle poses (circular mean for the heading) computed before
resampling; ``pose_cov`` the weighted sample covariance around it (``FastSLAMConfig.pose_cov="linearised"``: the
honest covariance of :mod:`slam2d.filters.fastslam_marginal` instead); the map (landmarks, covariances, ids) is the one
of the particle with the highest weight before resampling (followed through resampling to one of its copies):
its confirmed landmarks; its tentative ones are ``tentative_landmarks`` / ``tentative_ids``. Landmark ids are the
source's ids for known association, the particle's slot numbers otherwise.
``particles``: poses (M,3) and weights (M,) after this step, ``n_eff`` (before resampling) and ``resampled``;
``diagnostics.weight_resets`` (cumulative); ``state_dim`` (3 + 2 x landmarks of the shown particle, the size of one
particle's state, comparable to EKF-SLAM's); ``association`` (per observation: the shown particle's landmark id (a new
landmark's id included), or -1 for an ignored observation).

References: M. Montemerlo, S. Thrun, D. Koller, B. Wegbreit, "FastSLAM 2.0: An improved particle filtering
algorithm for simultaneous localization and mapping that provably converges", IJCAI 2003; S. Thrun, W. Burgard,
D. Fox, Probabilistic Robotics, ch. 13; J. Carpenter, P. Clifford, P. Fearnhead, "Improved particle filter for
nonlinear problems", 1999 (systematic resampling).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.association.base import AssociationConfig, resolve_method
from slam2d.association.tracks import TrackConfig, in_view
from slam2d.config import check_positive, check_probability
from slam2d.estimator import Diagnostics, Estimate, EstimatorLifecycle, ParticleView
from slam2d.filters.fastslam_marginal import LinearisedMarginal
from slam2d.filters.fastslam_particles import (
    ParticleSet,
    _congruence2,
    _logpdf2_sym,
    _observe,
    effective_sample_size,
    gaussian_logpdf2,
    landmark_init,
    landmark_update,
    motion_gaussian,
    normalize_log_weights,
    proposal_update,
    sample_gaussian_poses,
    sample_motion,
    systematic_resample,
)
from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle
from slam2d.log import Step
from slam2d.models.motion import MotionNoise
from slam2d.models.sensors import SensorConfig, range_bearing
from slam2d.sim.scenarios import MEMORY_ENV, memory_limit_mb

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]
#: bytes of one landmark slot of one particle (mean, covariance, track counters and sums), twice for resampling
_BYTES_PER_SLOT = 512.0

#: the particle set and kernels live in slam2d.filters.fastslam_particles; re-exported here
__all__ = ["FastSLAM", "FastSLAM2Config", "FastSLAMConfig", "ParticleSet", "effective_sample_size", "gaussian_logpdf2",
           "landmark_init", "landmark_update", "motion_gaussian", "normalize_log_weights", "proposal_update",
           "sample_gaussian_poses", "sample_motion", "systematic_resample", "weighted_pose_stats"]


# ----------------------------------------------------------------------------------------------------------------
# configuration


@dataclass(frozen=True, slots=True, kw_only=True)
class FastSLAMConfig:
    """FastSLAM settings (both versions)."""

    particles: int = 100
    """number of particles M (>= 1)."""
    version: int = 1
    """1: proposal = motion model (FastSLAM 1.0); 2: proposal conditioned on the observations (FastSLAM 2.0)."""
    resample_threshold: float = 0.5
    """resample when N_eff < resample_threshold * particles (0: never resample, 1: resample every step)."""
    new_landmark_likelihood: float = 1e-3
    """p0, a density in measurement space (1/(m rad)): per-particle ML starts a new landmark when the best match is
    less likely than this, and a new landmark multiplies the particle's weight by it."""
    initial_capacity: int = 16
    """landmark slots allocated per particle at reset; capacity doubles whenever it runs out."""
    candidate_margin_m: float = 2.0
    """per-particle ML only: landmarks farther than (largest observed range + this) from a particle are not
    considered as matches (m); keeps the per-observation cost proportional to the landmarks in view."""
    association_candidates: int = 4
    """per-particle ML only: the exact likelihood is evaluated for this many landmarks per particle and observation,
    those nearest (Euclidean, world frame) to where the particle places the observation."""
    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise assumed by the filter (filled from the log's metadata by the registry)."""
    motion_noise_scale: float = 1.0
    """multiplies every motion-noise variance the filter assumes (< 1: an overconfident filter)."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """range-bearing sensor assumed by the filter (filled from the log's metadata by the registry)."""
    association: AssociationConfig = field(default_factory=lambda: AssociationConfig(method="auto"))
    """method "known" uses the source's ids; any other method means per-particle maximum likelihood. Default
    ``auto``: known when the data carry ids (:func:`slam2d.association.resolve_method`)."""
    confirm_after: int = 2
    """per-particle ML: a landmark is tentative (not in the snapshot's map) until sighted this many times."""
    tentative_max_misses: int = 2
    """per-particle ML: a new landmark predicted well inside the view this many steps without a sighting is pruned
    (0: never); multiplied by 1/p_d (the sensor's ``misses_per_sighting``). With ``miss_rule="evidence"`` every
    sighting buys round(1/p_d) more misses."""
    confirmed_max_misses: int = 2
    """the same for confirmed landmarks (0: never)."""
    miss_rule: str = "evidence"
    """per-particle ML: the tracks' miss rule (:class:`~slam2d.association.tracks.TrackConfig`). The defaults
    (evidence, 2 / 2) are FastSLAM's existence counter from before the shared tracker (start ceil(2/p_d),
    +round(1/p_d) per sighting, -1 per miss; the start was 2 round(1/p_d); ``tests/unit/test_tracks.py``). Neither
    rule wins on the data used for choosing (below: ATE and map RMSE mixed, fewer duplicate landmarks with the
    evidence rule), so FastSLAM's behaviour is kept. Against the tracker's first FastSLAM defaults (consecutive
    misses, 3 / 0: a confirmed landmark is never pruned), one seed each, without ids; MRCLAM 7 robots 1-5, ATE /
    dead reckoning: FastSLAM 1.0 (300 particles) 0.09 0.37 0.46 0.36 0.49 (mean 0.35) against 0.22 0.51 0.42 0.29
    0.39 (0.37), 2.0 (100) 0.26 0.26 0.48 0.71 0.87 (0.52) against 0.22 0.42 0.58 0.31 0.76 (0.46); maps of 12-32
    landmarks for the 15 true ones (21-49 with 3 / 0: duplicates are never pruned), map RMSE better on 3 of the 10
    runs, worse on 5. Simulated (p_d = 1, no clutter; 5 seeds, mean ATE in m, 1.0 / 2.0): room 0.024 / 0.027
    against 0.023 / 0.026, warehouse 0.067 / 0.081 against 0.069 / 0.074, loop 0.45 / 0.70 against 0.40 / 0.58.
    Victoria Park was held out (README)."""
    pose_cov: str = "particles"
    """what ``pose_cov`` reports. ``"particles"``: the weighted particle covariance (cheap, and overconfident once
    the particles' paths coalesce). ``"linearised"``: known association only; EKF-SLAM's covariance recursion run at
    this filter's own estimate, plus the part of it the particle cloud no longer spans
    (:mod:`slam2d.filters.fastslam_marginal`); O(N^2) per observation like EKF-SLAM; the estimate is unchanged."""
    view_margin_m: float = 0.5
    """"well inside the view": predicted range <= max_range_m - view_margin_m (and inside the field of view)."""
    dynamic_test: bool = False
    """per-particle ML: the tracks' persistence rule (a tentative landmark whose sightings drift is pruned)."""

    def __post_init__(self) -> None:
        if isinstance(self.particles, bool) or not isinstance(self.particles, int) or self.particles < 1:
            raise ValueError(f"{type(self).__name__}.particles must be an integer >= 1 (got {self.particles!r})")
        if self.version not in (1, 2):
            raise ValueError(f"{type(self).__name__}.version must be 1 or 2 (got {self.version!r})")
        check_probability(self, "resample_threshold")
        if self.pose_cov not in ("particles", "linearised"):
            raise ValueError(f"{type(self).__name__}.pose_cov must be 'particles' or 'linearised' "
                             f"(got {self.pose_cov!r})")
        check_positive(self, "new_landmark_likelihood", "candidate_margin_m", "motion_noise_scale")
        if not isinstance(self.association_candidates, int) or self.association_candidates < 1:
            raise ValueError(f"{type(self).__name__}.association_candidates must be an integer >= 1 "
                             f"(got {self.association_candidates!r})")
        if not isinstance(self.initial_capacity, int) or self.initial_capacity < 1:
            raise ValueError(f"{type(self).__name__}.initial_capacity must be an integer >= 1 "
                             f"(got {self.initial_capacity!r})")
        # every particle allocates its landmark slots at reset (mean, covariance, track counters; copied when
        # resampling): refuse before the run rather than fail out of memory at its first step
        need_mb = self.particles * self.initial_capacity * _BYTES_PER_SLOT / 2**20
        if need_mb > memory_limit_mb():
            raise ValueError(f"{type(self).__name__}: particles={self.particles} x initial_capacity="
                             f"{self.initial_capacity} landmark slots would need about {need_mb:.3g} MB, over the "
                             f"limit of {memory_limit_mb():g} MB; set {MEMORY_ENV} to allow it")
        try:
            self.tracks(known=False)
        except ValueError as e:
            raise ValueError(f"{type(self).__name__}.{e}") from None

    def tracks(self, *, known: bool) -> TrackConfig:
        """The track rules: with known ids every landmark is confirmed at once and never pruned."""
        if known:
            return TrackConfig(confirm_after=1, tentative_max_misses=0, confirmed_max_misses=0)
        return TrackConfig(confirm_after=self.confirm_after, tentative_max_misses=self.tentative_max_misses,
                           confirmed_max_misses=self.confirmed_max_misses, view_margin_m=self.view_margin_m,
                           misses_per_sighting=self.sensor.misses_per_sighting, miss_rule=self.miss_rule,
                           dynamic_test=self.dynamic_test)


@dataclass(frozen=True, slots=True, kw_only=True)
class FastSLAM2Config(FastSLAMConfig):
    """The same settings with FastSLAM 2.0 as the default (registered as ``fastslam2``)."""

    version: int = 2
    """1: proposal = motion model (FastSLAM 1.0); 2: proposal conditioned on the observations (FastSLAM 2.0)."""


def weighted_pose_stats(poses: Array, weights: Array) -> tuple[Array, Array]:
    """Weighted mean pose (circular mean for theta) and weighted sample covariance. (M,3),(M,) -> (3,),(3,3)."""
    xy = weights @ poses[:, :2]
    th = math.atan2(float(weights @ np.sin(poses[:, 2])), float(weights @ np.cos(poses[:, 2])))
    mean = np.array([xy[0], xy[1], float(wrap_angle(th))])
    d = se2.local(mean, poses)
    cov = np.einsum("m,mi,mj->ij", weights, d, d)
    return mean, 0.5 * (cov + cov.T)


# ----------------------------------------------------------------------------------------------------------------
# the estimator


def _part(pts: Array | None, covs: Array | None, sel: BoolArray) -> tuple[Array | None, Array | None]:
    return (None, None) if pts is None or covs is None else (pts[sel], covs[sel])


class FastSLAM(EstimatorLifecycle):
    """FastSLAM 1.0 / 2.0 over range-bearing landmarks (implements the estimator protocol)."""

    def __init__(self, config: FastSLAMConfig | None = None) -> None:
        self.config = config or FastSLAMConfig()
        self._p: ParticleSet | None = None
        self._rng = np.random.default_rng(0)
        self._id_to_slot: dict[int, int] = {}
        self._slot_ids: list[int] = []
        self._best = 0
        self._pose = np.zeros(3)
        self._pose_cov = np.zeros((3, 3))
        self._n_eff = 0.0
        self._resampled = False
        self._weight_resets = 0
        self._assoc_out = np.zeros(0, dtype=np.int64)
        self._marginal: LinearisedMarginal | None = None
        self._r = self.config.sensor.covariance
        self._assoc = self.config.association
        self._t = 0
        #: FastSLAM 1.0 with known ids updates a scan's landmarks in one batch (tests switch it off to compare)
        self._batch_known = True

    @property
    def known(self) -> bool:
        return self._assoc.method == "known"

    @property
    def association_method(self) -> str:
        """The association method in use (``auto`` until the first step with observations resolves it)."""
        return self._assoc.method

    @property
    def particles(self) -> ParticleSet:
        """The current particle set (the live arrays; copy before mutating)."""
        if self._p is None:
            raise RuntimeError("FastSLAM.reset() must be called before use")
        return self._p

    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        pose = np.asarray(initial_pose, dtype=np.float64)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"initial_pose must be a finite (3,) array (got {initial_pose!r})")
        self._assoc = self.config.association
        self._p = ParticleSet.create(pose, self.config.particles, self.config.initial_capacity,
                                     self.config.tracks(known=self.known))
        self._rng = rng
        self._r = self.config.sensor.covariance
        self._id_to_slot, self._slot_ids = {}, []
        self._best = 0
        self._pose, self._pose_cov = pose.copy(), np.zeros((3, 3))
        self._n_eff = float(self.config.particles)
        self._resampled = False
        self._weight_resets = 0
        self._assoc_out = np.zeros(0, dtype=np.int64)
        self._marginal = LinearisedMarginal(pose, self._r) if self.config.pose_cov == "linearised" else None
        self._lifecycle_reset()

    # -- association ---------------------------------------------------------------------------------------------

    def _slot_for_id(self, lm_id: int) -> int:
        slot = self._id_to_slot.get(lm_id)
        if slot is None:
            slot = len(self._slot_ids)
            self._id_to_slot[lm_id] = slot
            self._slot_ids.append(lm_id)
            self.particles.ensure_capacity(slot + 1)
        return slot

    def _candidates(self, poses: Array, radius: float) -> tuple[IntArray, BoolArray]:
        """Per particle, the occupied slots within ``radius`` of its pose, left-packed. (M,3) -> (M,V), (M,V)."""
        p = self.particles
        used = int(p.lm_count.max())  # per-particle ML appends slots: nothing lives beyond the longest map
        dx = p.lm_mean[:, :used, 0] - poses[:, 0:1]
        dy = p.lm_mean[:, :used, 1] - poses[:, 1:2]
        near = (p.tracks.hits[:, :used] > 0) & (dx * dx + dy * dy <= radius * radius)
        rows, cols = np.nonzero(near)
        counts = np.bincount(rows, minlength=p.size)
        v = int(counts.max()) if counts.size else 0
        cand = np.zeros((p.size, v), dtype=np.int64)
        valid = np.zeros((p.size, v), dtype=bool)
        if v:
            start = np.cumsum(counts) - counts
            pos = np.arange(rows.size) - start[rows]
            cand[rows, pos] = cols
            valid[rows, pos] = True
        return cand, valid

    def _ml_associate(self, poses: Array, pose_cov: Array | None, z: Array, cand: IntArray,
                      valid: BoolArray) -> tuple[IntArray, BoolArray]:
        """Per particle, the candidate slot of highest likelihood and whether to start a new landmark instead.

        The likelihood is the one that enters the weight: N(z; h, H_m Sigma H_m^T + R) for 1.0, plus the pose
        term H_x P H_x^T for 2.0. Shapes: poses (M,3), pose_cov (M,3,3) or None, z (2,), cand/valid (M,V).
        """
        p = self.particles
        m = p.size
        log_p0 = math.log(self.config.new_landmark_likelihood)
        if cand.shape[1] == 0:
            return np.zeros(m, dtype=np.int64), np.ones(m, dtype=bool)
        rows = np.arange(m)[:, None]
        n_near = self.config.association_candidates
        if cand.shape[1] > n_near:
            # cheap pre-selection: the n_near landmarks nearest (Euclidean, world frame) to where this particle
            # places the observation; the exact likelihood is then evaluated for those only
            a = poses[:, 2] + z[1]
            ox, oy = poses[:, 0] + z[0] * np.cos(a), poses[:, 1] + z[0] * np.sin(a)
            mu_all = p.lm_mean[rows, cand]
            d2 = np.where(valid, (mu_all[..., 0] - ox[:, None]) ** 2 + (mu_all[..., 1] - oy[:, None]) ** 2, np.inf)
            near = np.argpartition(d2, n_near - 1, axis=1)[:, :n_near]
            cand, valid = cand[rows, near], valid[rows, near]
        mu, sig = p.lm_mean[rows, cand], p.lm_cov[rows, cand]
        r = self._r
        rng, bearing, h00, h01, h10, h11 = _observe(poses[:, None, :], mu)
        s00, s01, s11 = sig[..., 0, 0], sig[..., 0, 1], sig[..., 1, 1]
        g0 = g1 = p22 = np.zeros(1)
        if pose_cov is not None:
            # H_x P H_x^T with H_x = [-H_m | (0,-1)^T]: H_m (Sigma + P_xy) H_m^T + [[0, g0], [g0, 2 g1 + P_tt]],
            # where g = H_m P[:2, 2] (expanded by hand; see _observe)
            s00 = s00 + pose_cov[:, None, 0, 0]
            s01 = s01 + pose_cov[:, None, 0, 1]
            s11 = s11 + pose_cov[:, None, 1, 1]
            c0, c1 = pose_cov[:, None, 0, 2], pose_cov[:, None, 1, 2]
            g0, g1, p22 = h00 * c0 + h01 * c1, h10 * c0 + h11 * c1, pose_cov[:, None, 2, 2]
        a00, a01, a11, *_ = _congruence2(h00, h01, h10, h11, s00, s01, s11)
        a00, a01, a11 = a00 + r[0, 0], a01 + r[0, 1] + g0, a11 + r[1, 1] + 2.0 * g1 + p22
        ll = _logpdf2_sym(z[0] - rng, wrap_angle(z[1] - bearing), a00, a01, a11)
        ll = np.where(valid, ll, -np.inf)
        best = np.argmax(ll, axis=1)
        best_ll = ll[np.arange(m), best]
        return cand[np.arange(m), best], ~(best_ll >= log_p0)

    def _decide(self, lm_id: int, poses: Array, pose_cov: Array | None, z: Array,
                cand: IntArray, valid: BoolArray) -> tuple[IntArray, BoolArray]:
        """Slot per particle for one observation and whether it is new; allocates new slots (capacity grows)."""
        p = self.particles
        if self.known:
            slot = self._slot_for_id(lm_id)
            return np.full(p.size, slot, dtype=np.int64), p.tracks.hits[:, slot] == 0
        c, is_new = self._ml_associate(poses, pose_cov, z, cand, valid)
        if np.any(is_new):
            p.ensure_capacity(int(p.lm_count.max()) + 1)
            c = np.where(is_new, p.lm_count, c)
            p.lm_count += is_new
        return c, is_new

    def _update_landmarks(self, poses: Array, z: Array, c: IntArray, is_new: BoolArray) -> Array:
        """EKF-update slot c of each particle (or initialise it where ``is_new``); returns the update log-likelihoods.

        Shapes: poses (M,3), z (2,), c (M,), is_new (M,) -> (M,) (meaningless where is_new)."""
        p = self.particles
        rows = np.arange(p.size)
        r = self._r
        mu, sig, ll = landmark_update(poses, z, p.lm_mean[rows, c], p.lm_cov[rows, c], r)
        if is_new.any():
            mu0, sig0 = landmark_init(poses[is_new], z, r)
            mu[is_new], sig[is_new] = mu0, sig0
        p.lm_mean[rows, c] = mu
        p.lm_cov[rows, c] = sig
        self._track(poses, z, rows, c, is_new)
        return ll

    def _track(self, poses: Array, z: Array, rows: IntArray, c: IntArray, is_new: BoolArray) -> None:
        """Start (``is_new``) or sight the tracks (rows, c) with observation z (2,) or (n,2) taken at poses (n,3)."""
        tracks = self.particles.tracks
        pts, covs = landmark_init(poses, z, self._r) if tracks.config.dynamic_test else (None, None)
        new, old = is_new, ~is_new
        if new.any():
            tracks.start(c[new], self._t, *_part(pts, covs, new), rows=rows[new])
        if old.any():
            tracks.sight(c[old], self._t, *_part(pts, covs, old), rows=rows[old])

    # -- one step ------------------------------------------------------------------------------------------------

    def step(self, step: Step) -> None:
        self._check_step()
        p = self.particles
        cfg = self.config
        u = np.asarray(step.odometry, dtype=np.float64)
        obs = step.observations
        z_all = obs.z
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise ValueError(f"step {step.index}: odometry must be a finite (3,) array (got {step.odometry!r})")
        if not np.all(np.isfinite(z_all)):
            raise ValueError(f"step {step.index}: observations contain non-finite range or bearing")
        self._t = step.index
        if self._assoc.method == "auto" and len(obs):
            self._assoc = resolve_method(self._assoc, bool(np.any(obs.landmark_id >= 0)))
            p.tracks.config = self.config.tracks(known=self.known)
        if self._marginal is not None and self._assoc.method != "auto" and not self.known:
            raise ValueError("FastSLAMConfig.pose_cov='linearised' needs known association (per-particle ML gives "
                             f"each particle its own landmarks); association method is {self._assoc.method!r}")
        ids = np.asarray(obs.landmark_id, dtype=np.int64)
        use = np.flatnonzero(ids >= 0) if self.known else np.arange(len(obs))
        m = p.size
        rows = np.arange(m)
        r = self._r
        log_p0 = math.log(cfg.new_landmark_likelihood)
        assoc_slots = np.full((len(obs), m), -1, dtype=np.int64)

        noise = cfg.motion if cfg.motion_noise_scale == 1.0 else cfg.motion.scaled(cfg.motion_noise_scale)
        if cfg.version == 1:
            poses = sample_motion(p.poses, u, noise, self._rng)
            pose_cov = None
        else:
            poses, pose_cov = motion_gaussian(p.poses, u, noise)

        cand = np.zeros((m, 0), dtype=np.int64)
        valid = np.zeros((m, 0), dtype=bool)
        if not self.known:
            # one radius for association and for the existence counters: every landmark that could be in view
            radius = max(cfg.sensor.max_range_m, float(z_all[use, 0].max()) if use.size else 0.0)
            cand, valid = self._candidates(poses, radius + cfg.candidate_margin_m)

        dlogw = np.zeros(m)
        if cfg.version == 1 and self.known and self._batch_known and np.unique(ids[use]).size == use.size:
            # given the sampled pose, the EKFs of distinct landmarks are independent: update all of this scan's
            # landmarks at once, (M, k) in one go (the loop below gives the same numbers, with more overhead)
            slots = np.array([self._slot_for_id(int(i)) for i in ids[use]], dtype=np.int64)
            z_use = z_all[use]
            is_new = p.tracks.hits[:, slots] == 0
            mu, sig, ll = landmark_update(poses[:, None, :], z_use, p.lm_mean[:, slots], p.lm_cov[:, slots], r)
            if is_new.any():
                mu0, sig0 = landmark_init(np.broadcast_to(poses[:, None, :], (*is_new.shape, 3)), z_use, r)
                mu[is_new], sig[is_new] = mu0[is_new], sig0[is_new]
            p.lm_mean[:, slots] = mu
            p.lm_cov[:, slots] = sig
            grid_rows, grid_slots = np.broadcast_to(rows[:, None], is_new.shape), np.broadcast_to(slots, is_new.shape)
            self._track(np.broadcast_to(poses[:, None, :], (*is_new.shape, 3)).reshape(-1, 3),
                        np.broadcast_to(z_use, (*is_new.shape, 2)).reshape(-1, 2), grid_rows.reshape(-1),
                        grid_slots.reshape(-1), is_new.reshape(-1))
            dlogw += np.where(is_new, log_p0, ll).sum(axis=1)
            assoc_slots[use] = slots[:, None]
        elif cfg.version == 1:
            for j in use:
                z = z_all[j]
                c, is_new = self._decide(int(ids[j]), poses, None, z, cand, valid)
                ll = self._update_landmarks(poses, z, c, is_new)
                dlogw += np.where(is_new, log_p0, ll)
                assoc_slots[j] = c
        else:
            assert pose_cov is not None
            decisions: list[tuple[int, IntArray, BoolArray]] = []
            pending: set[int] = set()  # known ids first seen in this scan: initialised only after the draw
            for j in use:
                z = z_all[j]
                c, is_new = self._decide(int(ids[j]), poses, pose_cov, z, cand, valid)
                if self.known and is_new.any():
                    if int(c[0]) in pending:
                        # a repeated new id in one scan: no landmark exists yet to condition the proposal on;
                        # its sighting refines the fresh landmark after the draw (below)
                        decisions.append((int(j), c, is_new))
                        assoc_slots[j] = c
                        continue
                    pending.add(int(c[0]))
                mean2, cov2, ll = proposal_update(poses, pose_cov, z, p.lm_mean[rows, c], p.lm_cov[rows, c], r)
                poses = np.where(is_new[:, None], poses, mean2)
                pose_cov = np.where(is_new[:, None, None], pose_cov, cov2)
                dlogw += np.where(is_new, log_p0, ll)
                decisions.append((int(j), c, is_new))
                assoc_slots[j] = c
            poses = sample_gaussian_poses(poses, pose_cov, self._rng)
            # landmark EKFs at the drawn pose, in the order the observations were incorporated
            for jj, c, is_new in decisions:
                self._update_landmarks(poses, z_all[jj], c, is_new & (p.tracks.hits[rows, c] == 0))
        p.poses = poses

        if not self.known:
            self._count_misses(cand, valid)

        lw, degenerate = normalize_log_weights(p.log_weights + dlogw)
        if degenerate:
            self._weight_resets += 1
        w = np.exp(lw)
        self._n_eff = effective_sample_size(w)
        self._pose, self._pose_cov = weighted_pose_stats(p.poses, w)
        if self._marginal is not None:
            slots = assoc_slots[use, 0]
            self._marginal.step(self._pose, u, noise, slots, np.einsum("m,mkd->kd", w, p.lm_mean[:, slots]),
                                z_all[use])
            self._pose_cov = self._marginal.reported_pose_cov(self._pose_cov)
        best = int(np.argmax(w))
        self._resampled = self._n_eff < cfg.resample_threshold * m
        if self._resampled:
            idx = systematic_resample(w, self._rng)
            self._p = p = p.select(idx)
            p.log_weights = np.full(m, -math.log(m))
            # the best particle has w >= 1/M, so systematic resampling always keeps at least one copy of it
            best = int(np.flatnonzero(idx == best)[0])
        else:
            p.log_weights = lw
        self._best = best
        self._assoc_out = np.full(len(obs), -1, dtype=np.int64)
        shown = assoc_slots[:, best]
        for j in np.flatnonzero(shown >= 0):
            self._assoc_out[j] = self._slot_ids[shown[j]] if self.known else shown[j]

    def _count_misses(self, cand: IntArray, valid: BoolArray) -> None:
        """One more miss for each landmark predicted well inside the sensor's view and not sighted this step, then
        free the slots the tracks prune (their stale means stay; ``hits == 0`` marks them empty).

        Shapes: cand/valid (M,V) the landmarks near each particle (a superset of those in view)."""
        p = self.particles
        if cand.shape[1] == 0:
            return
        sensor = self.config.sensor
        rows = np.broadcast_to(np.arange(p.size)[:, None], cand.shape)
        z_hat = range_bearing(p.poses[:, None, :], p.lm_mean[rows, cand])
        view = valid & in_view(z_hat, sensor.max_range_m, sensor.fov_rad, p.tracks.config.view_margin_m)
        mask = np.zeros(p.tracks.hits.shape, dtype=bool)
        mask[rows[view], cand[view]] = True
        p.tracks.miss(mask, self._t)
        p.tracks.free(p.tracks.prune_mask())

    # -- snapshot ------------------------------------------------------------------------------------------------

    def finalize(self) -> None:
        self._lifecycle_finalize()

    def estimate(self) -> Estimate:
        self._check_ready()
        p = self.particles
        b = self._best
        slots = np.flatnonzero(p.tracks.confirmed[b])
        tent = np.flatnonzero(p.tracks.tentative[b])
        if self.known:
            ids = np.asarray(self._slot_ids, dtype=np.int64)[slots] if slots.size else np.zeros(0, dtype=np.int64)
        else:
            ids = slots.astype(np.int64)
        w = np.exp(p.log_weights)
        return Estimate(
            pose=self._pose.copy(),
            pose_cov=self._pose_cov.copy(),
            landmarks=p.lm_mean[b, slots].copy(),
            landmark_covs=p.lm_cov[b, slots].copy(),
            landmark_ids=ids,
            state_dim=3 + 2 * int(slots.size),
            association=self._assoc_out.copy(),
            tentative_landmarks=p.lm_mean[b, tent].copy(),
            tentative_ids=tent.astype(np.int64),
            particles=ParticleView(p.poses.copy(), w, float(self._n_eff), bool(self._resampled)),
            diagnostics=Diagnostics(weight_resets=self._weight_resets),
        )
