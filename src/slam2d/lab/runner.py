"""The runner: drives any estimator over a Log, times each step, keeps the history, and scores the result."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.config import split_overrides, to_dict, with_overrides
from slam2d.estimator import Estimate, Estimator, LoopEvent, SupportsLoopClosure
from slam2d.eval.association import run_association_scores
from slam2d.eval.trajectory import ate, rpe
from slam2d.geometry import se2
from slam2d.lab.registry import EstimatorSpec, association_method, get_spec, make_config, specs_of
from slam2d.log import Log
from slam2d.sim.scenarios import MEMORY_ENV, ScenarioConfig, memory_limit_mb
from slam2d.sim.simulator import simulate, spawn_streams

Array = NDArray[np.float64]

#: an accepted loop counts as false (``loops_false``) when its two poses are truly farther apart than this (beyond
#: twice the default sensor range nothing can be shared) ...
LOOP_TRUE_DISTANCE_M = 16.0
#: ... or when its relative-pose measurement is off the true relative pose by more than this
LOOP_TRUE_ERROR_M = 1.0


class DivergenceError(FloatingPointError):
    """An estimator produced a non-finite pose; the message names the step."""


def name_of(estimator: object) -> str:
    return type(estimator).__name__


@dataclass(frozen=True)
class RunResult:
    """What one run produced. Shapes: poses (T+1,3) online estimates; trajectory (T+1,3) final (smoothed) one;
    ``loops`` every loop-closure decision the estimator reported, in order (``closes_loops``: it can close loops)."""

    poses: Array
    trajectory: Array
    pose_covs: Array | None
    step_s: Array
    final: Estimate
    snapshots: list[Estimate] | None
    metrics: dict[str, Any] = field(default_factory=dict)
    loops: tuple[LoopEvent, ...] = ()
    closes_loops: bool = False


def _progress(total: int, enabled: bool) -> Callable[[int], None]:
    if not enabled:
        return lambda i: None
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency
        return lambda i: None
    bar = tqdm(total=total, file=sys.stderr, unit="step", leave=False)

    def update(i: int) -> None:
        bar.update(1)
        if i == total:
            bar.close()

    return update


def run(
    estimator: Estimator,
    log: Log,
    *,
    rng: np.random.Generator,
    keep_snapshots: bool = False,
    progress: bool | None = None,
    on_step: Callable[[int, Estimate], None] | None = None,
) -> RunResult:
    """Drive ``estimator`` over every step of ``log`` and score it against the log's truth (if any).

    ``progress=None`` shows a bar on stderr for runs longer than 2000 steps when stderr is a terminal.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"run: rng must be a numpy.random.Generator (np.random.default_rng(seed)), "
                        f"got {type(rng).__name__}")
    specs = specs_of(estimator)
    if len({spec.needs for spec in specs}) == 1:  # a registered back end: refused, as by run_named, on a log
        _check_needs(" or ".join(repr(spec.name) for spec in specs), specs[0].needs, log)  # lacking its input
    estimator.reset(log.initial_pose, rng=rng)
    t = log.num_steps
    poses = np.empty((t + 1, 3))
    covs: list[Array | None] = []
    snaps: list[Estimate] = []
    step_s = np.empty(t)
    first = estimator.estimate()
    poses[0] = first.pose
    covs.append(first.pose_cov)
    show = progress if progress is not None else (t > 2000 and sys.stderr.isatty())
    tick = _progress(t, show)
    snap = first
    assigned: list[NDArray[np.int64]] = []
    truth_ids: list[NDArray[np.int64]] = []
    loops: list[LoopEvent] = []
    for i, step in enumerate(log, start=1):
        t0 = time.perf_counter()
        estimator.step(step)
        snap = estimator.estimate()
        step_s[i - 1] = time.perf_counter() - t0
        poses[i] = snap.pose
        if not np.all(np.isfinite(poses[i])):  # a diverged filter is an error, never a result
            raise DivergenceError(f"{name_of(estimator)} diverged at step {i}: pose {poses[i].tolist()} "
                                  f"(odometry {step.odometry.tolist()})")
        covs.append(snap.pose_cov)
        if keep_snapshots:
            snaps.append(snap)
        loops.extend(snap.new_loops)
        assoc = snap.association
        if assoc is not None and len(assoc) == len(step.observations):
            assigned.append(np.asarray(assoc, dtype=np.int64))
            truth_ids.append(step.observations.landmark_id)
        if on_step is not None:
            on_step(i, snap)
        tick(i)
    estimator.finalize()  # smoothers optimise to convergence once the data are in
    snap = estimator.estimate()
    loops.extend(snap.new_loops)
    traj = snap.trajectory
    trajectory = np.asarray(traj, dtype=np.float64) if traj is not None and len(traj) == t + 1 else poses
    if not np.all(np.isfinite(trajectory)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(trajectory), axis=1))[0])
        raise DivergenceError(f"{name_of(estimator)} diverged: the final trajectory is not finite from step {bad}")
    pose_covs = None if any(c is None for c in covs) else np.asarray(covs)
    result = RunResult(poses, trajectory, pose_covs, step_s, snap, snaps if keep_snapshots else None,
                       loops=tuple(loops), closes_loops=isinstance(estimator, SupportsLoopClosure))
    result.metrics.update(score(result, log))
    if assigned and np.any(log.obs_id >= 0):  # the source knows ids: score the association
        result.metrics.update(run_association_scores(assigned, truth_ids))
    return result


def score(result: RunResult, log: Log) -> dict[str, Any]:
    """Flat metrics of a run: ATE/RPE against the log's truth when it has one, timing, map size."""
    m: dict[str, Any] = {
        "steps": int(log.num_steps),
        "step_ms_mean": float(np.mean(result.step_s) * 1e3) if result.step_s.size else 0.0,
        "step_ms_p99": float(np.percentile(result.step_s, 99) * 1e3) if result.step_s.size else 0.0,
        "landmarks_estimated": len(result.final.landmarks),
    }
    if log.true_poses is not None and log.num_steps >= 1:
        a = ate(result.trajectory, log.true_poses)
        r = rpe(result.trajectory, log.true_poses)
        m.update(
            ate_rmse_m=a.rmse_m,
            rpe_trans_rmse_m=r.trans_rmse_m,
            rpe_rot_rmse_rad=r.rot_rmse_rad,
            final_pose_error_m=float(np.hypot(*(result.trajectory[-1, :2] - log.true_poses[-1, :2]))),
        )
        if result.closes_loops:
            # false loop: the two poses are not truly near each other, or the constraint contradicts the truth
            true = log.true_poses
            acc = [lp for lp in result.loops if lp.accepted]
            far = [float(np.hypot(*(true[lp.a, :2] - true[lp.b, :2]))) > LOOP_TRUE_DISTANCE_M
                   or float(np.hypot(*se2.local(se2.between(true[lp.a], true[lp.b]), lp.T_a_b)[:2]))
                   > LOOP_TRUE_ERROR_M for lp in acc]
            m.update(loops_accepted=len(acc), loops_false=int(sum(far)))
    return m


def _check_particle_memory(name: str, cfg: object, log: Log) -> None:
    """A particle filter holds a map per particle: refuse (before allocating) a particles x landmarks product over
    the memory limit of :func:`slam2d.sim.scenarios.check_memory` (``SLAM2D_MAX_MEMORY_MB``)."""
    particles = to_dict(cfg).get("particles")
    if not isinstance(particles, int):
        return
    known = log.true_landmarks.shape[0] if log.true_landmarks is not None else 0
    seen = int(np.unique(log.obs_id[log.obs_id >= 0]).size) if log.obs_id.size else 0
    landmarks = max(known, seen, min(log.obs_step.size, 1000), 1)
    need_mb = particles * (landmarks * 8.0 * 8 + 64) * 3 / 2**20  # mean + covariance per landmark, a few copies
    limit_mb = memory_limit_mb()
    if need_mb > limit_mb:
        raise ValueError(f"{name}: particles={particles} with ~{landmarks} landmarks would need about "
                         f"{need_mb:.3g} MB, over the limit of {limit_mb:g} MB; set {MEMORY_ENV} to allow it")


def check_inputs(spec: EstimatorSpec, log: Log) -> None:
    """Refuse a log that lacks what the back end measures with (:attr:`EstimatorSpec.needs`): it would only be
    dead-reckoned, under the estimator's name."""
    _check_needs(repr(spec.name), spec.needs, log)


def _check_needs(name: str, needs: str, log: Log) -> None:
    what = str(log.metadata.get("dataset", log.metadata.get("scenario", "this log")))
    if needs == "scans" and (log.scan_step is None or len(log.scan_step) == 0):
        raise ValueError(f"estimator {name} needs lidar scans; {what} has none")
    if needs == "bearings" and len(log.obs_bearing_rad) and not np.isfinite(log.obs_bearing_rad).any():
        raise ValueError(f"estimator {name} needs landmark bearings; {what}'s observations are ranges only "
                         "(use range-only-ekf or range-only-graph)")
    if needs in ("bearings", "ranges") and not len(log.obs_step) and log.scan_step is not None \
            and len(log.scan_step):
        raise ValueError(f"estimator {name} needs landmark observations; {what} is a lidar log without any "
                         "(use --estimator lidar)")


def run_named(
    estimator: str,
    scenario: str | None = "room",
    *,
    seed: int = 0,
    overrides: Mapping[str, Any] | None = None,
    log: Log | None = None,
    keep_snapshots: bool = False,
    progress: bool | None = None,
) -> tuple[RunResult, dict[str, Any]]:
    """Simulate (or take ``log``), build the named estimator, run it; returns (result, flat JSON-ready record).

    ``overrides`` may name scenario fields (``landmarks``, ``sensor.range_std_m``) or estimator fields; a key that
    both know goes to the scenario, and the estimator then inherits the value through the log's metadata. Prefix a
    key with ``estimator.`` to set only the estimator's copy.
    """
    spec = get_spec(estimator)
    overrides = dict(overrides or {})
    est_only = {k.split(".", 1)[1]: v for k, v in overrides.items() if k.startswith("estimator.")}
    rest = {k.split(".", 1)[1] if k.startswith("scenario.") else k: v for k, v in overrides.items()
            if not k.startswith("estimator.")}
    if log is None:
        scen_over, est_over = split_overrides(rest, ScenarioConfig, spec.config_cls)
        cfg = with_overrides(ScenarioConfig(name=scenario or "room"), scen_over)
        if est_over or est_only:  # a bad estimator value is refused before the simulation, not after it
            with_overrides(spec.config_cls(), {**est_over, **est_only})
        log = simulate(cfg, seed)
    else:
        (est_over,) = split_overrides(rest, spec.config_cls)
    check_inputs(spec, log)
    # "auto" association is resolved from the whole log: known ids when any observation carries one
    est_cfg = make_config(estimator, {**est_over, **est_only}, log.metadata, has_ids=bool(np.any(log.obs_id >= 0)))
    _check_particle_memory(estimator, est_cfg, log)
    est = spec.factory(est_cfg)
    rng = spawn_streams(seed)["estimator"]
    result = run(est, log, rng=rng, keep_snapshots=keep_snapshots, progress=progress)
    record: dict[str, Any] = {
        "estimator": estimator,
        "scenario": str(log.metadata.get("scenario", log.metadata.get("dataset", "log"))),
        "seed": int(seed),
        "association_method": association_method(est_cfg),
        **result.metrics,
        "estimator_config": to_dict(est_cfg),
    }
    if "config" in log.metadata:
        record["scenario_config"] = log.metadata["config"]
    return result, record
