"""FastSLAM's particle set and pure kernels, all batched over a leading particle axis (M particles).

:class:`ParticleSet` holds every particle's pose, log-weight and landmark map in stacked arrays; the functions below
are the per-step maths (motion sampling, landmark EKF init/update, the FastSLAM 2.0 proposal, weights and
resampling). The estimator shell is :class:`slam2d.filters.fastslam.FastSLAM`, which re-exports these names.
References as in :mod:`slam2d.filters.fastslam`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.association.tracks import LandmarkTracks, TrackConfig
from slam2d.geometry import se2
from slam2d.geometry.angles import angle_diff, wrap_angle
from slam2d.models.motion import (
    MotionNoise,
    odometry_covariance,
    odometry_to_rtr,
    rtr_to_odometry,
    rtr_variances,
)
from slam2d.models.sensors import range_bearing_elementwise as _observe
from slam2d.models.sensors import range_bearing_inverse, range_bearing_inverse_jacobians

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_LOG_2PI = math.log(2.0 * math.pi)

# ----------------------------------------------------------------------------------------------------------------
# the particle set


@dataclass
class ParticleSet:
    """All particles as stacked arrays (mutated in place by the filter; :meth:`select` returns independent copies).

    Shapes: poses (M,3), log_weights (M,), lm_mean (M,K,2), lm_cov (M,K,2,2), lm_count (M,) int (per-particle ML:
    the next free slot; slots are appended), tracks: the landmarks' bookkeeping, (M,K) (``tracks.hits == 0``: an
    empty slot). K is the capacity, not the number of landmarks.
    """

    poses: Array
    log_weights: Array
    lm_mean: Array
    lm_cov: Array
    lm_count: IntArray
    tracks: LandmarkTracks

    @staticmethod
    def create(initial_pose: Array, particles: int, capacity: int,
               tracks: TrackConfig | None = None) -> ParticleSet:
        """``particles`` copies of ``initial_pose`` with uniform weights and empty maps."""
        if particles < 1:
            raise ValueError(f"FastSLAM needs at least one particle (got {particles})")
        m, k = int(particles), int(capacity)
        return ParticleSet(
            poses=np.tile(np.asarray(initial_pose, dtype=np.float64), (m, 1)),
            log_weights=np.full(m, -math.log(m)),
            lm_mean=np.zeros((m, k, 2)),
            lm_cov=np.zeros((m, k, 2, 2)),
            lm_count=np.zeros(m, dtype=np.int64),
            tracks=LandmarkTracks(tracks, m, k),
        )

    @property
    def size(self) -> int:
        return int(self.poses.shape[0])

    @property
    def capacity(self) -> int:
        return int(self.lm_mean.shape[1])

    def select(self, index: IntArray) -> ParticleSet:
        """Particles ``index`` (M',), each a fresh copy: fancy indexing copies, so no two particles share a map."""
        idx = np.asarray(index, dtype=np.int64)
        return ParticleSet(
            poses=self.poses[idx],
            log_weights=self.log_weights[idx],
            lm_mean=self.lm_mean[idx],
            lm_cov=self.lm_cov[idx],
            lm_count=self.lm_count[idx],
            tracks=self.tracks.select(idx),
        )

    def ensure_capacity(self, needed: int) -> None:
        """Grow the landmark axis to at least ``needed`` slots, at least doubling (amortised O(1) per landmark)."""
        k = self.capacity
        if needed <= k:
            return
        new_k = max(int(needed), 2 * k)
        m = self.size

        def grow(a: np.ndarray) -> np.ndarray:
            out = np.zeros((m, new_k, *a.shape[2:]), dtype=a.dtype)
            out[:, :k] = a
            return out

        self.lm_mean = grow(self.lm_mean)
        self.lm_cov = grow(self.lm_cov)
        self.tracks.grow(new_k)


# ----------------------------------------------------------------------------------------------------------------
# pure kernels (all batched over a leading particle axis)


def _inv2(a: Array) -> tuple[Array, Array]:
    """Inverse and determinant of stacked 2x2 matrices. Shapes: (...,2,2) -> (...,2,2), (...)."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    inv = np.empty_like(a)
    inv[..., 0, 0] = a[..., 1, 1]
    inv[..., 1, 1] = a[..., 0, 0]
    inv[..., 0, 1] = -a[..., 0, 1]
    inv[..., 1, 0] = -a[..., 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv /= det[..., None, None]
    return inv, det


def gaussian_logpdf2(nu: Array, s: Array) -> Array:
    """log N(nu; 0, S) for stacked 2-vectors. Shapes: (...,2),(...,2,2) -> (...). Non-PD S gives -inf."""
    s_inv, det = _inv2(s)
    d2 = np.einsum("...i,...ij,...j->...", nu, s_inv, nu)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = -0.5 * d2 - _LOG_2PI - 0.5 * np.log(det)
    return np.where((det > 0) & np.isfinite(out), out, -np.inf)


def _innovation(z: Array, z_hat: Array) -> Array:
    nu = z - z_hat
    nu[..., 1] = angle_diff(z[..., 1], z_hat[..., 1])
    return nu


def sample_motion(poses: Array, u: Array, noise: MotionNoise, rng: np.random.Generator) -> Array:
    """Draw each particle's new pose from the odometry model (noise in rot1-trans-rot2 space, as the simulator).

    Shapes: poses (M,3), u (3,) -> (M,3). References: Probabilistic Robotics table 5.6.
    """
    m = odometry_to_rtr(u)
    std = np.sqrt(rtr_variances(m, noise))
    draws = m + std * rng.standard_normal((poses.shape[0], 3))
    return se2.compose(poses, rtr_to_odometry(draws))


def motion_gaussian(poses: Array, u: Array, noise: MotionNoise) -> tuple[Array, Array]:
    """Linearised motion model per particle: mean ``x (+) u`` and covariance ``V Q V^T`` (V = d(x (+) u)/du).

    Shapes: poses (M,3), u (3,) -> (M,3), (M,3,3).
    """
    mean = se2.compose(poses, u)
    _, v = se2.compose_jacobians(poses, np.broadcast_to(u, poses.shape))
    q = odometry_covariance(u, noise)
    cov = v @ q @ np.swapaxes(v, -1, -2)
    return mean, 0.5 * (cov + np.swapaxes(cov, -1, -2))


def _congruence2(h00: Array, h01: Array, h10: Array, h11: Array, s00: Array, s01: Array,
                 s11: Array) -> tuple[Array, Array, Array, Array, Array, Array, Array]:
    """``H S H^T`` for symmetric 2x2 S, element-wise; also returns ``T = H S`` (t00, t01, t10, t11)."""
    t00, t01 = h00 * s00 + h01 * s01, h00 * s01 + h01 * s11
    t10, t11 = h10 * s00 + h11 * s01, h10 * s01 + h11 * s11
    return t00 * h00 + t01 * h01, t00 * h10 + t01 * h11, t10 * h10 + t11 * h11, t00, t01, t10, t11


def _logpdf2_sym(n0: Array, n1: Array, s00: Array, s01: Array, s11: Array) -> Array:
    """log N([n0, n1]; 0, [[s00, s01], [s01, s11]]) element-wise; -inf where S is not positive definite."""
    det = s00 * s11 - s01 * s01
    # an absurd outlier may overflow d2 to inf: that is a zero likelihood, handled by normalize_log_weights
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d2 = (s11 * n0 * n0 - 2.0 * s01 * n0 * n1 + s00 * n1 * n1) / det
        out = -0.5 * d2 - _LOG_2PI - 0.5 * np.log(det)
    return np.where((det > 0) & (s00 > 0) & np.isfinite(out), out, -np.inf)


def landmark_init(poses: Array, z: Array, r: Array) -> tuple[Array, Array]:
    """New landmark EKF from one observation: mean ``g^-1(x, z)``, covariance ``G_z R G_z^T``.

    Shapes: poses (M,3), z (2,) or (M,2), r (2,2) -> (M,2), (M,2,2). References: Probabilistic Robotics sec. 13.3.
    """
    zz = np.broadcast_to(z, (*poses.shape[:-1], 2))
    mean = range_bearing_inverse(poses, zz)
    _, gz = range_bearing_inverse_jacobians(poses, zz)
    return mean, gz @ r @ np.swapaxes(gz, -1, -2)


def landmark_update(poses: Array, z: Array, mean: Array, cov: Array, r: Array) -> tuple[Array, Array, Array]:
    """EKF update of each particle's landmark with observation ``z`` taken at a known pose.

    ``S = H Sigma H^T + R``, ``K = Sigma H^T S^-1``, ``mu' = mu + K nu``, ``Sigma' = Sigma - K S K^T``.
    Returns (new mean, new cov, log N(z; h(x, mu), S)) -- the last is the FastSLAM 1.0 importance weight.
    Written element-wise over the 2x2 blocks because numpy's stacked matmul is slow for tiny matrices.
    Shapes: poses (M,3), z (2,), mean (M,2), cov (M,2,2), r (2,2) -> (M,2), (M,2,2), (M,).
    References: Probabilistic Robotics sec. 13.3.
    """
    rng, bearing, h00, h01, h10, h11 = _observe(poses, mean)
    s00, s01, s11 = cov[..., 0, 0], 0.5 * (cov[..., 0, 1] + cov[..., 1, 0]), cov[..., 1, 1]
    a00, a01, a11, t00, t01, t10, t11 = _congruence2(h00, h01, h10, h11, s00, s01, s11)
    a00, a01, a11 = a00 + r[0, 0], a01 + 0.5 * (r[0, 1] + r[1, 0]), a11 + r[1, 1]
    det = a00 * a11 - a01 * a01
    i00, i01, i11 = a11 / det, -a01 / det, a00 / det
    # U = S^-1 T; K = T^T S^-1 = U^T; Sigma' = Sigma - T^T S^-1 T = Sigma - T^T U
    u00, u01 = i00 * t00 + i01 * t10, i00 * t01 + i01 * t11
    u10, u11 = i01 * t00 + i11 * t10, i01 * t01 + i11 * t11
    n0 = z[..., 0] - rng
    n1 = wrap_angle(z[..., 1] - bearing)
    new_mean = np.stack([mean[..., 0] + u00 * n0 + u10 * n1, mean[..., 1] + u01 * n0 + u11 * n1], axis=-1)
    c00 = s00 - (t00 * u00 + t10 * u10)
    c01 = s01 - (t00 * u01 + t10 * u11)
    c11 = s11 - (t01 * u01 + t11 * u11)
    new_cov = np.stack([np.stack([c00, c01], axis=-1), np.stack([c01, c11], axis=-1)], axis=-2)
    return new_mean, new_cov, _logpdf2_sym(n0, n1, a00, a01, a11)


def proposal_update(
    pose_mean: Array, pose_cov: Array, z: Array, lm_mean: Array, lm_cov: Array, r: Array
) -> tuple[Array, Array, Array]:
    """FastSLAM 2.0: condition each particle's Gaussian pose proposal on one observation of a known landmark.

    With ``Q_z = H_m Sigma H_m^T + R`` (landmark uncertainty plus sensor noise), the proposal is updated like a
    Kalman filter whose state is the pose: ``S = H_x P H_x^T + Q_z``, ``K = P H_x^T S^-1``,
    ``x' = x_hat + K nu``, ``P' = P - K S K^T``; this equals the information form
    ``P' = (H_x^T Q_z^-1 H_x + P^-1)^-1``, ``x' = x_hat + P' H_x^T Q_z^-1 nu`` of Montemerlo et al. 2003 and
    Probabilistic Robotics sec. 13.4, without inverting P. The returned log-likelihood
    ``log N(z; h(x_hat, mu), S)`` is the observation's importance-weight factor.

    Shapes: pose_mean (M,3), pose_cov (M,3,3), z (2,), lm_mean (M,2), lm_cov (M,2,2), r (2,2)
    -> (M,3), (M,3,3), (M,).
    """
    rng, bearing, h00, h01, h10, h11 = _observe(pose_mean, lm_mean)
    s00, s01, s11 = lm_cov[..., 0, 0], 0.5 * (lm_cov[..., 0, 1] + lm_cov[..., 1, 0]), lm_cov[..., 1, 1]
    q00, q01, q11, *_ = _congruence2(h00, h01, h10, h11, s00, s01, s11)
    q00, q01, q11 = q00 + r[0, 0], q01 + 0.5 * (r[0, 1] + r[1, 0]), q11 + r[1, 1]
    # H_x = [[-h00, -h01, 0], [-h10, -h11, -1]]; columns of C = P H_x^T, element-wise (3 rows each)
    p = pose_cov
    c0 = -(p[..., :, 0] * h00[..., None] + p[..., :, 1] * h01[..., None])
    c1 = -(p[..., :, 0] * h10[..., None] + p[..., :, 1] * h11[..., None] + p[..., :, 2])
    a00 = -(h00 * c0[..., 0] + h01 * c0[..., 1]) + q00
    a01 = -(h00 * c1[..., 0] + h01 * c1[..., 1]) + q01
    a11 = -(h10 * c1[..., 0] + h11 * c1[..., 1] + c1[..., 2]) + q11
    det = a00 * a11 - a01 * a01
    i00, i01, i11 = a11 / det, -a01 / det, a00 / det
    k0 = c0 * i00[..., None] + c1 * i01[..., None]  # K = C S^-1, column 0 (...,3)
    k1 = c0 * i01[..., None] + c1 * i11[..., None]
    n0 = z[..., 0] - rng
    n1 = wrap_angle(z[..., 1] - bearing)
    new_mean = pose_mean + k0 * n0[..., None] + k1 * n1[..., None]
    new_mean[..., 2] = wrap_angle(new_mean[..., 2])
    # P' = P - K S K^T = P - C K^T
    new_cov = p - (c0[..., :, None] * k0[..., None, :] + c1[..., :, None] * k1[..., None, :])
    return new_mean, 0.5 * (new_cov + np.swapaxes(new_cov, -1, -2)), _logpdf2_sym(n0, n1, a00, a01, a11)


def sample_gaussian_poses(mean: Array, cov: Array, rng: np.random.Generator) -> Array:
    """One draw per particle from N(mean, cov). Shapes: (M,3),(M,3,3) -> (M,3)."""
    # a tiny jitter keeps Cholesky alive when a proposal is (numerically) singular, e.g. zero motion noise
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(3))
    x = mean + np.einsum("...ij,...j->...i", chol, rng.standard_normal(mean.shape))
    x[..., 2] = wrap_angle(x[..., 2])
    return x


def normalize_log_weights(log_weights: Array) -> tuple[Array, bool]:
    """Log-sum-exp normalisation. NaN counts as -inf. Returns (normalised log-weights, degenerate).

    ``degenerate`` is True when every weight is zero (no finite log-weight); the weights are then reset to uniform,
    the documented recovery. Shapes: (M,) -> (M,).
    """
    lw = np.where(np.isnan(log_weights), -np.inf, log_weights)
    top = np.max(lw)
    if not np.isfinite(top):
        # +inf also lands here: a weight that dominates infinitely carries no usable information either
        return np.full(lw.shape, -math.log(lw.shape[0])), True
    lse = top + math.log(float(np.sum(np.exp(lw - top))))
    return lw - lse, False


def effective_sample_size(weights: Array) -> float:
    """``1 / sum(w^2)`` of normalised weights (M,)."""
    return float(1.0 / np.sum(weights * weights))


def systematic_resample(weights: Array, rng: np.random.Generator) -> IntArray:
    """Low-variance (systematic) resampling: one uniform offset, M evenly spaced pointers into the weights' CDF.

    Particle i is drawn floor(M w_i) or ceil(M w_i) times. Shapes: (M,) -> (M,) indices, sorted.
    References: Probabilistic Robotics table 4.4.
    """
    m = weights.shape[0]
    cdf = np.cumsum(weights)
    cdf /= cdf[-1]  # the last pointer must never run past the end because of rounding
    pointers = (rng.random() + np.arange(m)) / m
    return np.minimum(np.searchsorted(cdf, pointers, side="right"), m - 1).astype(np.int64)
