"""The multi-robot runner: drives :class:`~slam2d.graph.multi_robot.MultiGraphSLAM` over a MultiRobotLog and scores it.

Why its own runner and not an entry in the estimator registry: the estimator contract is one robot's
``reset(initial_pose)`` / ``step(Step)``, and everything built on it (the single-robot runner, sweeps, break-it
experiments, the web lab) assumes one trajectory and one pose per step. A multi-robot back end consumes a
:class:`~slam2d.multi_log.MultiStep` (every robot's step plus robot-robot sightings) and produces one trajectory per
robot, so it keeps the same lifecycle (reset / step / estimate / finalize, out-of-order use raises
``EstimatorStateError``) with multi-robot types, and is reached by name through :data:`MULTI_ESTIMATORS` here.

Scores: each robot's ATE after its own SE(2) alignment (comparable with ``slam2d run --robot N``); the joint ATE
(every robot's poses under ONE alignment: are the robots consistent with each other?); the landmark map error after
that joint alignment; with unknown starts, the error of each recovered start transform (robot k's start in the
frame of robot 1's start against the truth) and every merge decision.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from slam2d.association import AssociationConfig
from slam2d.eval.mapping import map_error
from slam2d.eval.trajectory import align_se2, ate
from slam2d.geometry import se2
from slam2d.geometry.angles import angle_diff
from slam2d.graph.multi_robot import MultiEstimate, MultiGraphSLAM, config_from_log
from slam2d.multi_log import MultiRobotLog

Array = NDArray[np.float64]

#: multi-robot back ends by name (the single-robot ones are in slam2d.lab.registry)
MULTI_ESTIMATORS = {"multi-graph": "joint factor graph over all robots' poses and the shared landmarks, "
                                   "robot-robot range-bearing factors, map merging for unknown starts"}


@dataclass(frozen=True)
class MultiRunResult:
    """The final joint estimate, the flat metrics and the wall time of the run (s)."""

    final: MultiEstimate
    metrics: dict[str, Any]
    seconds: float


def run_multi(log: MultiRobotLog, *, estimator: str = "multi-graph", unknown_starts: bool = False,
              association: str = "known", seed: int = 0, **config: Any) -> MultiRunResult:
    """Run the named multi-robot back end over ``log`` (noise from the log) and score it against the log's truth.

    ``association``: a :class:`~slam2d.association.AssociationConfig` method; ``config``: further
    :class:`~slam2d.graph.multi_robot.MultiGraphConfig` fields. The known starts are the logs' initial poses.
    """
    if estimator not in MULTI_ESTIMATORS:
        raise ValueError(f"unknown multi-robot estimator {estimator!r}; valid: {sorted(MULTI_ESTIMATORS)}")
    assoc = AssociationConfig(method=cast(Any, association))
    cfg = config_from_log(log, unknown_starts=unknown_starts, association=assoc, **config)
    est = MultiGraphSLAM(cfg)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    est.reset(None if unknown_starts else np.array([lg.initial_pose for lg in log.logs]), rng=rng)
    for ms in log:
        est.step(ms)
    est.finalize()
    final = est.estimate()
    seconds = time.perf_counter() - t0
    metrics = score_multi(final, log)
    metrics.update(estimator=estimator, unknown_starts=unknown_starts, association=association, seed=seed,
                   seconds=seconds, steps=log.num_steps)
    return MultiRunResult(final, metrics, seconds)


def score_multi(final: MultiEstimate, log: MultiRobotLog) -> dict[str, Any]:
    """Per-robot and joint metrics against the log's truth (see the module docstring)."""
    truth = [lg.true_poses for lg in log.logs]
    out: dict[str, Any] = {"robots": list(log.robots), "groups": [int(g) for g in final.groups],
                           "counters": final.counters}
    if any(t is None for t in truth):
        return out
    tp = [np.asarray(t) for t in truth]
    out["ate_rmse_m"] = {str(r): ate(final.trajectories[i], tp[i]).rmse_m for i, r in enumerate(log.robots)}
    # one alignment for the robots in robot 1's frame (all of them when starts are known or all merged)
    in0 = np.flatnonzero(final.groups == final.groups[0])
    est_all = np.concatenate([final.trajectories[i] for i in in0])
    ref_all = np.concatenate([tp[i] for i in in0])
    joint = align_se2(est_all, ref_all)
    moved = se2.transform_points(joint, est_all[:, :2])
    out["joint_ate_rmse_m"] = float(np.sqrt(np.mean(np.sum((moved - ref_all[:, :2]) ** 2, axis=1))))
    out["joint_frame_robots"] = [int(log.robots[i]) for i in in0]
    true_lm = log.logs[0].true_landmarks
    if true_lm is not None:
        mine = final.landmark_groups == final.groups[0]
        me = map_error(final.landmarks[mine], true_lm, alignment=joint)
        out.update(map_rmse_m=me.rmse_m, map_matched=me.matched, map_spurious=me.spurious, map_missed=me.missed,
                   landmarks_estimated=int(final.landmarks.shape[0]))
    starts: dict[str, Any] = {}
    for i in range(1, len(log.robots)):
        key = str(log.robots[i])
        if final.groups[i] != final.groups[0]:
            starts[key] = None  # never merged into robot 1's frame
            continue
        est_rel = se2.between(final.starts[0], final.starts[i])
        true_rel = se2.between(tp[0][0], tp[i][0])
        starts[key] = {"translation_error_m": float(np.hypot(*(est_rel[:2] - true_rel[:2]))),
                       "rotation_error_rad": float(abs(angle_diff(est_rel[2], true_rel[2])))}
    out["start_errors"] = starts
    stamps = log.stamps_s
    out["merges"] = [{"step": ev.step, "time_s": float(stamps[ev.step]), "robots_a": list(ev.robots_a),
                      "robots_b": list(ev.robots_b), "accepted": ev.hypothesis.accepted,
                      "reason": ev.hypothesis.reason, "landmark_pairs": ev.landmark_pairs,
                      "sighting_pairs": ev.sighting_pairs, "chi2": ev.hypothesis.chi2, "dof": ev.hypothesis.dof}
                     for ev in final.merges]
    return out


def table_rows(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """One printable row per robot plus a joint row."""
    rows: list[dict[str, Any]] = []
    for r in metrics.get("robots", []):
        se = (metrics.get("start_errors") or {}).get(str(r))
        rows.append({"robot": r, "ate_rmse_m": metrics.get("ate_rmse_m", {}).get(str(r), float("nan")),
                     "start_error_m": se["translation_error_m"] if se else "",
                     "start_error_rad": se["rotation_error_rad"] if se else "",
                     "group": metrics["groups"][metrics["robots"].index(r)]})
    rows.append({"robot": "joint", "ate_rmse_m": metrics.get("joint_ate_rmse_m", float("nan")),
                 "map_rmse_m": metrics.get("map_rmse_m", float("nan")),
                 "landmarks": metrics.get("landmarks_estimated", "")})
    return rows
