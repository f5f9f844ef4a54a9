"""Small records of the lifelong layers: the counters an estimator reports, and a compact pose buffer (both
re-exported by :mod:`slam2d.maps.layers`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class LayerStats:
    """Lifelong-mode counters of an estimator: keyframes, cells in the static layer, cells promoted into / demoted
    out of it so far, points labelled dynamic in the last scan and in all, bytes of the layer grids, tracking
    failures, floor-marker readings used as pose fixes, floor markers mapped on first sighting (unsurveyed ones)."""

    keyframes: int = 0
    static_cells: int = 0
    promoted: int = 0
    demoted: int = 0
    dynamic_points_last: int = 0
    dynamic_points_total: int = 0
    grid_bytes: int = 0
    tracking_failures: int = 0
    marker_fixes: int = 0
    markers_mapped: int = 0


class PoseBuffer:
    """Poses (3,) appended one at a time into fixed 4096-row blocks: 24 bytes a pose, no per-pose object."""

    BLOCK = 4096

    def __init__(self) -> None:
        self._blocks: list[Array] = []
        self._n = 0

    def append(self, pose: Array) -> None:
        if self._n % self.BLOCK == 0:
            self._blocks.append(np.empty((self.BLOCK, 3)))
        self._blocks[-1][self._n % self.BLOCK] = pose
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def array(self) -> Array:
        return np.concatenate(self._blocks)[: self._n] if self._blocks else np.zeros((0, 3))
