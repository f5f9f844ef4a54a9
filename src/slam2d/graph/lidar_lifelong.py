"""Surveyed floor markers in the lidar back end's lifelong mode (``LidarSLAMConfig.surveyed_markers``).

The lifelong mode localises every scan against its static layer, so its error is the layer's: the first pass
draws the layer with the drift of scan matching (tens of centimetres over a 100 m warehouse) and every later pass
inherits it. A warehouse that surveys its floor markers (their positions in the map frame, to
``survey_sigma_m``) removes that: each reading of a surveyed marker is an absolute fix. After the scan's match, the
pose is corrected by a small Gauss-Newton solve

    min_x  (x - x_match)^T C^-1 (x - x_match) + sum_i |R(th)^T (m_i - t) - z_i|^2 / (std_cam^2 + sigma_survey^2)

where ``C`` is the match covariance plus a floor (``marker_match_sigma_xy_m``, ``marker_match_sigma_theta_rad``):
the match's Hessian counts every point as independent evidence, but all of them lean on the same layer, whose
error is one shared offset that the Hessian knows nothing about. The corrected pose is then used to label the
scan and draw the layers, so the first pass is drawn in the survey's frame and later passes are held there by the
layer and by the markers. Readings of markers not in the survey are ignored.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.models.floor_markers import marker_in_robot, marker_in_robot_jacobians

__all__ = ["MarkerSurvey", "fuse_marker_fixes"]

Array = NDArray[np.float64]


class MarkerSurvey:
    """Surveyed marker positions (id, x, y) in the map frame, looked up by id."""

    def __init__(self, surveyed: tuple[tuple[int, float, float], ...]) -> None:
        rows = np.asarray(surveyed, dtype=np.float64).reshape(-1, 3)
        ids = rows[:, 0].astype(np.int64)
        order = np.argsort(ids, kind="stable")
        self.ids = ids[order]
        self.xy = rows[order, 1:].copy()
        if len(self.ids) > 1 and np.any(np.diff(self.ids) == 0):
            dup = int(self.ids[1:][np.diff(self.ids) == 0][0])
            raise ValueError(f"LidarSLAMConfig.surveyed_markers: marker id {dup} is listed twice")
        self.fixes = 0  # readings used

    def __len__(self) -> int:
        return len(self.ids)

    def lookup(self, ids: ArrayLike) -> tuple[Array, NDArray[np.bool_]]:
        """(surveyed xy (K,2), known (K,)) of marker ``ids`` (K,); unknown ids get zeros and False."""
        q = np.asarray(ids, dtype=np.int64).reshape(-1)
        if not len(self.ids):
            return np.zeros((len(q), 2)), np.zeros(len(q), bool)
        k = np.clip(np.searchsorted(self.ids, q), 0, len(self.ids) - 1)
        known = self.ids[k] == q
        return np.where(known[:, None], self.xy[k], 0.0), known


def fuse_marker_fixes(pose: ArrayLike, cov: ArrayLike, readings: ArrayLike, markers: ArrayLike, variance: float,
                      iterations: int = 3) -> tuple[Array, Array]:
    """Correct ``pose`` (3,) with covariance ``cov`` (3,3) by readings ``readings`` (K,2) (robot frame) of markers at
    known ``markers`` (K,2) (map frame), each axis of each reading with ``variance``: Gauss-Newton on the
    objective of the module docstring. Returns (pose, covariance) of the fused estimate."""
    x0 = np.asarray(pose, dtype=np.float64).copy()
    z = np.asarray(readings, dtype=np.float64).reshape(-1, 2)
    m = np.asarray(markers, dtype=np.float64).reshape(-1, 2)
    prior = np.asarray(np.linalg.inv(np.asarray(cov, dtype=np.float64)), np.float64)
    x = x0.copy()
    h = prior
    for _ in range(iterations):
        r = marker_in_robot(x, m) - z  # (K,2)
        hp, _ = marker_in_robot_jacobians(np.broadcast_to(x, (len(m), 3)), m)  # (K,2,3)
        d = x - x0
        d[2] = float(np.arctan2(np.sin(d[2]), np.cos(d[2])))
        h = prior + np.einsum("kai,kaj->ij", hp, hp) / variance
        b = prior @ d + np.einsum("kai,ka->i", hp, r) / variance
        dx = -np.linalg.solve(h, b)
        x = x + dx
        x[2] = float(np.arctan2(np.sin(x[2]), np.cos(x[2])))
        if np.hypot(dx[0], dx[1]) < 1e-6 and abs(dx[2]) < 1e-7:
            break
    return x, np.asarray(np.linalg.inv(h), np.float64)
