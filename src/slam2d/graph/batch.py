"""Batch landmark graph SLAM from a recorded log: one factor graph over every pose and landmark, and its structure.

This is the textbook "full SLAM" problem the lab's graph page animates: odometry ``between`` factors chain the
poses, ``range_bearing`` factors join each pose to the landmarks it saw (by the log's ids), and Gauss-Newton
(:class:`slam2d.graph.Optimizer`) moves all of them at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.graph.factors import KINDS
from slam2d.graph.graph import FactorGraph, Values
from slam2d.log import Log
from slam2d.models.motion import MotionNoise, odometry_factor
from slam2d.models.sensors import range_bearing_inverse

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class BatchProblem:
    """A log as a factor graph with its starting point.

    Shapes: ``initial`` holds poses keyed 0..T and landmarks keyed by their ids (first-sighting positions);
    ``obs_steps``/``obs_ids`` (K,) the pose and landmark of every range-bearing factor.
    """

    graph: FactorGraph
    initial: Values
    obs_steps: IntArray
    obs_ids: IntArray


def landmark_graph(log: Log, noise: MotionNoise, sensor_cov: ArrayLike, initial_poses: ArrayLike) -> BatchProblem:
    """The full-SLAM factor graph of ``log`` (observations with an id >= 0), started from ``initial_poses``.

    Landmarks start where their first sighting places them from the initial pose. Shapes: initial_poses (T+1,3),
    sensor_cov (2,2).
    """
    t = log.num_steps
    poses = np.asarray(initial_poses, dtype=np.float64).reshape(-1, 3)
    if len(poses) != t + 1:
        raise ValueError(f"initial_poses must have {t + 1} rows (one per pose of the log), got {len(poses)}")
    graph = FactorGraph()
    z, info = odometry_factor(log.odometry, noise)
    graph.add_between(np.arange(t), np.arange(1, t + 1), z, info)
    keep = log.obs_id >= 0
    steps, ids = log.obs_step[keep], log.obs_id[keep]
    z = np.column_stack([log.obs_range_m[keep], log.obs_bearing_rad[keep]])
    graph.add_range_bearing(steps, ids, z, np.linalg.inv(np.asarray(sensor_cov, dtype=np.float64)))
    lm_ids, first = np.unique(ids, return_index=True)
    points = range_bearing_inverse(poses[steps[first]], z[first]) if len(first) else np.zeros((0, 2))
    return BatchProblem(graph, Values(np.arange(t + 1), poses, lm_ids, points), steps.astype(np.int64),
                        ids.astype(np.int64))


def information_pattern(graph: FactorGraph, pose_keys: ArrayLike, point_keys: ArrayLike) -> NDArray[np.bool_]:
    """Block structure of the information matrix ``J^T Omega J``: True where two variables share a factor (and
    on the diagonal). Variables are ordered poses first (``pose_keys`` order), then points. Shapes: (V,V) bool.

    Structural only (no linearisation), so it is cheap for any graph size; the sparsity of this pattern is what
    makes graph SLAM scale.
    """
    pk = np.asarray(pose_keys, dtype=np.int64).reshape(-1)
    qk = np.asarray(point_keys, dtype=np.int64).reshape(-1)
    v = len(pk) + len(qk)
    out = np.eye(v, dtype=bool)
    index = {"pose": (pk, 0), "point": (qk, len(pk))}
    for block in graph.blocks():
        cols = []
        for row, kind in enumerate(KINDS[block.kind].var_kinds):
            keys, offset = index[kind]
            order = np.argsort(keys, kind="stable")
            pos = np.clip(np.searchsorted(keys, block.keys[row], sorter=order), 0, max(len(keys) - 1, 0))
            idx = order[pos] if len(keys) else pos
            if len(keys) == 0 or np.any(keys[idx] != block.keys[row]):
                raise ValueError(f"{block.kind} factor refers to a {kind} key that is not in the variable list")
            cols.append(idx + offset)
        for a in cols:
            for b in cols:
                out[a, b] = True
    return out
