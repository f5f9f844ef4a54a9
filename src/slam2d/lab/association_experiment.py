"""Data association measured without a SLAM back end.

For snapshots of a simulated run, the experiment builds the belief a back end would hold: the true pose plus an
error drawn from the pose covariance P, and a map of landmarks known up to a small covariance (some landmarks are
left out of the map on purpose, so their sightings should become NEW). Candidates are predicted from that belief
with ``S_joint = H blockdiag(P, sigma_l^2 I) H^T + I (x) R`` (:func:`candidates_from_belief`), and every method is
scored against the simulator's true ids with :mod:`slam2d.eval.association`.

The same functions drive ``slam2d experiment association`` and the web lab's data-association page.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.association import METHODS, AssociationConfig, Candidates, associate, candidates_from_belief
from slam2d.config import check_nonnegative, check_positive, check_probability
from slam2d.eval.association import AssociationCounts, association_counts
from slam2d.log import Log, Observations
from slam2d.models.sensors import range_bearing
from slam2d.sim.simulator import simulate

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class AssociationExperimentConfig:
    """What one association experiment simulates and how uncertain the belief is."""

    scenario: str = "scramble"
    """simulated scenario (see ``slam2d.sim.SCENARIOS``)."""
    steps: int = 300
    """steps simulated per seed."""
    snapshots_per_seed: int = 10
    """poses (evenly spaced over the run) at which the methods are scored."""
    pose_std_xy_m: float = 0.3
    """standard deviation of the belief's position error, per axis (m)."""
    pose_std_theta_rad: float = 0.05
    """standard deviation of the belief's heading error (rad)."""
    landmark_std_m: float = 0.05
    """standard deviation of each mapped landmark's position error, per axis (m)."""
    unmapped_fraction: float = 0.1
    """fraction of landmarks left out of the map: their sightings are correct only as NEW."""
    clutter_rate: float = 0.0
    """mean spurious detections per scan, passed to the simulator's sensor."""
    candidate_margin_m: float = 1.0
    """landmarks predicted up to this far beyond the sensor's maximum range are offered as candidates (m)."""
    methods: tuple[str, ...] = METHODS
    """methods to compare."""
    association: AssociationConfig = field(default_factory=AssociationConfig)
    """gates and method parameters (its ``method`` is replaced by each entry of ``methods``)."""

    def __post_init__(self) -> None:
        check_positive(self, "pose_std_xy_m", "pose_std_theta_rad", "landmark_std_m")
        check_nonnegative(self, "clutter_rate", "candidate_margin_m")
        check_probability(self, "unmapped_fraction")
        if self.steps < 1 or self.snapshots_per_seed < 1:
            raise ValueError("AssociationExperimentConfig.steps and .snapshots_per_seed must be >= 1")
        bad = [m for m in self.methods if m not in METHODS]
        if bad or not self.methods:
            raise ValueError(f"AssociationExperimentConfig.methods must be a non-empty subset of {list(METHODS)} "
                             f"(got {list(self.methods)})")


@dataclass(frozen=True)
class AssociationTrial:
    """One scored snapshot: the truth, the belief, and what the association is given.

    Shapes: true_pose (3,), belief_pose (3,), pose_cov (3,3), map_landmarks (M,2) believed positions of the mapped
    landmarks with map_ids (M,); observations K; candidates L (the mapped landmarks near the belief).
    """

    step: int
    true_pose: Array
    belief_pose: Array
    pose_cov: Array
    map_landmarks: Array
    map_ids: NDArray[np.int64]
    observations: Observations
    candidates: Candidates


@dataclass(frozen=True)
class MethodSummary:
    """Pooled counts of one method over all seeds and snapshots, per-seed precision and recall, and timing."""

    method: str
    counts: AssociationCounts
    seed_precision: tuple[float, ...]
    seed_recall: tuple[float, ...]
    ms_per_call: float
    truncated_calls: int

    def row(self) -> dict[str, Any]:
        p = np.array(self.seed_precision, dtype=float)
        r = np.array(self.seed_recall, dtype=float)
        return {
            "method": self.method,
            "precision": self.counts.precision,
            "recall": self.counts.recall,
            "false_new_rate": self.counts.false_new_rate,
            "missed_new_rate": self.counts.missed_new_rate,
            "precision_seed_min": float(np.nanmin(p)) if np.isfinite(p).any() else float("nan"),
            "recall_seed_min": float(np.nanmin(r)) if np.isfinite(r).any() else float("nan"),
            "matches": self.counts.matches,
            "ms_per_call": self.ms_per_call,
            "truncated": self.truncated_calls,
        }


@dataclass(frozen=True)
class AssociationExperimentResult:
    config: AssociationExperimentConfig
    seeds: tuple[int, ...]
    methods: tuple[MethodSummary, ...]

    def rows(self) -> list[dict[str, Any]]:
        return [m.row() for m in self.methods]

    def by_method(self) -> dict[str, MethodSummary]:
        return {m.method: m for m in self.methods}


def _simulate(config: AssociationExperimentConfig, seed: int) -> Log:
    overrides: dict[str, Any] = {"steps": config.steps}
    if config.clutter_rate > 0:
        overrides["clutter_rate"] = config.clutter_rate
    return simulate(config.scenario, seed, **overrides)


def association_trials(log: Log, config: AssociationExperimentConfig, rng: np.random.Generator) -> list[
        AssociationTrial]:
    """Build the snapshots of one run: one map (with its errors and unmapped landmarks), then per snapshot a pose
    belief with a fresh error drawn from P, and the candidates predicted from it."""
    if log.true_poses is None or log.true_landmarks is None or log.true_landmark_ids is None:
        raise ValueError("association experiment needs a log with ground truth (true_poses, true_landmarks)")
    sensor = log.metadata.get("sensor", {})
    r = np.diag([float(sensor.get("range_std_m", 0.1)) ** 2, float(sensor.get("bearing_std_rad", 0.02)) ** 2])
    max_range = float(sensor.get("max_range_m", 8.0)) + config.candidate_margin_m
    n_lm = len(log.true_landmarks)
    mapped = rng.random(n_lm) >= config.unmapped_fraction
    map_ids = log.true_landmark_ids[mapped].astype(np.int64)
    map_lm = log.true_landmarks[mapped] + rng.normal(0.0, config.landmark_std_m, size=(int(mapped.sum()), 2))
    p = np.diag([config.pose_std_xy_m**2, config.pose_std_xy_m**2, config.pose_std_theta_rad**2])
    steps = np.unique(np.linspace(1, log.num_steps, config.snapshots_per_seed).round().astype(int))
    trials = []
    for t in steps:
        true_pose = log.true_poses[t]
        belief = true_pose + rng.multivariate_normal(np.zeros(3), p)
        near = range_bearing(belief, map_lm)[:, 0] <= max_range
        cov = np.zeros((3 + 2 * int(near.sum()),) * 2)
        cov[:3, :3] = p
        cov[3:, 3:] = config.landmark_std_m**2 * np.eye(2 * int(near.sum()))
        cands = candidates_from_belief(belief, map_lm[near], map_ids[near], cov, r)
        trials.append(AssociationTrial(int(t), true_pose, belief, p, map_lm, map_ids, log.observations_at(int(t)),
                                       cands))
    return trials


def run_association_experiment(config: AssociationExperimentConfig, seeds: Iterable[int]) -> (
        AssociationExperimentResult):
    """Score every method of ``config.methods`` on the same snapshots of every seed; pooled and per-seed numbers."""
    seeds = tuple(int(s) for s in seeds)
    if not seeds:
        raise ValueError("run_association_experiment needs at least one seed")
    pooled = {m: AssociationCounts() for m in config.methods}
    per_seed: dict[str, list[AssociationCounts]] = {m: [] for m in config.methods}
    elapsed = dict.fromkeys(config.methods, 0.0)
    truncated = dict.fromkeys(config.methods, 0)
    calls = 0
    for seed in seeds:
        log = _simulate(config, seed)
        trials = association_trials(log, config, np.random.default_rng([seed, 7]))
        calls += len(trials)
        for m in config.methods:
            cfg = dataclasses.replace(config.association, method=m)  # type: ignore[arg-type]
            rng = np.random.default_rng([seed, 11])
            seed_counts = AssociationCounts()
            for tr in trials:
                t0 = time.perf_counter()
                res = associate(tr.observations, tr.candidates, cfg, rng=rng)
                elapsed[m] += time.perf_counter() - t0
                truncated[m] += int(res.truncated)
                seed_counts += association_counts(tr.observations.landmark_id, res.assignment, tr.candidates.ids)
            pooled[m] += seed_counts
            per_seed[m].append(seed_counts)
    summaries = tuple(
        MethodSummary(m, pooled[m], tuple(c.precision for c in per_seed[m]), tuple(c.recall for c in per_seed[m]),
                      1e3 * elapsed[m] / max(calls, 1), truncated[m])
        for m in config.methods
    )
    return AssociationExperimentResult(config, seeds, summaries)


def summary_record(result: AssociationExperimentResult) -> dict[str, Any]:
    """A JSON-ready record: config, seeds, one row per method."""
    from slam2d.config import to_dict

    return {"experiment": "association", "config": to_dict(result.config), "seeds": list(result.seeds),
            "methods": result.rows()}
