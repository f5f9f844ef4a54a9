"""Motion models with noise and Jacobians.

Odometry model (Thrun et al., Probabilistic Robotics, sec. 5.4): a relative motion u = [dx, dy, dtheta] is read
as (rot1, trans, rot2); each part gets zero-mean Gaussian noise whose variance grows with the motion
(alpha1..alpha4, table 5.6). Velocity model (sec. 5.3): commands (v, w) held for dt move the robot along an
arc, ``exp([v dt, 0, w dt])``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_nonnegative
from slam2d.geometry import se2
from slam2d.geometry.angles import angle_diff, wrap_angle, wrap_angle_scalar

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class MotionNoise:
    """Odometry noise (Probabilistic Robotics table 5.6) plus a floor so that standing still is not certain."""

    alpha_rot_rot: float = 0.0025
    """alpha1: rotation variance per squared rotation (rad^2/rad^2)."""
    alpha_rot_trans: float = 0.0004
    """alpha2: rotation variance per squared translation (rad^2/m^2)."""
    alpha_trans_trans: float = 0.0025
    """alpha3: translation variance per squared translation (m^2/m^2)."""
    alpha_trans_rot: float = 0.0001
    """alpha4: translation variance per squared rotation (m^2/rad^2)."""
    min_trans_std_m: float = 0.002
    """standard deviation added to the translation even without motion (m)."""
    min_rot_std_rad: float = 0.001
    """standard deviation added to each rotation even without motion (rad)."""

    def __post_init__(self) -> None:
        check_nonnegative(self, "alpha_rot_rot", "alpha_rot_trans", "alpha_trans_trans", "alpha_trans_rot",
                          "min_trans_std_m", "min_rot_std_rad")

    def scaled(self, factor: float) -> MotionNoise:
        """All variances multiplied by ``factor`` (e.g. 0.1 for an overconfident filter)."""
        if not factor > 0:
            raise ValueError(f"scale factor must be > 0 (got {factor})")
        s = float(np.sqrt(factor))
        return MotionNoise(
            alpha_rot_rot=self.alpha_rot_rot * factor,
            alpha_rot_trans=self.alpha_rot_trans * factor,
            alpha_trans_trans=self.alpha_trans_trans * factor,
            alpha_trans_rot=self.alpha_trans_rot * factor,
            min_trans_std_m=self.min_trans_std_m * s,
            min_rot_std_rad=self.min_rot_std_rad * s,
        )


def odometry_to_rtr(u: ArrayLike) -> Array:
    """[dx, dy, dtheta] -> [rot1, trans, rot2]. For a pure rotation rot1 = 0. Shapes: (...,3) -> (...,3)."""
    u = np.asarray(u, dtype=np.float64)
    trans = np.hypot(u[..., 0], u[..., 1])
    rot1 = np.where(trans > 1e-9, np.arctan2(u[..., 1], u[..., 0]), 0.0)
    return np.stack([rot1, trans, angle_diff(u[..., 2], rot1)], axis=-1)


def rtr_to_odometry(m: ArrayLike) -> Array:
    """[rot1, trans, rot2] -> [dx, dy, dtheta]."""
    m = np.asarray(m, dtype=np.float64)
    return np.stack(
        [m[..., 1] * np.cos(m[..., 0]), m[..., 1] * np.sin(m[..., 0]), wrap_angle(m[..., 0] + m[..., 2])], axis=-1
    )


def rtr_to_odometry_jacobians(m: ArrayLike) -> tuple[Array]:
    """``(J_u_m,)``: d[dx,dy,dtheta]/d[rot1,trans,rot2], (...,3,3)."""
    m = np.asarray(m, dtype=np.float64)
    c, s, t = np.cos(m[..., 0]), np.sin(m[..., 0]), m[..., 1]
    one, zero = np.ones_like(c), np.zeros_like(c)
    return (se2.matrix_from_rows([-t * s, c, zero], [t * c, s, zero], [one, zero, one]),)



def rtr_variances(m: ArrayLike, noise: MotionNoise) -> Array:
    """Variances of (rot1, trans, rot2) for motion ``m`` (table 5.6 plus the noise floor). Shapes: (...,3)->(...,3)."""
    m = np.asarray(m, dtype=np.float64)
    r1, t, r2 = m[..., 0], m[..., 1], m[..., 2]
    r1, r2 = angle_diff(r1, 0.0), angle_diff(r2, 0.0)
    v1 = noise.alpha_rot_rot * r1**2 + noise.alpha_rot_trans * t**2 + noise.min_rot_std_rad**2
    vt = noise.alpha_trans_trans * t**2 + noise.alpha_trans_rot * (r1**2 + r2**2) + noise.min_trans_std_m**2
    v2 = noise.alpha_rot_rot * r2**2 + noise.alpha_rot_trans * t**2 + noise.min_rot_std_rad**2
    return np.stack([v1, vt, v2], axis=-1)


def odometry_covariance(u: ArrayLike, noise: MotionNoise) -> Array:
    """Covariance of a measured motion u in [dx, dy, dtheta] coordinates: V diag(var) V^T. (...,3)->(...,3,3)."""
    m = odometry_to_rtr(u)
    (v,) = rtr_to_odometry_jacobians(m)
    var = rtr_variances(m, noise)
    return np.einsum("...ij,...j,...kj->...ik", v, var, v)


#: added to an odometry covariance before inverting it where it may be zero (a standstill): online graph SLAM adds it
#: to every step, range-only graph SLAM to the standstills
ODOMETRY_FLOOR_VAR = 1e-8


def odometry_factor(u: ArrayLike, noise: MotionNoise, *, floor_var: float = 0.0) -> tuple[Array, Array]:
    """Measurement and information of the between factor that odometry ``u`` becomes: ``(z, info)``.

    The between factor's error (``graph/factors.py``, g2o EdgeSE2) expresses the translation residual in the frame
    of the END of the motion: ``e = [R(dtheta)^T (t - [dx, dy]); theta - dtheta]``. So the error covariance is the
    [dx, dy, dtheta] covariance rotated by ``R(dtheta)^T``; inverting the unrotated covariance would weight the
    along- and across-track directions wrongly after every turn. ``floor_var`` is added to every diagonal entry of
    the covariance (isotropic, so rotation leaves it unchanged) to keep a standstill's information finite.
    Shapes: (...,3) -> (...,3), (...,3,3).
    """
    z = np.array(u, dtype=np.float64)
    cov_e = se2.covariance_in_frame(odometry_covariance(z, noise), z[..., 2]) + floor_var * np.eye(3)
    return z, np.asarray(np.linalg.inv(cov_e), dtype=np.float64)


def sample_odometry(u_true: ArrayLike, noise: MotionNoise, rng: np.random.Generator) -> Array:
    """A noisy odometry reading of the true relative motion ``u_true`` (noise applied in rot1-trans-rot2 space)."""
    m = odometry_to_rtr(u_true)
    std = np.sqrt(rtr_variances(m, noise))
    return rtr_to_odometry(m + std * rng.standard_normal(m.shape))


def odometry_predict(pose: ArrayLike, u: ArrayLike) -> Array:
    """Pose after relative motion u: ``compose(pose, u)``. Shapes: (...,3),(...,3) -> (...,3)."""
    return se2.compose(pose, u)


def odometry_predict_jacobians(pose: ArrayLike, u: ArrayLike) -> tuple[Array, Array]:
    """``(J_x_pose, J_x_u)`` (Probabilistic Robotics G and V, in [dx,dy,dtheta] control coordinates)."""
    return se2.compose_jacobians(pose, u)



# Scalar twins (plain floats, no batch axis) for per-step filter hot paths; tests pin them to the array versions.
def odometry_scalar(pose: Array, u: Array) -> tuple[Array, Array, Array]:
    """``pose (+) u`` and its Jacobians ``G = d/d pose``, ``V = d/d u`` (3,3) in scalar arithmetic.

    Twin of :func:`odometry_predict` (and its Jacobians) without the batched-array overheads, for filters that run
    it once per step; ``odometry_scalar_value``/``_jacobians`` expose it to the finite-difference check.
    """
    x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
    dx, dy, dth = float(u[0]), float(u[1]), float(u[2])
    c, s = math.cos(th), math.sin(th)
    new = np.array([x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle_scalar(th + dth)])
    G = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
    V = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return new, G, V


def odometry_scalar_value(pose: Array, u: Array) -> Array:
    return odometry_scalar(pose, u)[0]


def odometry_scalar_jacobians(pose: Array, u: Array) -> tuple[Array, Array]:
    _, G, V = odometry_scalar(pose, u)
    return G, V


def odometry_covariance_scalar(u: Array, noise: MotionNoise) -> Array:
    """Scalar twin of :func:`odometry_covariance` (covariance of u in [dx, dy, dtheta]); a test checks
    that the two agree."""
    dx, dy, dth = float(u[0]), float(u[1]), float(u[2])
    t = math.hypot(dx, dy)
    r1 = math.atan2(dy, dx) if t > 1e-9 else 0.0
    r2 = wrap_angle_scalar(dth - r1)
    r1w = wrap_angle_scalar(r1)
    v1 = noise.alpha_rot_rot * r1w**2 + noise.alpha_rot_trans * t**2 + noise.min_rot_std_rad**2
    vt = noise.alpha_trans_trans * t**2 + noise.alpha_trans_rot * (r1w**2 + r2**2) + noise.min_trans_std_m**2
    v2 = noise.alpha_rot_rot * r2**2 + noise.alpha_rot_trans * t**2 + noise.min_rot_std_rad**2
    c, s = math.cos(r1), math.sin(r1)
    J = np.array([[-t * s, c, 0.0], [t * c, s, 0.0], [1.0, 0.0, 1.0]])  # d[dx,dy,dth]/d[rot1,trans,rot2]
    return (J * np.array([v1, vt, v2])) @ J.T


@dataclass(frozen=True, slots=True, kw_only=True)
class VelocityNoise:
    """Velocity-model noise (Probabilistic Robotics table 5.3): std of v and w grow with |v| and |w|."""

    alpha_v_v: float = 0.01
    """variance of v per v^2."""
    alpha_v_w: float = 0.001
    """variance of v per w^2 (m^2/rad^2)."""
    alpha_w_v: float = 0.001
    """variance of w per v^2 (rad^2/m^2)."""
    alpha_w_w: float = 0.01
    """variance of w per w^2."""

    def __post_init__(self) -> None:
        check_nonnegative(self, "alpha_v_v", "alpha_v_w", "alpha_w_v", "alpha_w_w")


def velocity_increment(vw: ArrayLike, dt: float) -> Array:
    """Relative motion of an arc driven at (v, w) for dt seconds. Shapes: (...,2) -> (...,3)."""
    vw = np.asarray(vw, dtype=np.float64)
    zero = np.zeros_like(vw[..., 0])
    return se2.exp(np.stack([vw[..., 0] * dt, zero, vw[..., 1] * dt], axis=-1))


def velocity_increment_jacobians(vw: ArrayLike, dt: float) -> tuple[Array]:
    """``(J_u_vw,)`` (...,3,2)."""
    vw = np.asarray(vw, dtype=np.float64)
    zero = np.zeros_like(vw[..., 0])
    (j,) = se2.exp_jacobians(np.stack([vw[..., 0] * dt, zero, vw[..., 1] * dt], axis=-1))
    return (np.stack([j[..., :, 0] * dt, j[..., :, 2] * dt], axis=-1),)



def velocity_predict(pose: ArrayLike, vw: ArrayLike, dt: float) -> Array:
    """Pose after driving (v, w) for dt from ``pose``."""
    return se2.compose(pose, velocity_increment(vw, dt))


def velocity_predict_jacobians(pose: ArrayLike, vw: ArrayLike, dt: float) -> tuple[Array, Array]:
    """``(J_x_pose (...,3,3), J_x_vw (...,3,2))``."""
    u = velocity_increment(vw, dt)
    ja, jb = se2.compose_jacobians(pose, u)
    (ju,) = velocity_increment_jacobians(vw, dt)
    return ja, jb @ ju



def velocity_covariance(vw: ArrayLike, noise: VelocityNoise) -> Array:
    """Covariance of the (v, w) command. Shapes: (...,2) -> (...,2,2)."""
    vw = np.asarray(vw, dtype=np.float64)
    v2, w2 = vw[..., 0] ** 2, vw[..., 1] ** 2
    var_v = noise.alpha_v_v * v2 + noise.alpha_v_w * w2
    var_w = noise.alpha_w_v * v2 + noise.alpha_w_w * w2
    zero = np.zeros_like(var_v)
    return se2.matrix_from_rows([var_v, zero], [zero, var_w])
