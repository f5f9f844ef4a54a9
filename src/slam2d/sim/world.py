"""Worlds: static point landmarks, wall segments, and moving objects (forklifts) that follow closed paths."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MovingObject:
    """A box that drives around a closed polyline at constant speed; it reflects lidar and shows up as a point."""

    path: Array
    """(P,2) closed polyline (last point joins the first)."""
    speed_mps: float
    size_m: tuple[float, float] = (1.2, 0.8)

    def position(self, time_s: float) -> Array:
        """Centre at ``time_s``, shape (2,)."""
        pts = np.vstack([self.path, self.path[:1]])
        seg = np.diff(pts, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        s = (self.speed_mps * time_s) % lengths.sum()
        k = int(np.searchsorted(np.cumsum(lengths), s, side="right"))
        k = min(k, len(lengths) - 1)
        s0 = s - (np.cumsum(lengths)[k] - lengths[k])
        return pts[k] + seg[k] * (s0 / lengths[k])

    def segments(self, time_s: float) -> Array:
        """The box outline as four wall segments (axis aligned), shape (4,4)."""
        c = self.position(time_s)
        hx, hy = 0.5 * self.size_m[0], 0.5 * self.size_m[1]
        corners = c + np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        return np.hstack([corners, np.roll(corners, -1, axis=0)])


@dataclass(frozen=True)
class World:
    """Ground truth of a scenario. Shapes: landmarks (N,2), landmark_ids (N,), walls (W,4), descriptors (N,D)."""

    landmarks: Array
    landmark_ids: NDArray[np.int64]
    walls: Array
    descriptors: Array | None = None
    moving: tuple[MovingObject, ...] = field(default_factory=tuple)
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 10.0, 10.0)
    """(xmin, ymin, xmax, ymax) of the area the world occupies (m)."""

    def segments_at(self, time_s: float) -> Array:
        """Walls plus the outlines of moving objects at ``time_s``."""
        if not self.moving:
            return self.walls
        return np.vstack([self.walls, *[m.segments(time_s) for m in self.moving]])

    def solid_segments(self, time_s: float) -> Array:
        """What the robot cannot drive through: the static walls and the edge of ``bounds`` (worlds without walls
        are fenced by their bounds, so no robot ever leaves the world). Moving objects are not solid: a robot
        cannot stop a forklift that drives at it, and a drone flies over them. ``time_s`` is kept for worlds whose
        solid parts may one day move."""
        return np.vstack([self.walls, box_walls(*self.bounds)])

    def moving_positions(self, time_s: float) -> Array:
        """(M,2) centres of the moving objects."""
        return np.array([m.position(time_s) for m in self.moving]).reshape(-1, 2)


def box_walls(x0: float, y0: float, x1: float, y1: float) -> Array:
    """Four segments outlining an axis-aligned rectangle, shape (4,4)."""
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
    return np.hstack([c, np.roll(c, -1, axis=0)])
