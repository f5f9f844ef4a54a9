"""TUM RGB-D trajectory files: one pose per line, ``timestamp tx ty tz qx qy qz qw`` (space separated).

A planar pose ``[x, y, theta]`` becomes ``tz = 0`` and the unit quaternion of a rotation by ``theta`` about z:
``(qx, qy, qz, qw) = (0, 0, sin(theta/2), cos(theta/2))``. Lines starting with ``#`` are comments. This is the format
of Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM Systems" (IROS 2012), read by tools such as evo.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry.angles import wrap_angle
from slam2d.io import bounded
from slam2d.io.atomic import atomic_write

Array = NDArray[np.float64]


def poses_to_tum(stamps_s: ArrayLike, poses: ArrayLike) -> Array:
    """Rows ``[t, x, y, 0, 0, 0, sin(theta/2), cos(theta/2)]``. Shapes: (N,),(N,3) -> (N,8)."""
    t = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] != t.shape[0]:
        raise ValueError(f"need stamps (N,) and poses (N,3) of equal length, got {t.shape} and {p.shape}")
    half = 0.5 * p[:, 2]
    zeros = np.zeros_like(t)
    return np.stack([t, p[:, 0], p[:, 1], zeros, zeros, zeros, np.sin(half), np.cos(half)], axis=-1)


def tum_to_poses(rows: ArrayLike) -> tuple[Array, Array]:
    """Inverse of :func:`poses_to_tum` for planar rows; the heading is the quaternion's rotation about z.

    Shapes: (N,8) -> (N,), (N,3). Raises ValueError when a pose leaves the plane (tz, qx or qy not ~0).
    """
    r = np.asarray(rows, dtype=np.float64)
    if r.ndim != 2 or r.shape[1] != 8:
        raise ValueError(f"TUM rows must have 8 columns, got shape {r.shape}")
    if r.size and np.max(np.abs(r[:, [3, 4, 5]])) > 1e-6:
        raise ValueError("TUM trajectory is not planar (tz, qx or qy is not zero)")
    theta = wrap_angle(2.0 * np.arctan2(r[:, 6], r[:, 7]))
    return r[:, 0].copy(), np.stack([r[:, 1], r[:, 2], theta], axis=-1)


def write_tum(path: str | Path, stamps_s: ArrayLike, poses: ArrayLike) -> Path:
    """Write a planar trajectory as a TUM file (full float precision). Shapes: (N,),(N,3)."""
    rows = poses_to_tum(stamps_s, poses)
    p = Path(path)
    with atomic_write(p) as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        np.savetxt(f, rows, fmt="%.17g")
    return p


def read_tum(path: str | Path) -> tuple[Array, Array]:
    """Read a planar TUM file written by :func:`write_tum` (or any planar one). Returns stamps (N,), poses (N,3)."""
    p = Path(path)
    rows: list[list[float]] = []
    for lineno, line in enumerate(bounded.iter_lines(p, ValueError), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise ValueError(f"{p}:{lineno}: expected 8 numbers (timestamp tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            rows.append([float(v) for v in parts])
        except ValueError:
            raise ValueError(f"{p}:{lineno}: not a number in {s!r}") from None
    return tum_to_poses(np.array(rows, dtype=np.float64).reshape(-1, 8))
