"""Solid walls for the true robot: a motion that would take the robot's disc into a wall (or across one) is
stopped, keeping only its rotation. The simulator applies this to every step, so every driver (keys, route,
explore) and every scenario obeys it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry import se2

Array = NDArray[np.float64]

#: radius of the robot's footprint (m): its centre never comes closer than this to a wall
ROBOT_RADIUS_M = 0.3


def clearance(points: ArrayLike, segments: ArrayLike) -> Array:
    """Distance from each point to the nearest segment (inf without segments). Shapes: (N,2), (W,4) -> (N,)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    s = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(s) == 0:
        return np.full(len(p), np.inf)
    a, d = s[:, :2], s[:, 2:] - s[:, :2]
    t = np.einsum("nwk,wk->nw", p[:, None, :] - a[None], d) / np.maximum(np.einsum("wk,wk->w", d, d), 1e-300)
    q = a[None] + np.clip(t, 0.0, 1.0)[..., None] * d[None]
    return np.asarray(np.linalg.norm(p[:, None, :] - q, axis=-1).min(axis=1))


def crosses(start: ArrayLike, end: ArrayLike, segments: ArrayLike) -> bool:
    """True when the straight move ``start -> end`` properly intersects a segment. Shapes: (2,), (2,), (W,4)."""
    p, r = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64) - np.asarray(start, np.float64)
    s = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(s) == 0 or not np.any(r):
        return False
    q, e = s[:, :2], s[:, 2:] - s[:, :2]
    den = r[0] * e[:, 1] - r[1] * e[:, 0]
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[:, 0] * e[:, 1] - qp[:, 1] * e[:, 0]) / den
        u = (qp[:, 0] * r[1] - qp[:, 1] * r[0]) / den
    return bool(np.any((den != 0) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)))


def allowed_motion(pose: ArrayLike, u: ArrayLike, segments: ArrayLike, radius_m: float = ROBOT_RADIUS_M
                   ) -> tuple[Array, bool]:
    """The part of the relative motion ``u`` (in the robot frame) the walls allow, and whether it was blocked.

    A move is allowed when it crosses no segment and ends at least ``radius_m`` from every segment, or when it
    increases the clearance (so a robot already too close can always back away). A blocked move keeps its rotation
    and loses its translation. Shapes: pose (3,), u (3,), segments (W,4) -> ((3,), bool).
    """
    pose = np.asarray(pose, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if not np.any(u[:2]):
        return u, False
    end = se2.compose(pose, u)
    before, after = clearance(np.vstack([pose[:2], end[:2]]), segments)
    if not crosses(pose[:2], end[:2], segments) and (after >= radius_m or after > before):
        return u, False
    return np.array([0.0, 0.0, u[2]]), True
