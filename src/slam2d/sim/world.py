"""Worlds: static point landmarks, wall segments, floor markers, and moving objects (forklifts) on closed paths."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

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
    """(x, y) extent of the box; with ``heading_aligned`` (length, width) along the direction of travel."""
    heading_aligned: bool = False
    """turn the box to face along the path segment it is on (otherwise it stays axis aligned)."""
    phase_m: float = 0.0
    """distance along the path at time 0 (m)."""

    @cached_property
    def _legs(self) -> tuple[Array, Array, Array, Array]:
        """Path corners (closed), leg vectors, leg lengths and their running sum (computed once)."""
        pts = np.vstack([self.path, self.path[:1]])
        seg = np.diff(pts, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        return pts, seg, lengths, np.cumsum(lengths)

    def _locate(self, time_s: float) -> tuple[Array, Array]:
        """Centre (2,) and unit direction of travel (2,) at ``time_s``."""
        pts, seg, lengths, cum = self._legs
        s = (self.speed_mps * time_s + self.phase_m) % cum[-1]
        k = int(np.searchsorted(cum, s, side="right"))
        k = min(k, len(lengths) - 1)
        s0 = s - (cum[k] - lengths[k])
        return pts[k] + seg[k] * (s0 / lengths[k]), seg[k] / lengths[k]

    def position(self, time_s: float) -> Array:
        """Centre at ``time_s``, shape (2,)."""
        return self._locate(time_s)[0]

    def corners(self, time_s: float) -> Array:
        """The box's four corners at ``time_s``, shape (4,2), counter-clockwise."""
        c, d = self._locate(time_s)
        hx, hy = 0.5 * self.size_m[0], 0.5 * self.size_m[1]
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        if self.heading_aligned:
            local = local @ np.array([[d[0], d[1]], [-d[1], d[0]]])
        return c + local

    def segments(self, time_s: float) -> Array:
        """The box outline as four wall segments, shape (4,4)."""
        corners = self.corners(time_s)
        return np.hstack([corners, np.roll(corners, -1, axis=0)])


@dataclass(frozen=True)
class World:
    """Ground truth of a scenario. Shapes: landmarks (N,2), landmark_ids (N,), walls (W,4), descriptors (N,D),
    floor_markers (M,2) (marker ``i`` has id ``i``)."""

    landmarks: Array
    landmark_ids: NDArray[np.int64]
    walls: Array
    descriptors: Array | None = None
    moving: tuple[MovingObject, ...] = field(default_factory=tuple)
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 10.0, 10.0)
    """(xmin, ymin, xmax, ymax) of the area the world occupies (m)."""
    floor_markers: Array = field(default_factory=lambda: np.zeros((0, 2)))

    def segments_at(self, time_s: float) -> Array:
        """Walls plus the outlines of moving objects at ``time_s``."""
        if not self.moving:
            return self.walls
        return np.vstack([self.walls, *[m.segments(time_s) for m in self.moving]])

    def segments_near(self, time_s: float, xy: Array, radius_m: float) -> Array:
        """The segments of :meth:`segments_at` that come within ``radius_m`` of ``xy``: a lidar with that range
        cannot see the others, and a big warehouse has thousands of them (an O(W) cull before the O(B x W) cast)."""
        seg = self.segments_at(time_s)
        return seg[segment_distances(np.asarray(xy, dtype=np.float64), seg) <= radius_m]

    def moving_positions(self, time_s: float) -> Array:
        """(M,2) centres of the moving objects."""
        return np.array([m.position(time_s) for m in self.moving]).reshape(-1, 2)


def segment_distances(p: Array, segments: Array) -> Array:
    """Distance from point ``p`` (2,) to each segment (W,4) -> (W,)."""
    a, b = segments[:, :2], segments[:, 2:]
    ab = b - a
    den = np.maximum(np.sum(ab * ab, axis=1), 1e-18)
    t = np.clip(np.sum((p - a) * ab, axis=1) / den, 0.0, 1.0)
    q = a + t[:, None] * ab
    return np.hypot(p[0] - q[:, 0], p[1] - q[:, 1])


def box_walls(x0: float, y0: float, x1: float, y1: float) -> Array:
    """Four segments outlining an axis-aligned rectangle, shape (4,4)."""
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
    return np.hstack([c, np.roll(c, -1, axis=0)])
