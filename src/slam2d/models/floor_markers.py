"""Floor markers read by a short-range downward camera.

A marker is an ID'd tag on the floor. When it lies inside the camera's footprint (a disc of ``footprint_radius_m``
under the robot) the camera reports its id and its position in the robot frame:

    z = R(theta)^T (m - t)

with isotropic Gaussian noise of ``std_m`` per axis. The id is read from the tag, so there is no association
problem; the point is that identical aisles get told apart by the markers in them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_positive

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class FloorCameraConfig:
    """A downward-looking camera that reads floor markers."""

    footprint_radius_m: float = 1.0
    """markers closer than this to the robot (horizontally) are read (m)."""
    std_m: float = 0.01
    """noise standard deviation of each coordinate of a reading (m)."""
    read_every: int = 1
    """read the markers every this many steps."""

    def __post_init__(self) -> None:
        check_positive(self, "footprint_radius_m", "std_m")
        if self.read_every < 1:
            raise ValueError(f"FloorCameraConfig.read_every must be >= 1 (got {self.read_every})")


def marker_in_robot(pose: ArrayLike, marker: ArrayLike) -> Array:
    """Marker position in the robot frame. Shapes: (...,3),(...,2) -> (...,2)."""
    pose, marker = np.asarray(pose, dtype=np.float64), np.asarray(marker, dtype=np.float64)
    dx, dy = marker[..., 0] - pose[..., 0], marker[..., 1] - pose[..., 1]
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


def marker_in_robot_jacobians(pose: ArrayLike, marker: ArrayLike) -> tuple[Array, Array]:
    """``(H_pose (...,2,3), H_marker (...,2,2))`` of :func:`marker_in_robot`."""
    pose, marker = np.asarray(pose, dtype=np.float64), np.asarray(marker, dtype=np.float64)
    dx, dy = marker[..., 0] - pose[..., 0], marker[..., 1] - pose[..., 1]
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    c, s, dx, dy = np.broadcast_arrays(c, s, dx, dy)
    hp = np.zeros(c.shape + (2, 3))
    hp[..., 0, 0], hp[..., 0, 1], hp[..., 0, 2] = -c, -s, -s * dx + c * dy
    hp[..., 1, 0], hp[..., 1, 1], hp[..., 1, 2] = s, -c, -c * dx - s * dy
    hm = np.zeros(c.shape + (2, 2))
    hm[..., 0, 0], hm[..., 0, 1] = c, s
    hm[..., 1, 0], hm[..., 1, 1] = -s, c
    return hp, hm



def sense_floor_markers(pose: ArrayLike, markers: ArrayLike, config: FloorCameraConfig,
                        rng: np.random.Generator) -> tuple[Array, NDArray[np.int64]]:
    """Readings of the markers under the camera: (xy (K,2) in the robot frame, ids (K,)); marker ``i`` has id ``i``.

    Noise is drawn for every marker, seen or not, so one marker's noise does not depend on what else is in view.
    """
    m = np.asarray(markers, dtype=np.float64).reshape(-1, 2)
    z = marker_in_robot(pose, m)
    noise = rng.standard_normal(z.shape) * config.std_m
    seen = np.hypot(z[:, 0], z[:, 1]) <= config.footprint_radius_m
    return (z + noise)[seen], np.flatnonzero(seen).astype(np.int64)
