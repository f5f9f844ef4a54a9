"""Online graph SLAM: a pose per step, odometry and landmark factors, place-recognition loop closures.

Every step adds the new pose (initialised from odometry), an odometry factor and the step's range-bearing factors
(through the association module); every ``optimize_every`` steps, and whenever a loop closure is accepted, the
whole graph is re-optimised from the current estimate (warm start) by a reused :class:`~slam2d.graph.optimizer.
Optimizer`, whose symbolic analysis is redone only when the structure has grown. Loop closures come from place
recognition over keyframes (landmark-constellation descriptors), geometric verification (RANSAC with an honest
covariance), and a chi-square gate against the current estimate and its marginal covariance; accepted loop factors
also carry a robust kernel so that a wrong one that slipped through is down-weighted.

With ``loop_closure`` off the robot also forgets landmarks it has not seen for ``revisit_gap_steps``: a re-sighting
after such a gap starts a new landmark, exactly as if the place were not recognised.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

import slam2d.association as association
from slam2d.association import CLUTTER, NEW, AssociationConfig, Candidates
from slam2d.config import check_positive
from slam2d.filters.base import Estimate
from slam2d.frontend.place_recognition import (
    KeyframeDatabase,
    PlaceRecognitionConfig,
    loop_gate,
    observation_points,
    verify_loop,
)
from slam2d.geometry import se2
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.marginals import marginal_covariances
from slam2d.graph.optimizer import Optimizer, OptimizerConfig
from slam2d.log import Step
from slam2d.models.motion import MotionNoise, odometry_covariance, odometry_predict_jacobians
from slam2d.models.sensors import (
    SensorConfig,
    range_bearing,
    range_bearing_inverse,
    range_bearing_inverse_jacobians,
    range_bearing_jacobians,
)

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class GraphSLAMConfig:
    """Online graph SLAM settings."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise (filled from the log's metadata)."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """range-bearing sensor noise and range (filled from the log's metadata)."""
    association: AssociationConfig = field(default_factory=lambda: AssociationConfig(method="known"))
    """how observations are matched to landmarks."""
    optimize_every: int = 10
    """re-optimise the whole graph every this many steps (and after every accepted loop closure)."""
    iterations: int = 5
    """Levenberg-Marquardt iterations per online optimisation (warm-started from the current estimate)."""
    final_iterations: int = 50
    """iterations of the optimisation run when the estimate is read after the last step (``finalize``)."""
    loop_closure: bool = True
    """detect loops by place recognition; when off, landmarks unseen for ``revisit_gap_steps`` are forgotten."""
    revisit_gap_steps: int = 60
    """with loop closure off: a landmark re-seen after this many steps counts as a new one."""
    keyframe_every: int = 5
    """steps between keyframes used for place recognition."""
    place: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)
    """place recognition and verification."""
    loop_gate_probability: float = 0.999
    """a verified loop must agree with the current estimate at this chi-square probability (3 dof)."""
    loop_robust_kernel: str = "cauchy"
    """robust kernel on loop-closure factors: none, huber, cauchy or dcs."""
    odometry_info_scale: float = 1.0
    """multiply odometry information (> 1: overconfident odometry, the "2 m offset" puzzle)."""
    loop_info_scale: float = 1.0
    """multiply loop-closure information (< 1: a weak loop constraint)."""

    def __post_init__(self) -> None:
        for n in ("optimize_every", "iterations", "final_iterations", "revisit_gap_steps", "keyframe_every"):
            if getattr(self, n) < 1:
                raise ValueError(f"GraphSLAMConfig.{n} must be >= 1 (got {getattr(self, n)})")
        check_positive(self, "odometry_info_scale", "loop_info_scale")
        if not 0 < self.loop_gate_probability < 1:
            raise ValueError(f"GraphSLAMConfig.loop_gate_probability must be in (0, 1) (got "
                             f"{self.loop_gate_probability})")
        if self.loop_robust_kernel not in ("none", "huber", "cauchy", "dcs"):
            raise ValueError(f"GraphSLAMConfig.loop_robust_kernel must be none, huber, cauchy or dcs "
                             f"(got {self.loop_robust_kernel!r})")


@dataclass(frozen=True)
class LoopRecord:
    """A verified loop candidate between pose keys a < b, and whether the gate accepted it."""

    a: int
    b: int
    T_a_b: Array
    d2: float
    accepted: bool


class GraphSLAM:
    """Online graph SLAM estimator (implements the estimator protocol)."""

    def __init__(self, config: GraphSLAMConfig | None = None) -> None:
        self.config = config or GraphSLAMConfig()

    # ------------------------------------------------------------------ protocol
    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        cfg = self.config
        self.rng = rng
        self.graph = FactorGraph()
        self.values = Values(np.array([0]), np.asarray(initial_pose, dtype=np.float64).reshape(1, 3))
        self.optimizer = Optimizer(self.graph, OptimizerConfig(method="lm", max_iterations=cfg.iterations))
        self.index = 0
        self.pose_cov = np.zeros((3, 3))  # marginal of the newest pose: last optimisation + odometry since
        self.point_cov: dict[int, Array] = {}
        self.last_seen: dict[int, int] = {}
        self.alias: dict[int, int] = {}  # source id -> landmark key (loop closure off: forgotten ids re-keyed)
        self.next_key = 0
        self.db = KeyframeDatabase(cfg.place)
        self.keyframes: dict[int, tuple[Array, Array]] = {}
        self.loops: list[LoopRecord] = []
        self.last_assignment = np.zeros(0, dtype=np.int64)
        self.latency_s: list[float] = []
        self.optimizations = 0
        self._finalized = False

    def step(self, step: Step) -> None:
        t0 = time.perf_counter()
        cfg = self.config
        t = step.index
        self.index = t
        self._finalized = False
        prev = self.values.poses[-1]
        u = np.asarray(step.odometry, dtype=np.float64)
        pose = se2.compose(prev, u)
        q = odometry_covariance(u, cfg.motion)
        ja, jb = odometry_predict_jacobians(prev, u)
        self.pose_cov = ja @ self.pose_cov @ ja.T + jb @ q @ jb.T
        self.values.add_poses([t], [pose])
        self.graph.add_between([t - 1], [t], u[None], (np.linalg.inv(q) * cfg.odometry_info_scale)[None])

        obs = step.observations
        loop_added = False
        if len(obs):
            self._add_landmark_factors(t, pose, obs)
            if t % cfg.keyframe_every == 0:
                if cfg.loop_closure:
                    loop_added = self._detect_loop(t, obs.z)
                else:
                    self._remember_keyframe(t, obs.z)
        else:
            self.last_assignment = np.zeros(0, dtype=np.int64)
        if loop_added or t % cfg.optimize_every == 0:
            self._optimize(cfg.iterations * (4 if loop_added else 1))
        self.latency_s.append(time.perf_counter() - t0)

    def estimate(self) -> Estimate:
        cfg = self.config
        order = np.argsort(self.values.point_keys)
        return Estimate(
            pose=self.values.poses[-1].copy(),
            pose_cov=self.pose_cov.copy(),
            landmarks=self.values.points[order].copy(),
            landmark_covs=np.array([self.point_cov.get(int(k), np.eye(2)) for k in self.values.point_keys[order]]
                                   ).reshape(-1, 2, 2),
            landmark_ids=self.values.point_keys[order].copy(),
            extras={
                "trajectory": self.values.poses.copy(),
                "state_dim": int(3 * len(self.values.poses) + 2 * len(self.values.points)),
                "assoc": self.last_assignment.copy(),
                "loops_accepted": sum(1 for lp in self.loops if lp.accepted),
                "loops_rejected": sum(1 for lp in self.loops if not lp.accepted),
                "loops": [(lp.a, lp.b, lp.accepted, lp.T_a_b) for lp in self.loops],
                "optimizations": self.optimizations,
                "latency_s": self.latency_s[-1] if self.latency_s else 0.0,
                "loop_closure": cfg.loop_closure,
            },
        )

    def finalize(self) -> None:
        """Optimise to convergence (called by the runner after the last step)."""
        if not self._finalized:
            self._optimize(self.config.final_iterations)
            self._finalized = True

    def close_loop_now(self, z: Array) -> bool:
        """Try to close a loop from observations ``z`` (K,2) taken at the newest pose, whatever ``loop_closure``
        says, and optimise to convergence if one is accepted (the lab's "close loop" button)."""
        added = self._detect_loop(self.index, np.asarray(z, dtype=np.float64).reshape(-1, 2), add_keyframe=False)
        if added:
            self._optimize(self.config.final_iterations)
        return added

    def chi2_per_dof(self) -> dict[str, float]:
        """Mean whitened squared error per measurement dimension: odometry, loop and landmark factors separately
        (about 1 each when the noise models are right; far above 1 flags the factors that are being violated)."""
        from slam2d.graph.problem import factor_chi2

        out: dict[str, float] = {}
        for b in self.graph.blocks():
            if not b.size:
                continue
            chi = factor_chi2(self.graph, self.values, b.kind)
            if b.kind == "between":
                odo = b.keys[1] == b.keys[0] + 1
                groups = {"odometry": odo, "loop": ~odo}
            else:
                groups = {b.kind: np.ones(b.size, dtype=bool)}
            for name, mask in groups.items():
                if np.any(mask):
                    out[name] = float(chi[mask].sum()) / (int(mask.sum()) * b.z.shape[1])
        return out

    def graph_view(self) -> dict[str, Any]:
        """Nodes and edges for drawing: pose/point positions and edges (i, j, type) as index arrays."""
        edges = {}
        for b in self.graph.blocks():
            edges[b.kind] = b.keys.T.copy()
        return {"poses": self.values.poses.copy(), "pose_keys": self.values.pose_keys.copy(),
                "points": self.values.points.copy(), "point_keys": self.values.point_keys.copy(), "edges": edges}

    # ------------------------------------------------------------------ internals
    def _marginals(self, pose_keys: Any = (), point_keys: Any = ()) -> Array:
        """Joint marginal covariance of the selected variables (poses first), reusing the optimiser's analysis."""
        an = self.optimizer.analysis
        if an is None or not an.compatible(self.graph, self.values):
            an = None
        return marginal_covariances(self.graph, self.values, pose_keys, point_keys, analysis=an).joint

    def _optimize(self, iterations: int) -> None:
        cfg = self.optimizer.config
        if cfg.max_iterations != iterations:
            self.optimizer.config = OptimizerConfig(method="lm", max_iterations=iterations)
        self.values, _ = self.optimizer.optimize(self.values)
        self.optimizations += 1
        # refresh the uncertainty used by association (landmarks only when it is not the oracle) and the loop gate
        keys = self.values.point_keys if self.config.association.method != "known" else np.zeros(0, np.int64)
        cov = self._marginals([int(self.values.pose_keys[-1])], keys)
        self.pose_cov = cov[:3, :3]
        for i, k in enumerate(keys):
            self.point_cov[int(k)] = cov[3 + 2 * i: 5 + 2 * i, 3 + 2 * i: 5 + 2 * i]

    def _new_key(self) -> int:
        while self.next_key in self.point_cov or np.any(self.values.point_keys == self.next_key):
            self.next_key += 1
        k = self.next_key
        self.next_key += 1
        return k

    def _add_landmark_factors(self, t: int, pose: Array, obs: Any) -> None:
        cfg = self.config
        R = cfg.sensor.covariance
        z = obs.z
        keys = np.asarray(self.values.point_keys, dtype=np.int64)
        if cfg.association.method == "known":
            assign = np.full(len(obs), CLUTTER, dtype=np.int64)
            for i, sid in enumerate(obs.landmark_id):
                sid = int(sid)
                if sid < 0:
                    continue
                key: int | None = self.alias.get(sid, sid)
                if key is not None and key in self.last_seen and not cfg.loop_closure \
                        and t - self.last_seen[key] > cfg.revisit_gap_steps:
                    key = None  # not recognised: it will start a new landmark
                if key is None:
                    key = self._new_key() + 1_000_000
                    self.alias[sid] = key
                else:
                    self.alias.setdefault(sid, key)
                assign[i] = key
        else:
            assign = self._associate(t, pose, obs, keys)
        new_mask = assign == NEW
        if np.any(new_mask):
            assign[new_mask] = [self._new_key() for _ in range(int(new_mask.sum()))]
        use = assign >= 0
        if not np.any(use):
            self.last_assignment = assign
            return
        known_keys = set(int(k) for k in keys)
        fresh = [i for i in np.flatnonzero(use) if int(assign[i]) not in known_keys]
        # a new landmark is initialised from its first sighting (inverse sensor model)
        seen: set[int] = set()
        init_keys, init_pts = [], []
        for j in fresh:
            k = int(assign[j])
            if k in seen:
                continue
            seen.add(k)
            init_keys.append(k)
            init_pts.append(range_bearing_inverse(pose, z[j]))
            gp, gz = range_bearing_inverse_jacobians(pose, z[j])
            self.point_cov[k] = gp @ self.pose_cov @ gp.T + gz @ R @ gz.T
        if init_keys:
            self.values.add_points(init_keys, np.array(init_pts))
        idx = np.flatnonzero(use)
        info = np.broadcast_to(np.linalg.inv(R), (idx.size, 2, 2))
        self.graph.add_range_bearing(np.full(idx.size, t), assign[idx], z[idx], info)
        for k in assign[idx]:
            self.last_seen[int(k)] = t
        self.last_assignment = assign

    def _associate(self, t: int, pose: Array, obs: Any, keys: NDArray[np.int64]) -> NDArray[np.int64]:
        """Unknown association: candidates in range, S from the marginals, the configured method."""
        cfg = self.config
        R = cfg.sensor.covariance
        pts = self.values.points
        if keys.size:
            near = np.hypot(*(pts - pose[:2]).T) <= cfg.sensor.max_range_m + 3.0
            if not cfg.loop_closure:
                recent = np.array([t - self.last_seen.get(int(k), -10**9) <= cfg.revisit_gap_steps for k in keys])
                near &= recent
            cand_keys, cand_pts = keys[near], pts[near]
        else:
            cand_keys, cand_pts = keys, pts
        if cand_keys.size == 0:
            return np.where(np.ones(len(obs), dtype=bool), NEW, NEW).astype(np.int64)
        zp = range_bearing(pose, cand_pts)
        hp, hl = range_bearing_jacobians(pose, cand_pts)
        lcov = np.array([self.point_cov.get(int(k), np.eye(2)) for k in cand_keys])
        s_blocks = hp @ self.pose_cov @ np.swapaxes(hp, 1, 2) + hl @ lcov @ np.swapaxes(hl, 1, 2) + R
        hp_stack = hp.reshape(-1, 3)
        s_joint = hp_stack @ self.pose_cov @ hp_stack.T
        for i in range(len(cand_keys)):
            s_joint[2 * i:2 * i + 2, 2 * i:2 * i + 2] = s_blocks[i]
        cands = Candidates(cand_keys.astype(np.int64), zp, s_blocks, s_joint)
        assoc_fn = getattr(association, "associate", None)
        if assoc_fn is None:
            raise ValueError("not yet implemented: association method "
                             f"{cfg.association.method!r} needs slam2d.association.associate")
        return np.asarray(assoc_fn(obs, cands, cfg.association, rng=self.rng).assignment, dtype=np.int64)

    def _remember_keyframe(self, t: int, z: Array) -> None:
        pts, covs = observation_points(z, self.config.sensor.covariance)
        if self.db.add(t, pts):
            self.keyframes[t] = (pts, covs)

    def _detect_loop(self, t: int, z: Array, add_keyframe: bool = True) -> bool:
        cfg = self.config
        pts, covs = observation_points(z, cfg.sensor.covariance)
        hits = self.db.query(pts, t)
        accepted = False
        for a, _ in hits:
            if a not in self.keyframes:  # the keyframe was dropped: nothing to verify against
                continue
            pa, ca = self.keyframes[a]
            hyp = verify_loop(pa, ca, pts, covs, cfg.place, self.rng)
            if hyp is None:
                continue
            pose_a = self.values.poses[np.searchsorted(self.values.pose_keys, a)]
            t_pred = se2.between(pose_a, self.values.poses[-1])
            joint = self._marginals([a, t])
            ja, jb = se2.between_jacobians(pose_a, self.values.poses[-1])
            j = np.hstack([ja, jb])
            ok, d2 = loop_gate(hyp.T_a_b, hyp.cov, t_pred, j @ joint @ j.T, cfg.loop_gate_probability)
            self.loops.append(LoopRecord(a, t, hyp.T_a_b, d2, ok))
            if ok:
                info = np.linalg.inv(hyp.cov) * cfg.loop_info_scale
                kernel = None if cfg.loop_robust_kernel == "none" else cfg.loop_robust_kernel
                self.graph.add_between([a], [t], hyp.T_a_b[None], info[None], robust=kernel)
                accepted = True
                break
        if add_keyframe and self.db.add(t, pts):
            self.keyframes[t] = (pts, covs)
        return accepted
