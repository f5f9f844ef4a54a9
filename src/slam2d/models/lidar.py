"""2D lidar: rays cast against wall segments, all rays x all segments in one vectorised pass."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_nonnegative, check_positive

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class LidarConfig:
    """A planar scanning range finder."""

    enabled: bool = True
    """simulate scans at all."""
    beams: int = 181
    """number of beams, evenly spread over the field of view."""
    fov_rad: float = np.pi
    """full field of view centred on the heading (rad)."""
    max_range_m: float = 12.0
    """beams that hit nothing report this range (m)."""
    range_std_m: float = 0.02
    """range noise standard deviation on hits (m)."""
    every: int = 1
    """take a scan every this many steps."""

    def __post_init__(self) -> None:
        check_positive(self, "fov_rad", "max_range_m")
        check_nonnegative(self, "range_std_m")
        if self.fov_rad > 2 * np.pi + 1e-12:  # beams past a full turn would repeat directions
            raise ValueError(f"LidarConfig.fov_rad must be <= 2*pi (got {self.fov_rad})")
        if self.beams < 1:
            raise ValueError(f"LidarConfig.beams must be >= 1 (got {self.beams})")
        if self.every < 1:
            raise ValueError(f"LidarConfig.every must be >= 1 (got {self.every})")

    def angles(self) -> Array:
        """Beam angles in the robot frame, shape (beams,)."""
        if self.beams == 1:
            return np.zeros(1)
        return np.linspace(-0.5 * self.fov_rad, 0.5 * self.fov_rad, self.beams)


def cast_rays(pose: ArrayLike, angles: ArrayLike, segments: ArrayLike, max_range: float) -> Array:
    """Distance along each beam to the first segment hit (``max_range`` when none is hit).

    Shapes: pose (3,), angles (B,), segments (W,4) as [x0, y0, x1, y1] -> (B,).
    Solves origin + t*d = a + s*(b - a) for every (beam, segment) pair at once; a hit needs t >= 0 and 0 <= s <= 1.
    """
    pose = np.asarray(pose, dtype=np.float64)
    ang = pose[2] + np.asarray(angles, dtype=np.float64)
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if seg.shape[0] == 0:
        return np.full(ang.shape, float(max_range))
    d = np.stack([np.cos(ang), np.sin(ang)], axis=-1)[:, None, :]  # (B,1,2)
    a = seg[None, :, :2]
    e = (seg[:, 2:] - seg[:, :2])[None]  # (1,W,2)
    w = a - pose[:2]  # (1,W,2)
    denom = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]  # cross(d, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / denom
        s = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t >= 0) & (s >= 0) & (s <= 1)
    t = np.where(hit, t, np.inf)
    return np.minimum(t.min(axis=1), max_range)


def simulate_scan(
    pose: ArrayLike, segments: ArrayLike, config: LidarConfig, rng: np.random.Generator
) -> Array:
    """A noisy scan; beams without a hit report ``config.max_range_m`` exactly."""
    angles = config.angles()
    r = cast_rays(pose, angles, segments, config.max_range_m)
    noise = rng.standard_normal(r.shape) * config.range_std_m
    hit = r < config.max_range_m
    return np.where(hit, np.clip(r + noise, 0.0, config.max_range_m), config.max_range_m)


def scan_to_points(ranges: ArrayLike, angles: ArrayLike, max_range: float) -> Array:
    """Beam endpoints in the robot frame for beams that hit something. Shapes: (B,),(B,) -> (K,2)."""
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    ok = np.isfinite(r) & (r < max_range) & (r > 0)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=-1)
