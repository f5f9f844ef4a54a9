"""Floor markers in the lidar back end: marker nodes in the keyframe pose graph, re-sightings closing loops.

A floor marker (:mod:`slam2d.models.floor_markers`) is read with its id, so its association is certain: every
reading becomes a ``point`` factor (:mod:`slam2d.graph.factors`, ``e = R(th)^T (m - t) - z``, the marker model's
own measurement function) between a keyframe and the marker's 2D node, with the information of the camera's noise
in the keyframe frame. A marker read again after ``loop_min_separation`` keyframes ties the new keyframe to the old
ones through its node: a loop closure no scan matcher has to find, and one that fixes the position along an aisle,
where scans see no end.

Readings between keyframes are attached to the newest keyframe through the tracked pose relative to it (the lidar
tracking over less than one keyframe spacing, a few millimetres; its uncertainty is added as ``attach_sigma_per_m``
per metre of that offset). Making a keyframe per reading would add graph nodes at every marker pass (a reading
comes every step a marker is under the camera), and the tracked offset is far more certain than the marker's own
noise budget. One reading per (keyframe, marker) is kept: the first, the one with the smallest offset.

A re-sighting is solved like a loop: a local solve (newest ``window`` keyframes plus the neighbourhood of each old
keyframe that saw the marker, every other keyframe held fixed), then ``loop_full_iterations`` Gauss-Newton
iterations on the whole graph (the lidar estimator's rule for loops); other readings only add factors, which the
next solve uses. Without any marker reading the graph is :class:`~slam2d.graph.incremental.IncrementalPoseGraph`
exactly (every method defers to it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.geometry import se2
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.incremental import IncrementalConfig, IncrementalPoseGraph
from slam2d.graph.optimizer import Optimizer, OptimizerConfig, Summary
from slam2d.log import MarkerReadings
from slam2d.models.floor_markers import FloorCameraConfig

__all__ = ["KeyframeMarkers", "MarkerPoseGraph", "MarkerSettings"]

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, slots=True, kw_only=True)
class MarkerSettings:
    """How the lidar back end uses floor-marker readings (when a step carries any)."""

    enabled: bool = True
    """use the readings (False: ignore them, the back end as it is without markers)."""
    camera: FloorCameraConfig = field(default_factory=FloorCameraConfig)
    """the camera model whose ``std_m`` sets a reading's information."""
    attach_sigma_per_m: float = 0.02
    """standard deviation added per metre of tracked motion between a reading and its keyframe (m/m)."""
    resight_keyframes: int = 30
    """a marker read again this many keyframes after its last reading triggers a loop-like solve."""
    full_iterations: int = 5
    """whole-graph Gauss-Newton iterations after a re-sighting (0: the local solve only)."""

    def __post_init__(self) -> None:
        if self.attach_sigma_per_m < 0:
            raise ValueError(f"MarkerSettings.attach_sigma_per_m must be >= 0 (got {self.attach_sigma_per_m})")
        if self.resight_keyframes < 1 or self.full_iterations < 0:
            raise ValueError("MarkerSettings.resight_keyframes must be >= 1 and full_iterations >= 0 (got "
                             f"{self.resight_keyframes}, {self.full_iterations})")


class MarkerPoseGraph(IncrementalPoseGraph):
    """:class:`IncrementalPoseGraph` with marker nodes (point keys 0..M-1 in order of first reading) and ``point``
    factors from keyframes to them."""

    def __init__(self, initial_pose: Array, config: IncrementalConfig | None = None) -> None:
        super().__init__(initial_pose, config)
        self.marker_ids: list[int] = []
        self._slot: dict[int, int] = {}
        self._markers = np.zeros((0, 2))
        self._o_pose: list[int] = []  # per observation: keyframe, marker slot, z (2,), information (2,2)
        self._o_slot: list[int] = []
        self._o_z: list[Array] = []
        self._o_info: list[Array] = []
        self._of_pose: dict[int, list[int]] = {}  # keyframe -> its observations
        self._of_slot: list[list[int]] = []  # marker slot -> its observations

    @property
    def markers(self) -> Array:
        """(M, 2) marker estimates, in the order of :attr:`marker_ids`."""
        return self._markers

    @property
    def num_observations(self) -> int:
        return len(self._o_pose)

    def observers(self, marker_id: int) -> list[int]:
        """Keyframes that read ``marker_id`` (in reading order; empty for an unknown id)."""
        s = self._slot.get(int(marker_id))
        return [] if s is None else [self._o_pose[o] for o in self._of_slot[s]]

    def add_marker_observations(self, pose: int, ids: IntArray, z: Array, information: Array) -> None:
        """Readings (K,) of existing keyframe ``pose``: ``z`` (K,2) in its frame, ``information`` (K,2,2). A new
        marker starts at the keyframe's estimate composed with its reading. No solve here."""
        if not 0 <= pose < self.num_poses:
            raise ValueError(f"add_marker_observations: keyframe {pose} does not exist ({self.num_poses} keyframes)")
        self._factored = None  # marker factors are not in the last full solve's factorisation
        for mid, zk, ik in zip(np.asarray(ids, np.int64).tolist(), np.asarray(z, np.float64).reshape(-1, 2),
                               np.asarray(information, np.float64).reshape(-1, 2, 2), strict=True):
            s = self._slot.get(mid)
            if s is None:
                s = self._slot[mid] = len(self.marker_ids)
                self.marker_ids.append(mid)
                self._of_slot.append([])
                self._markers = np.vstack([self._markers, se2.transform_points(self._poses[pose], zk[None])])
            o = len(self._o_pose)
            self._o_pose.append(pose)
            self._o_slot.append(s)
            self._o_z.append(zk.copy())
            self._o_info.append(ik.copy())
            self._of_pose.setdefault(pose, []).append(o)
            self._of_slot[s].append(o)

    def solve_resighting(self, old_poses: list[int], full_iterations: int) -> None:
        """A re-sighting's solve: local around the newest keyframes and ``old_poses``, then whole-graph iterations."""
        self._solve_local(self.num_poses - 1, np.asarray(sorted(set(old_poses)), np.int64))
        if full_iterations:
            self._solve_full(full_iterations)

    # ------------------------------------------------------------------ solves with marker factors
    def _with_markers(self, g: FactorGraph, obs: IntArray) -> tuple[FactorGraph, IntArray, IntArray]:
        """Add the ``point`` factors ``obs``; (graph, their keyframes, their marker slots)."""
        pose = np.asarray(self._o_pose, np.int64)[obs]
        slot = np.asarray(self._o_slot, np.int64)[obs]
        if len(obs):
            g.add_point(pose, slot, np.asarray(self._o_z)[obs], np.asarray(self._o_info)[obs])
        return g, pose, slot

    def _solve_local(self, t: int, loops: NDArray[np.int64]) -> None:
        if not self._o_pose:
            super()._solve_local(t, loops)
            return
        c = self.config
        free_arr, edges = self._local_region(t, loops)
        # every marker a free keyframe read is free; all its readings enter (the old readers held fixed)
        slots = sorted({self._o_slot[o] for p in free_arr.tolist() for o in self._of_pose.get(p, [])})
        obs = np.asarray(sorted(o for s in slots for o in self._of_slot[s]), np.int64)
        g, opose, _ = self._with_markers(self._graph(edges), obs)
        touched = np.unique(np.concatenate([self._ei[edges], self._ej[edges], opose]))
        fixed = np.setdiff1d(touched, free_arr)
        if fixed.size == 0:
            fixed = touched[:1]
        sl = np.asarray(slots, np.int64)
        vals = Values(touched, self._poses[touched], sl, self._markers[sl])
        out, _ = Optimizer(g, OptimizerConfig(method="gn", max_iterations=c.iterations),
                           fixed_pose_keys=fixed).optimize(vals)
        self._poses[out.pose_keys] = out.poses
        if len(out.point_keys):
            self._markers[out.point_keys] = out.points
        self.local_solves += 1

    def _solve_full(self, iterations: int, method: str = "gn") -> Summary:
        if not self._o_pose:
            return super()._solve_full(iterations, method)
        n = self.num_poses
        g, _, _ = self._with_markers(self._graph(np.arange(self.num_edges)), np.arange(len(self._o_pose)))
        cfg = OptimizerConfig(method="lm" if method == "lm" else "gn", max_iterations=iterations)
        m = np.arange(len(self.marker_ids))
        opt = Optimizer(g, cfg)
        out, summary = opt.optimize(Values(np.arange(n), self.poses, m, self._markers))
        self._poses[:n] = out.poses
        self._markers[out.point_keys] = out.points
        self.full_solves += 1
        self._factored = opt if cfg.method == "gn" else None  # newest_covariance reads its factor
        return summary


class KeyframeMarkers:
    """The lidar estimator's marker bookkeeping: readings to keyframe factors, re-sightings to solves."""

    def __init__(self, settings: MarkerSettings) -> None:
        self.settings = settings
        self.readings = 0
        self.factors = 0
        self.resightings = 0
        self._attached: set[tuple[int, int]] = set()  # (keyframe, marker id) pairs that have their factor

    def observe(self, graph: MarkerPoseGraph, keyframe: int, rel: Array, readings: MarkerReadings) -> bool:
        """Attach the readings taken at pose ``rel`` relative to ``keyframe``; True when a re-sighting solve moved
        the keyframes."""
        ids = np.asarray(readings.ids, np.int64).reshape(-1)
        if keyframe < 0 or not len(ids):
            return False
        self.readings += len(ids)
        fresh = np.array([(keyframe, i) not in self._attached for i in ids.tolist()], dtype=bool)
        ids, xy = ids[fresh], np.asarray(readings.xy_m, np.float64).reshape(-1, 2)[fresh]
        if not len(ids):
            return False
        s = self.settings
        z = se2.transform_points(np.asarray(rel, np.float64), xy)
        var = s.camera.std_m**2 + (s.attach_sigma_per_m * float(np.hypot(rel[0], rel[1])))**2
        # isotropic noise stays isotropic in any frame: information var^-1 I
        info = np.repeat((np.eye(2) / var)[None], len(ids), axis=0)
        olds: list[int] = []
        for i in ids.tolist():
            seen = graph.observers(i)
            if seen and keyframe - max(seen) >= s.resight_keyframes:
                olds.extend(seen)
            self._attached.add((keyframe, i))
        graph.add_marker_observations(keyframe, ids, z, info)
        self.factors += len(ids)
        if not olds:
            return False
        self.resightings += 1
        graph.solve_resighting(olds, s.full_iterations)
        return True
