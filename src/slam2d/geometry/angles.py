"""Angle wrapping: the one place where headings are brought into range.

Convention: every wrapped angle lies in the half-open interval [-pi, pi).
``wrap_angle(pi) == -pi`` and ``wrap_angle(-pi) == -pi``; a test pins this.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

TWO_PI = 2.0 * np.pi


def wrap_angle(angle: ArrayLike) -> NDArray[np.float64]:
    """Wrap angles to [-pi, pi), keeping shape.

    Shapes: any -> same.
    """
    a = np.asarray(angle, dtype=np.float64)
    r = np.mod(a + np.pi, TWO_PI) - np.pi
    # np.mod can round up to exactly 2*pi for inputs a hair below -pi; fold it back.
    return np.where(r >= np.pi, r - TWO_PI, r)


def angle_diff(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Signed difference ``a - b`` wrapped to [-pi, pi). Every angular residual goes through here."""
    return wrap_angle(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))


def wrap_angle_scalar(angle: float) -> float:
    """Scalar twin of :func:`wrap_angle` (same [-pi, pi) convention) for per-observation hot paths, where a numpy
    call's overhead dominates; a test checks that the two agree, boundaries included."""
    r = (angle + math.pi) % (2.0 * math.pi) - math.pi
    return r - 2.0 * math.pi if r >= math.pi else r
