"""The lidar estimator's ``pose_cov``: the pose's marginal covariance in its pose graph, at bounded cost per scan.

A scan match's own covariance (ICP's ``sigma^2 (J^T J)^-1``) is the pose's uncertainty relative to the local map, a
few millimetres: reported as the pose's covariance it made the estimator's NEES run three orders of magnitude above
the chi-square band. The pose's uncertainty in the world is the graph's marginal, which grows along the keyframe
chain and shrinks when a loop enters. Kept here without a whole-graph factorisation per scan:

* the newest keyframe's marginal is exact after each whole-graph Gauss-Newton solve (read from that solve's
  factorisation, :meth:`slam2d.graph.incremental.IncrementalPoseGraph.newest_covariance`), and carried along each
  new keyframe edge in between: the linearised chain, which for a graph without loops equals its marginal;
* each scan's pose is the newest keyframe composed with the tracked relative pose, carried the same way with the
  covariance an edge to it would get.

Lifelong mode localises every scan in its static layer, which never moves: a pose is as uncertain as the map where
it matched plus the match itself. :meth:`PoseCovariance.in_layer` takes the map's uncertainty there to be that of the
nearest coverage keyframe (the pose that mapped that ground), so it grows while new ground is mapped and falls back
when old ground is seen again; a saved map's keyframes are its frame (zero).

Shapes: poses (3,), covariances (3,3).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from slam2d.geometry import se2

Array = NDArray[np.float64]


class PoseCovariance:
    """The newest keyframe's marginal (``keyframe``, world frame) and what the scans after it get from it."""

    def __init__(self, floor_xy_m: float, floor_theta_rad: float) -> None:
        self.floor = np.diag([floor_xy_m**2, floor_xy_m**2, floor_theta_rad**2])
        self.keyframe = np.zeros((3, 3))  # the first keyframe is the gauge: held, zero covariance
        self.coverage: list[Array] = []  # lifelong mode: each coverage keyframe's covariance when it was added
        self.current = np.zeros((3, 3))  # lifelong mode: the last scan's

    def in_layer(self, near_d2: Array, match_cov: Array, new_keyframe: bool) -> Array:
        """Lifelong mode: the scan's covariance, the nearest coverage keyframe's (squared distances ``near_d2``
        (K,); none yet: zero) plus the floored match's; ``new_keyframe``: the scan becomes a coverage keyframe."""
        base = self.coverage[int(np.argmin(near_d2))] if len(near_d2) else np.zeros((3, 3))
        self.current = base + match_cov + self.floor
        if new_keyframe:
            self.coverage.append(self.current)
        return self.current

    def edge(self, prev: Array, match_cov: Array) -> Array:
        """The covariance of a relative pose from keyframe pose ``prev`` measured by a scan match of world-frame
        covariance ``match_cov``: turned into ``prev``'s frame and floored (ICP's covariance misses wrong matches
        and the map's discretisation). Every keyframe edge's information is its inverse. (Turned by ``prev``'s
        heading, where the factor's error lies in the END pose's frame: off by the edge's own turn, at most
        ``keyframe_angle_rad``, which only matters for an anisotropic match; kept, since every lidar result
        depends on it.)"""
        return se2.covariance_in_frame(match_cov, float(prev[2])) + self.floor

    def carried(self, kf: Array, rel: Array, rel_cov: Array) -> Array:
        """The newest keyframe's marginal carried to ``compose(kf, rel)`` through a ``between`` factor of covariance
        ``rel_cov``, whose translation error lies in its END pose's frame (:func:`slam2d.graph.factors.eval_between`):
        the graph's own linearisation, so a chain of these equals the chain's marginal. Written out for one pose
        (:func:`slam2d.geometry.se2.compose_jacobians` is batched: ten times the cost, once a scan)."""
        c, s = math.cos(kf[2]), math.sin(kf[2])
        x, y = float(rel[0]), float(rel[1])
        ja = np.array([[1.0, 0.0, -s * x - c * y], [0.0, 1.0, c * x - s * y], [0.0, 0.0, 1.0]])
        return self._plus(ja @ self.keyframe @ ja.T, rel_cov, kf[2] + rel[2])

    @staticmethod
    def _plus(base: Array, cov: Array, theta: float) -> Array:
        """``base + J cov J^T`` with ``J`` the rotation by ``theta`` (on x, y), symmetrised."""
        c, s = math.cos(theta), math.sin(theta)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out = base + turn @ cov @ turn.T
        return np.asarray(0.5 * (out + out.T), dtype=np.float64)

    def keyframe_added(self, prev: Array, z: Array, edge_cov: Array, exact: Array | None) -> None:
        """A keyframe joined to the previous one (at ``prev``) by the edge ``z`` of covariance ``edge_cov``;
        ``exact``: its marginal when the graph was just solved whole (None: carried)."""
        self.keyframe = self.carried(prev, z, edge_cov) if exact is None else exact

    def at(self, kf: Array, rel: Array, match_cov: Array, is_keyframe: bool) -> Array:
        """``pose_cov`` of the scan at ``rel`` from the newest keyframe (at ``kf``), tracked with ``match_cov``
        (``is_keyframe``: the scan is that keyframe)."""
        if is_keyframe:
            return self.keyframe.copy()
        # edge(kf, match_cov) turned into kf's frame; here the rotation by -kf[2], written out
        return self.carried(kf, rel, self._plus(self.floor, match_cov, -kf[2]))
