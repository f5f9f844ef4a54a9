"""Worlds: static point landmarks, wall segments, floor markers, and moving objects (forklifts) on closed paths."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

_TILE_M = 5.0  # tile side of the wall lookup in World.segments_near


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

    def marker_survey(self, sigma_m: float, rng: np.random.Generator) -> tuple[tuple[int, float, float], ...]:
        """The floor markers as a survey of the floor would give them (:func:`marker_survey`)."""
        return marker_survey(self.floor_markers, sigma_m, rng)

    @cached_property
    def _fleet(self) -> dict[str, Array]:
        """Every moving object's path padded to the longest one, so all of them are placed in one pass."""
        n, p = len(self.moving), max((len(m.path) for m in self.moving), default=0)
        pts = np.zeros((n, p + 1, 2))
        seg = np.zeros((n, p, 2))
        lengths = np.ones((n, p))
        cum = np.full((n, p), np.inf)  # padding never counts as a passed leg
        legs = np.zeros(n, dtype=np.int64)
        for i, m in enumerate(self.moving):
            mp, ms, ml, mc = m._legs
            k = len(ml)
            pts[i, : k + 1], seg[i, :k], lengths[i, :k], cum[i, :k], legs[i] = mp, ms, ml, mc, k
        half = np.array([[0.5 * m.size_m[0], 0.5 * m.size_m[1]] for m in self.moving]).reshape(n, 2)
        return {"pts": pts, "seg": seg, "lengths": lengths, "cum": cum, "legs": legs,
                "total": cum[np.arange(n), legs - 1] if n else np.zeros(0),
                "speed": np.array([m.speed_mps for m in self.moving]),
                "phase": np.array([m.phase_m for m in self.moving]),
                "aligned": np.array([m.heading_aligned for m in self.moving], dtype=bool),
                "local": half[:, None, :] * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])}

    def _fleet_state(self, time_s: float) -> tuple[Array, Array]:
        """(M,2) centres and (M,2) unit directions of travel: :meth:`MovingObject._locate` for all at once."""
        f = self._fleet
        rows = np.arange(len(self.moving))
        s = (f["speed"] * time_s + f["phase"]) % f["total"]
        k = np.minimum(np.sum(f["cum"] <= s[:, None], axis=1), f["legs"] - 1)
        length = f["lengths"][rows, k]
        s0 = s - (f["cum"][rows, k] - length)
        seg = f["seg"][rows, k]
        return f["pts"][rows, k] + seg * (s0 / length)[:, None], seg / length[:, None]

    def segments_at(self, time_s: float) -> Array:
        """Walls plus the outlines of moving objects at ``time_s``."""
        if not self.moving:
            return self.walls
        centre, d = self._fleet_state(time_s)
        local = self._fleet["local"]  # (M,4,2)
        aligned = self._fleet["aligned"]
        if np.any(aligned):  # rotate the boxes that face along their path: R(d) @ corner
            rot = np.stack([local[..., 0] * d[:, None, 0] - local[..., 1] * d[:, None, 1],
                            local[..., 0] * d[:, None, 1] + local[..., 1] * d[:, None, 0]], axis=-1)
            local = np.where(aligned[:, None, None], rot, local)
        corners = centre[:, None, :] + local
        boxes = np.concatenate([corners, np.roll(corners, -1, axis=1)], axis=-1).reshape(-1, 4)
        return np.vstack([self.walls, boxes])

    def segments_near(self, time_s: float, xy: Array, radius_m: float) -> Array:
        """The segments of :meth:`segments_at` that a lidar at ``xy`` with range ``radius_m`` could hit: every one
        within ``radius_m`` of ``xy`` (and a few a little farther; those can only report hits beyond the range).

        Walls are looked up per 5 m tile (cached: the tile's walls within ``radius_m`` plus half the tile's diagonal
        of its centre), so a big warehouse's thousands of segments are not all measured at every scan."""
        p = np.asarray(xy, dtype=np.float64)
        key = (int(np.floor(p[0] / _TILE_M)), int(np.floor(p[1] / _TILE_M)), float(radius_m))
        walls = self._tile_cache.get(key)
        if walls is None:
            centre = (np.array(key[:2], dtype=np.float64) + 0.5) * _TILE_M
            reach = radius_m + _TILE_M / np.sqrt(2.0) + 1e-9
            walls = self.walls[segment_distances(centre, self.walls) <= reach]
            self._tile_cache[key] = walls
        if not self.moving:
            return walls
        boxes = self.segments_at(time_s)[len(self.walls):]
        keep = segment_distances(p, boxes) <= radius_m
        # a forklift right under the sensor is being flown over: it does not wrap the scan in its own box
        keep &= ~np.repeat(self._contains(time_s, p), 4)
        return np.vstack([walls, boxes[keep]])

    def _contains(self, time_s: float, p: Array) -> NDArray[np.bool_]:
        """(M,) whether each moving object's box contains point ``p``."""
        centre, d = self._fleet_state(time_s)
        rel = p - centre
        aligned = self._fleet["aligned"]
        along = np.where(aligned, rel[:, 0] * d[:, 0] + rel[:, 1] * d[:, 1], rel[:, 0])
        across = np.where(aligned, -rel[:, 0] * d[:, 1] + rel[:, 1] * d[:, 0], rel[:, 1])
        half = self._fleet["local"][:, 2]  # (hx, hy)
        return np.asarray((np.abs(along) <= half[:, 0]) & (np.abs(across) <= half[:, 1]), dtype=bool)

    @cached_property
    def _tile_cache(self) -> dict[tuple[int, int, float], Array]:
        return {}

    def solid_segments(self, time_s: float) -> Array:
        """What the robot cannot drive through: the static walls and the edge of ``bounds`` (worlds without walls
        are fenced by their bounds, so no robot ever leaves the world). Moving objects are not solid: a robot
        cannot stop a forklift that drives at it, and a drone flies over them. ``time_s`` is kept for worlds whose
        solid parts may one day move."""
        return np.vstack([self.walls, box_walls(*self.bounds)])

    def moving_positions(self, time_s: float) -> Array:
        """(M,2) centres of the moving objects."""
        if not self.moving:
            return np.zeros((0, 2))
        return self._fleet_state(time_s)[0]


def marker_survey(markers: Array, sigma_m: float, rng: np.random.Generator) -> tuple[tuple[int, float, float], ...]:
    """True floor markers (M,2) (marker ``i`` has id ``i``) as a survey of the floor would give them: (id, x, y),
    each position off the truth by a normal draw of ``sigma_m`` per axis. Empty without markers."""
    xy = markers + rng.normal(0.0, sigma_m, markers.shape)
    return tuple((i, float(x), float(y)) for i, (x, y) in enumerate(xy.tolist()))


def segment_distances(p: Array, segments: Array) -> Array:
    """Distance from points ``p`` (..., 2) to each segment (W,4) -> (..., W)."""
    a, b = segments[:, :2], segments[:, 2:]
    ab = b - a
    den = np.maximum(np.sum(ab * ab, axis=1), 1e-18)
    ap = np.asarray(p, dtype=np.float64)[..., None, :] - a
    t = np.clip(np.sum(ap * ab, axis=-1) / den, 0.0, 1.0)
    d = ap - t[..., None] * ab
    return np.hypot(d[..., 0], d[..., 1])


def box_walls(x0: float, y0: float, x1: float, y1: float) -> Array:
    """Four segments outlining an axis-aligned rectangle, shape (4,4)."""
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
    return np.hstack([c, np.roll(c, -1, axis=0)])
