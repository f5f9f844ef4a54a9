"""Lidar scan features: beam endpoints, line segments by split-and-merge, and corners where neighbouring segments meet.

Split-and-merge (Nguyen et al. 2005 compare it with other line extractors): the scan's points, in beam order, are
first cut into runs at no-return beams and at jumps larger than ``max_gap_m``. A run is split at the point farthest
from the chord between its ends while that distance exceeds ``split_threshold_m``; then neighbouring pieces whose
union still fits one line (total least squares, max residual below the threshold) are merged. Each piece is
fitted by total least squares (PCA) and kept if it has ``min_points`` points and ``min_length_m`` of extent.

Corners: two consecutive segments (in beam order) whose directions differ by at least ``min_corner_angle_rad`` and
whose line intersection lies within ``max_corner_gap_m`` of both segments' facing ends. Corners are point features
in the scan frame, so they can be handed to landmark back ends as range-bearing observations
(:func:`corner_observations`).

The per-point work (distances to a chord, fits) is vectorised; the loop runs over pieces of the scan (tens per
scan), never over beams.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_positive
from slam2d.log import Scan

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class LineExtractionConfig:
    """Split-and-merge and corner settings."""

    split_threshold_m: float = 0.05
    """split a piece where a point is farther than this from the chord / merged fit (m)."""
    max_gap_m: float = 0.3
    """consecutive points farther apart than this start a new run (m)."""
    min_points: int = 6
    """a segment needs at least this many points."""
    min_length_m: float = 0.3
    """a segment must be at least this long (m)."""
    min_corner_angle_rad: float = np.deg2rad(30.0)
    """two segments meeting at less than this angle do not make a corner (rad)."""
    max_corner_gap_m: float = 0.3
    """the line intersection must lie within this distance of both segments' facing ends (m)."""

    def __post_init__(self) -> None:
        check_positive(self, "split_threshold_m", "max_gap_m", "min_length_m", "min_corner_angle_rad",
                       "max_corner_gap_m")
        if self.min_points < 2:
            raise ValueError(f"LineExtractionConfig.min_points must be >= 2 (got {self.min_points})")


@dataclass(frozen=True)
class LineSegments:
    """Fitted segments in the scan frame. Shapes (L segments): start (L,2), end (L,2) (projected onto the fitted line,
    in beam order), normal_angle (L,) and distance (L,) of the line ``x cos a + y sin a = d`` (d >= 0), first and last
    (L,) point indices into the input scan, rms (L,) fit residual (m)."""

    start: Array
    end: Array
    normal_angle: Array
    distance: Array
    first: NDArray[np.int64]
    last: NDArray[np.int64]
    rms: Array

    def __len__(self) -> int:
        return int(self.start.shape[0])

    @property
    def length(self) -> Array:
        return np.hypot(*(self.end - self.start).T)


def _fit(p: Array) -> tuple[float, float, float, float]:
    """Total least squares line through points (N,2): (normal angle, distance, rms, max residual)."""
    m = p.mean(axis=0)
    c = p - m
    _, vec = np.linalg.eigh(c.T @ c)
    n = vec[:, 0]
    d = float(n @ m)
    if d < 0:
        n, d = -n, -d
    r = c @ n
    return float(np.arctan2(n[1], n[0])), d, float(np.sqrt(np.mean(r**2))), float(np.max(np.abs(r)))


def _chord_split(p: Array, thr: float) -> int | None:
    """Index of the point farthest from the chord p[0]-p[-1], or None if all are within ``thr``."""
    a, b = p[0], p[-1]
    ab = b - a
    L = float(np.hypot(*ab))
    if L < 1e-12:
        d = np.hypot(*(p - a).T)
    else:
        d = np.abs(ab[0] * (p[:, 1] - a[1]) - ab[1] * (p[:, 0] - a[0])) / L
    k = int(np.argmax(d[1:-1])) + 1 if len(p) > 2 else 0
    return k if len(p) > 2 and d[k] > thr else None


def extract_lines(ranges: ArrayLike, angles: ArrayLike, max_range: float,
                  config: LineExtractionConfig | None = None) -> LineSegments:
    """Line segments of one scan. Shapes: ranges (B,), angles (B,) in beam order.

    NaN, inf, non-positive and max-range readings are no-returns: they break runs and are never part of a line.
    """
    cfg = config or LineExtractionConfig()
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    if r.shape != a.shape:
        raise ValueError(f"extract_lines: ranges {r.shape} and angles {a.shape} differ in shape")
    ok = np.isfinite(r) & (r > 0) & (r < max_range)
    pts = np.stack([np.where(ok, r, 0) * np.cos(a), np.where(ok, r, 0) * np.sin(a)], axis=-1)
    idx = np.flatnonzero(ok)
    if len(idx) < cfg.min_points:
        return _empty()
    # runs: break at no-return beams (index jumps) and at big spatial gaps
    gap = np.hypot(*np.diff(pts[idx], axis=0).T)
    breaks = np.flatnonzero((np.diff(idx) > 1) | (gap > cfg.max_gap_m)) + 1
    runs = [run for run in np.split(idx, breaks) if len(run) >= cfg.min_points]

    pieces: list[NDArray[np.int64]] = []
    for run in runs:
        stack = [run]
        out: list[NDArray[np.int64]] = []
        while stack:  # split, keeping beam order (right part pushed first so the left is processed first)
            cur = stack.pop()
            k = _chord_split(pts[cur], cfg.split_threshold_m)
            if k is None:
                out.append(cur)
            else:
                stack.append(cur[k:])
                stack.append(cur[: k + 1] if k + 1 < len(cur) else cur)
        # merge neighbours that still fit one line
        merged: list[NDArray[np.int64]] = []
        for piece in out:
            if merged:
                both = np.union1d(merged[-1], piece)
                if _fit(pts[both])[3] <= cfg.split_threshold_m:
                    merged[-1] = both
                    continue
            merged.append(piece)
        pieces += merged

    rows = []
    for piece in pieces:
        if len(piece) < cfg.min_points:
            continue
        alpha, d, rms, _ = _fit(pts[piece])
        n = np.array([np.cos(alpha), np.sin(alpha)])
        t = np.array([-n[1], n[0]])
        s = pts[piece] @ t
        start, end = d * n + s[0] * t, d * n + s[-1] * t
        if np.hypot(*(end - start)) < cfg.min_length_m:
            continue
        rows.append((start, end, alpha, d, piece[0], piece[-1], rms))
    if not rows:
        return _empty()
    return LineSegments(np.array([r_[0] for r_ in rows]), np.array([r_[1] for r_ in rows]),
                        np.array([r_[2] for r_ in rows]), np.array([r_[3] for r_ in rows]),
                        np.array([r_[4] for r_ in rows], dtype=np.int64),
                        np.array([r_[5] for r_ in rows], dtype=np.int64), np.array([r_[6] for r_ in rows]))


def _empty() -> LineSegments:
    z = np.zeros(0)
    zi = np.zeros(0, dtype=np.int64)
    return LineSegments(np.zeros((0, 2)), np.zeros((0, 2)), z, z.copy(), zi, zi.copy(), z.copy())


def line_corners(lines: LineSegments, config: LineExtractionConfig | None = None) -> Array:
    """Corners where consecutive segments meet (all pairs at once). Shapes: -> (C,2) in the scan frame."""
    cfg = config or LineExtractionConfig()
    if len(lines) < 2:
        return np.zeros((0, 2))
    a1, d1 = lines.normal_angle[:-1], lines.distance[:-1]
    a2, d2 = lines.normal_angle[1:], lines.distance[1:]
    # angle between the two lines, folded to [0, pi/2]
    diff = np.abs(np.mod(a2 - a1 + np.pi / 2, np.pi) - np.pi / 2)
    det = np.cos(a1) * np.sin(a2) - np.sin(a1) * np.cos(a2)
    safe = np.where(np.abs(det) > 1e-9, det, 1.0)
    x = (d1 * np.sin(a2) - d2 * np.sin(a1)) / safe
    y = (np.cos(a1) * d2 - np.cos(a2) * d1) / safe
    c = np.stack([x, y], axis=-1)
    near1 = np.hypot(*(c - lines.end[:-1]).T)
    near2 = np.hypot(*(c - lines.start[1:]).T)
    ok = (np.abs(det) > 1e-9) & (diff >= cfg.min_corner_angle_rad) & (near1 <= cfg.max_corner_gap_m) & (
        near2 <= cfg.max_corner_gap_m)
    return c[ok]


def corner_observations(corners: ArrayLike) -> Array:
    """Corners (C,2) in the scan frame as [range, bearing] observations (C,2) for landmark back ends."""
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    return np.stack([np.hypot(c[:, 0], c[:, 1]), np.arctan2(c[:, 1], c[:, 0])], axis=-1)


def scan_points(scan: Scan, min_range: float, max_range: float) -> Array:
    """Endpoints (K,2) in the scan frame of beams that hit within [min_range, min(max_range, scan max)) m."""
    r = np.asarray(scan.ranges_m, dtype=np.float64)
    a = np.asarray(scan.angles_rad, dtype=np.float64)
    ok = np.isfinite(r) & (r > min_range) & (r < min(max_range, scan.max_range_m))
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=-1)
