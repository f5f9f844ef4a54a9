"""The lidar back end's lifelong mode (``layers`` set, ``--estimator lidar-lifelong``) and its surveyed floor markers
(``LidarSLAMConfig.surveyed_markers``).

The map is the static layer of :mod:`slam2d.maps.layers`, and every scan is localised against it (a fixed number of
points, a lookup per point, no search) from the odometry guess; points the layer labels dynamic take no part in the
match and never enter the static layer (they go to the decaying dynamic layer). A scan becomes a keyframe only where
no keyframe lies within ``coverage_m`` (keyframe culling by coverage: in mapped ground nothing is added, so
keyframes, the graph and the layers grow with the mapped area, never with time). Loop closure is off in this mode: a
revisit is matched against the map it made the first time, which bounds the error by the map's own; correcting a map
drawn with drift would need the layers re-drawn from moved keyframes, which this mode does not do. Surveyed floor
markers instead keep that drift out of the map: each reading corrects the matched pose before the scan is drawn
(below); unsurveyed markers can be mapped on their first sighting (``map_unsurveyed_markers``), which pins later
passes to that first pass, drift included.

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
layer and by the markers. Readings of markers not in the survey are ignored, unless ``map_unsurveyed_markers``:

Unsurveyed markers (``map_unsurveyed_markers``) are mapped on their first sighting: the mean of its readings at the
matched poses, frozen once the marker leaves the camera, with the match floor's variance (the poses of one sighting
share their error); later readings correct the pose like surveyed ones, with that variance added. Such a marker
carries the drift of the pass that mapped it, as the static layer does.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.models.floor_markers import marker_in_robot, marker_in_robot_jacobians

__all__ = ["LifelongMarkers", "MarkerSurvey", "fuse_marker_fixes"]

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


def fuse_marker_fixes(pose: ArrayLike, cov: ArrayLike, readings: ArrayLike, markers: ArrayLike,
                      variance: float | ArrayLike, iterations: int = 3) -> tuple[Array, Array]:
    """Correct ``pose`` (3,) with covariance ``cov`` (3,3) by readings ``readings`` (K,2) (robot frame) of markers at
    known ``markers`` (K,2) (map frame), each axis of reading k with ``variance`` (scalar or (K,)): Gauss-Newton on
    the objective of the module docstring. Returns (pose, covariance) of the fused estimate."""
    x0 = np.asarray(pose, dtype=np.float64).copy()
    z = np.asarray(readings, dtype=np.float64).reshape(-1, 2)
    m = np.asarray(markers, dtype=np.float64).reshape(-1, 2)
    w = np.broadcast_to(1.0 / np.asarray(variance, dtype=np.float64), (len(m),))[:, None, None]
    prior = np.asarray(np.linalg.inv(np.asarray(cov, dtype=np.float64)), np.float64)
    x = x0.copy()
    h = prior
    for _ in range(iterations):
        r = marker_in_robot(x, m) - z  # (K,2)
        hp, _ = marker_in_robot_jacobians(np.broadcast_to(x, (len(m), 3)), m)  # (K,2,3)
        d = x - x0
        d[2] = float(np.arctan2(np.sin(d[2]), np.cos(d[2])))
        h = prior + np.einsum("kai,kaj->ij", hp * w, hp)
        b = prior @ d + np.einsum("kai,ka->i", hp * w, r)
        dx = -np.linalg.solve(h, b)
        x = x + dx
        x[2] = float(np.arctan2(np.sin(x[2]), np.cos(x[2])))
        if np.hypot(dx[0], dx[1]) < 1e-6 and abs(dx[2]) < 1e-7:
            break
    return x, np.asarray(np.linalg.inv(h), np.float64)


class LifelongMarkers:
    """The lifelong mode's floor markers: surveyed ones (and, optionally, ones mapped on first sighting) turned into
    pose fixes (see the module docstring)."""

    def __init__(self, survey: MarkerSurvey, *, map_unsurveyed: bool, camera_var: float, survey_var: float,
                 match_floor: Array) -> None:
        self.survey = survey
        self.map_unsurveyed = map_unsurveyed
        self.camera_var, self.survey_var = camera_var, survey_var
        self.floor = np.asarray(match_floor, np.float64)
        self.mapped_var = float(self.floor[0, 0])  # a mapped marker shares the error of the poses that saw it
        self.fixes = 0  # readings used as fixes
        self._mapped: dict[int, Array] = {}  # frozen mapped markers: id -> map-frame position
        self._pending: dict[int, list[Array]] = {}  # markers in their first sighting: id -> readings in the map frame

    @property
    def mapped(self) -> int:
        """Markers mapped so far (their first sighting over)."""
        return len(self._mapped)

    def correct(self, pose: Array, cov: Array, ids: ArrayLike, xy: ArrayLike) -> tuple[Array, Array]:
        """The pose (and covariance) corrected by one camera reading: ``ids`` (K,), robot-frame ``xy`` (K,2)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        z = np.asarray(xy, np.float64).reshape(-1, 2)
        m, known = self.survey.lookup(ids)
        var = np.full(len(ids), self.camera_var + self.survey_var)
        if self.map_unsurveyed:
            for k, i in enumerate(ids.tolist()):
                if not known[k] and i in self._mapped:
                    m[k], known[k], var[k] = self._mapped[i], True, self.camera_var + self.mapped_var
        if known.any():
            pose, cov = fuse_marker_fixes(pose, cov + self.floor, z[known], m[known], var[known])
            self.fixes += int(np.count_nonzero(known))
        if self.map_unsurveyed:
            here = set(ids.tolist())
            for i in [i for i in self._pending if i not in here]:  # left the camera: its first sighting is over
                self._mapped[i] = np.mean(self._pending.pop(i), axis=0)
            c, s = np.cos(pose[2]), np.sin(pose[2])
            for k in np.flatnonzero(~known).tolist():
                world = pose[:2] + np.array([c * z[k, 0] - s * z[k, 1], s * z[k, 0] + c * z[k, 1]])
                self._pending.setdefault(int(ids[k]), []).append(world)
        return pose, cov
