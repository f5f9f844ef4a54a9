"""Point-landmark sensor models with Jacobians and inverse models.

Range-bearing: z = [|l - t|, atan2(l_y - y, l_x - x) - theta]. Bearing-only and range-only take one row of it.
Absolute position (GPS): z = [x, y].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_nonnegative, check_positive, check_probability
from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle, wrap_angle_scalar

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class SensorConfig:
    """A range-bearing landmark sensor."""

    max_range_m: float = 8.0
    """landmarks farther than this are not seen (m)."""
    fov_rad: float = 2 * np.pi
    """full field of view, centred on the heading (rad); 2*pi is omnidirectional."""
    range_std_m: float = 0.1
    """range noise standard deviation (m)."""
    bearing_std_rad: float = 0.02
    """bearing noise standard deviation (rad)."""
    detection_prob: float = 1.0
    """probability that a landmark in range is reported."""
    clutter_rate: float = 0.0
    """mean number of spurious detections per scan (Poisson), uniform in range and field of view."""
    descriptor_dim: int = 0
    """length of the optional landmark signature vector (0: none)."""
    descriptor_std: float = 0.05
    """noise on each observed signature component."""

    def __post_init__(self) -> None:
        check_positive(self, "max_range_m", "fov_rad", "range_std_m", "bearing_std_rad")
        check_probability(self, "detection_prob")
        check_nonnegative(self, "clutter_rate", "descriptor_std")
        if self.fov_rad > 2 * np.pi + 1e-12:
            raise ValueError(f"SensorConfig.fov_rad must be <= 2*pi (got {self.fov_rad})")
        if self.descriptor_dim < 0:
            raise ValueError(f"SensorConfig.descriptor_dim must be >= 0 (got {self.descriptor_dim})")

    @property
    def misses_per_sighting(self) -> float:
        """How many unreported in-view steps one sighting is worth: 1/detection_prob (capped at 20), so map
        management does not drop landmarks that a sensor with a low detection probability simply did not report."""
        return 1.0 / max(self.detection_prob, 0.05)

    @property
    def covariance(self) -> Array:
        """R = diag(range_std^2, bearing_std^2)."""
        return np.diag([self.range_std_m**2, self.bearing_std_rad**2])


def range_bearing(pose: ArrayLike, landmark: ArrayLike) -> Array:
    """Predicted [range, bearing] of ``landmark`` from ``pose``. Shapes: (...,3),(...,2) -> (...,2)."""
    pose, landmark = np.asarray(pose, dtype=np.float64), np.asarray(landmark, dtype=np.float64)
    dx, dy = landmark[..., 0] - pose[..., 0], landmark[..., 1] - pose[..., 1]
    return np.stack([np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx) - pose[..., 2])], axis=-1)


def range_bearing_jacobians(pose: ArrayLike, landmark: ArrayLike) -> tuple[Array, Array]:
    """``(H_pose (...,2,3), H_landmark (...,2,2))`` (Probabilistic Robotics eq. 10.18)."""
    pose, landmark = np.asarray(pose, dtype=np.float64), np.asarray(landmark, dtype=np.float64)
    dx, dy = landmark[..., 0] - pose[..., 0], landmark[..., 1] - pose[..., 1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    zero = np.zeros_like(q)
    hl = se2.matrix_from_rows([dx / r, dy / r], [-dy / q, dx / q])
    hp = se2.matrix_from_rows([-dx / r, -dy / r, zero], [dy / q, -dx / q, zero - 1.0])
    return hp, hl



def range_bearing_inverse(pose: ArrayLike, z: ArrayLike) -> Array:
    """Landmark position from a [range, bearing] measurement at ``pose``. Shapes: (...,3),(...,2) -> (...,2)."""
    pose, z = np.asarray(pose, dtype=np.float64), np.asarray(z, dtype=np.float64)
    a = pose[..., 2] + z[..., 1]
    return np.stack([pose[..., 0] + z[..., 0] * np.cos(a), pose[..., 1] + z[..., 0] * np.sin(a)], axis=-1)


def range_bearing_inverse_jacobians(pose: ArrayLike, z: ArrayLike) -> tuple[Array, Array]:
    """``(G_pose (...,2,3), G_z (...,2,2))``: the Jacobians used to augment an EKF-SLAM state."""
    pose, z = np.asarray(pose, dtype=np.float64), np.asarray(z, dtype=np.float64)
    a = pose[..., 2] + z[..., 1]
    c, s, r = np.cos(a), np.sin(a), z[..., 0]
    c, s, r = np.broadcast_arrays(c, s, r)
    one, zero = np.ones_like(c), np.zeros_like(c)
    gp = se2.matrix_from_rows([one, zero, -r * s], [zero, one, r * c])
    gz = se2.matrix_from_rows([c, -r * s], [s, r * c])
    return gp, gz



def bearing_only(pose: ArrayLike, landmark: ArrayLike) -> Array:
    """Predicted bearing, shape (...,1)."""
    return range_bearing(pose, landmark)[..., 1:]


def bearing_only_jacobians(pose: ArrayLike, landmark: ArrayLike) -> tuple[Array, Array]:
    """``(H_pose (...,1,3), H_landmark (...,1,2))``."""
    hp, hl = range_bearing_jacobians(pose, landmark)
    return hp[..., 1:, :], hl[..., 1:, :]



def range_only(pose: ArrayLike, landmark: ArrayLike) -> Array:
    """Predicted range, shape (...,1)."""
    return range_bearing(pose, landmark)[..., :1]


def range_only_jacobians(pose: ArrayLike, landmark: ArrayLike) -> tuple[Array, Array]:
    """``(H_pose (...,1,3), H_landmark (...,1,2))``."""
    hp, hl = range_bearing_jacobians(pose, landmark)
    return hp[..., :1, :], hl[..., :1, :]



def absolute_position(pose: ArrayLike) -> Array:
    """GPS-like measurement of the position, shape (...,2)."""
    return np.asarray(pose, dtype=np.float64)[..., :2].copy()


def absolute_position_jacobians(pose: ArrayLike) -> tuple[Array]:
    """``(H_pose (...,2,3),)``."""
    pose = np.asarray(pose, dtype=np.float64)
    h = np.zeros(pose.shape[:-1] + (2, 3))
    h[..., 0, 0] = h[..., 1, 1] = 1.0
    return (h,)



def visible(z: ArrayLike, config: SensorConfig) -> NDArray[np.bool_]:
    """Which predicted [range, bearing] values fall inside the sensor's range and field of view."""
    z = np.asarray(z, dtype=np.float64)
    return (z[..., 0] <= config.max_range_m) & (z[..., 0] > 1e-6) & (np.abs(z[..., 1]) <= 0.5 * config.fov_rad)


def sense_landmarks(
    pose: ArrayLike,
    landmarks: ArrayLike,
    landmark_ids: ArrayLike,
    config: SensorConfig,
    rng: np.random.Generator,
    descriptors: ArrayLike | None = None,
) -> tuple[Array, NDArray[np.int64], Array | None]:
    """Simulate one noisy scan of point landmarks (without clutter; see :func:`sense_clutter`).

    Returns (z (K,2), ids (K,), descriptors (K,D) or None). Noise draws happen for every landmark, visible or not,
    so that a landmark's noise sequence does not depend on what else is in view.
    """
    lm = np.asarray(landmarks, dtype=np.float64).reshape(-1, 2)
    ids = np.asarray(landmark_ids, dtype=np.int64).reshape(-1)
    z_true = range_bearing(pose, lm)
    noise = rng.standard_normal((lm.shape[0], 2)) * [config.range_std_m, config.bearing_std_rad]
    detect = rng.random(lm.shape[0]) < config.detection_prob
    desc_noise = rng.standard_normal((lm.shape[0], config.descriptor_dim)) * config.descriptor_std
    keep = visible(z_true, config) & detect
    z = z_true + noise
    z[:, 1] = wrap_angle(z[:, 1])
    z[:, 0] = np.maximum(z[:, 0], 0.0)
    desc = None
    if config.descriptor_dim > 0 and descriptors is not None:
        desc = (np.asarray(descriptors, dtype=np.float64) + desc_noise)[keep]
    return z[keep], ids[keep], desc


def sense_clutter(config: SensorConfig, rng: np.random.Generator) -> tuple[Array, Array | None]:
    """Spurious detections: Poisson count, uniform in range and field of view, random signatures."""
    n = int(rng.poisson(config.clutter_rate)) if config.clutter_rate > 0 else 0
    r = rng.uniform(0.2, config.max_range_m, size=n)
    b = rng.uniform(-0.5 * config.fov_rad, 0.5 * config.fov_rad, size=n)
    desc = rng.random((n, config.descriptor_dim)) if config.descriptor_dim > 0 else None
    return np.stack([r, wrap_angle(b)], axis=-1).reshape(n, 2), desc


def range_bearing_scalar(pose: Array, landmark: Array) -> tuple[Array, Array]:
    """[range, bearing] of one landmark and its Jacobian ``[H_pose | H_landmark]`` (2,5), in scalar arithmetic.

    Twin of :func:`range_bearing` and its Jacobians: the batched version costs ~80 us per call from array overheads
    and EKF-SLAM calls this once per observation. ``range_bearing_scalar_value``/``_jacobians`` expose it to the
    finite-difference check.
    """
    dx, dy = float(landmark[0]) - float(pose[0]), float(landmark[1]) - float(pose[1])
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    z = np.array([r, wrap_angle_scalar(math.atan2(dy, dx) - float(pose[2]))])
    H = np.array([[-dx / r, -dy / r, 0.0, dx / r, dy / r], [dy / q, -dx / q, -1.0, -dy / q, dx / q]])
    return z, H


def range_bearing_scalar_value(pose: Array, landmark: Array) -> Array:
    return range_bearing_scalar(pose, landmark)[0]


def range_bearing_scalar_jacobians(pose: Array, landmark: Array) -> tuple[Array, Array]:
    H = range_bearing_scalar(pose, landmark)[1]
    return H[:, :3], H[:, 3:]


def range_bearing_elementwise(poses: Array, lm: Array) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Element-wise twin of :func:`range_bearing` and its landmark Jacobian, fast for FastSLAM's small batches.

    Returns (range, bearing (unwrapped), h00, h01, h10, h11) with ``H_m = [[h00, h01], [h10, h11]]``; the pose
    Jacobian is ``H_x = [-H_m | (0, -1)^T]``. ``range_bearing_elementwise_value``/``_jacobians`` expose it to the
    finite-difference check. Shapes: poses (...,3), lm (...,2) -> six (...) arrays.
    """
    dx, dy = lm[..., 0] - poses[..., 0], lm[..., 1] - poses[..., 1]
    # a floor keeps padded/empty candidate slots (means at the origin) and a landmark on the robot finite
    q = np.maximum(dx * dx + dy * dy, 1e-18)
    rng = np.sqrt(q)
    bearing = np.arctan2(dy, dx) - poses[..., 2]
    return rng, bearing, dx / rng, dy / rng, -dy / q, dx / q


def range_bearing_elementwise_value(pose: Array, landmark: Array) -> Array:
    r, b, *_ = range_bearing_elementwise(pose, landmark)
    return np.stack([r, wrap_angle(b)], axis=-1)


def range_bearing_elementwise_jacobians(pose: Array, landmark: Array) -> tuple[Array, Array]:
    _, _, h00, h01, h10, h11 = range_bearing_elementwise(pose, landmark)
    zero, one = np.zeros_like(h00), np.ones_like(h00)
    return (se2.matrix_from_rows([-h00, -h01, zero], [-h10, -h11, -one]),
            se2.matrix_from_rows([h00, h01], [h10, h11]))
