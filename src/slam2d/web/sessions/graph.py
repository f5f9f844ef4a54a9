"""Page 7: batch graph SLAM on the drive so far: build the factor graph, then watch Gauss-Newton iterate."""

from __future__ import annotations

from typing import Any

import numpy as np

from slam2d.eval.trajectory import ate
from slam2d.graph import Optimizer, OptimizerConfig, Values
from slam2d.graph.batch import BatchProblem, information_pattern, landmark_graph
from slam2d.lab.registry import make_estimator
from slam2d.models.lidar import LidarConfig
from slam2d.models.motion import MotionNoise
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator
from slam2d.sim.trajectory import WaypointFollower
from slam2d.web.params import Param
from slam2d.web.sessions.base import Array, Sections, Session, block_average, downsample, seed_param

#: seconds between two Gauss-Newton iterations, so the correction can be watched spreading
ITERATION_PERIOD_S = 0.4
MAX_ITERATIONS = 20


GRAPH_LABELS = {
    "poses": "poses",
    "landmarks": "landmarks",
    "factors": "factors",
    "iteration": "Gauss-Newton iteration",
    "cost": "cost (sum of squared whitened errors)",
    "ate_initial_m": "ATE before optimising (m)",
    "ate_now_m": "ATE now (m)",
    "omega_nonzero_blocks": "non-zero blocks of Ω",
    "omega_blocks": "blocks of Ω in all",
}


class GraphSession(Session):
    """The robot drives the room's route (odometry and known-id range-bearing observations are recorded);
    "optimize" builds the factor graph (:func:`slam2d.graph.batch.landmark_graph`), starts from the dead-reckoned
    poses and first-sighting landmarks, and runs one Gauss-Newton iteration per animation tick."""

    page = "graph"
    title = "graph SLAM"
    scalars = ("poses", "landmarks", "factors", "iteration", "cost", "ate_initial_m", "ate_now_m",
               "omega_nonzero_blocks", "omega_blocks")
    labels = GRAPH_LABELS

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("steps", "drive length (steps)", "int", 150, lo=10, hi=600, step=10, live=False),
            Param("motion_noise", "odometry noise (× default variance)", "float", 4.0, lo=0.1, hi=20.0, step=0.1,
                  live=False),
            seed_param(),
        ]
        super().__init__(params, seed)
        self.actions = (("optimize", "optimize"), ("reset", "reset"))
        self._build()

    def _build(self) -> None:
        cfg = ScenarioConfig(name="room", motion=MotionNoise().scaled(float(self.values["motion_noise"])),
                             lidar=LidarConfig(enabled=False))
        self.sim = Simulator(cfg, seed=int(self.values["seed"]))
        self.route = WaypointFollower(self.sim.waypoints, float(self.sim.config.speed_mps or 1.0))
        self.dr = make_estimator("dead-reckoning", log_metadata=self.sim.metadata())
        self.dr.reset(self.sim.initial_pose, rng=self.sim.rng["estimator"])
        self.dr_path: list[Array] = [self.sim.initial_pose.copy()]
        self.problem: BatchProblem | None = None
        self.values_now: Values | None = None
        self.optimizer: Optimizer | None = None
        self.iteration = 0
        self.cost = float("nan")
        self.converged = False
        self.omega: Array | None = None
        self.omega_nnz = (0, 0)
        self.initial_ate = float("nan")
        self._first_cost = float("nan")
        self._acc = 0.0
        self.notices = []

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def rows(self) -> list[str]:
        if self.problem is None:
            return ["poses"]
        return list(self.scalars)

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if value != old:
            self._build()

    def on_action(self, name: str) -> None:
        if name == "reset":
            self._build()
        elif name == "optimize" and self.problem is None:
            self._make_graph()

    def _make_graph(self) -> None:
        log = self.sim.to_log()
        poses = np.asarray(self.dr_path)
        self.problem = landmark_graph(log, self.sim.config.motion, self.sim.config.sensor.covariance, poses)
        self.values_now = self.problem.initial
        self.optimizer = Optimizer(self.problem.graph, OptimizerConfig(method="gn", max_iterations=1))
        pattern = information_pattern(self.problem.graph, self.values_now.pose_keys, self.values_now.point_keys)
        self.omega = block_average(pattern.astype(np.float64))
        self.omega_nnz = (int(pattern.sum()), pattern.size)
        assert log.true_poses is not None
        self.true_poses = np.asarray(log.true_poses)
        self.initial_ate = ate(poses, self.true_poses).rmse_m

    def advance(self, wall_dt_s: float) -> None:
        if self.problem is None:
            # still driving: record the route at 20 steps/s until the chosen length
            if self.sim.index >= int(self.values["steps"]):
                return
            self._acc += wall_dt_s * 20.0
            n = min(int(self._acc), 8)
            self._acc = 0.0 if n == 8 else self._acc - n
            for _ in range(min(n, int(self.values["steps"]) - self.sim.index)):
                v, w = self.route.command(self.sim.pose, self.sim.world.walls)
                step = self.sim.step(v, w)
                self.dr.step(step)
                self.dr_path.append(np.asarray(self.dr.estimate().pose, dtype=np.float64).copy())
            return
        if self.converged:
            return
        self._acc += wall_dt_s
        if self._acc < ITERATION_PERIOD_S:
            return
        self._acc = 0.0
        self.iterate()

    def iterate(self) -> None:
        """One Gauss-Newton iteration (stops when the cost no longer drops or after ``MAX_ITERATIONS``)."""
        assert self.optimizer is not None and self.values_now is not None
        try:
            new, summary = self.optimizer.optimize(self.values_now)
        except Exception as e:
            self.notices = [f"optimisation failed: {type(e).__name__}: {e}"]
            self.converged = True
            return
        self.iteration += 1
        prev = self.cost
        self.cost = float(summary.cost_final)
        self.values_now = new
        if self.iteration == 1:
            self._first_cost = float(summary.cost_initial)
        if self.iteration >= MAX_ITERATIONS or (prev == prev and prev - self.cost <= 1e-6 * max(prev, 1e-12)):
            self.converged = True
            ate_now = ate(self.current_poses(), self.true_poses).rmse_m
            self.complete_task(f"Done: the cost fell from {self._first_cost:.4g} to {self.cost:.4g} in "
                               f"{self.iteration} Gauss-Newton iterations, and the trajectory error from "
                               f"{self.initial_ate:.3f} m (dead reckoning) to {ate_now:.3f} m: every pose and landmark "
                               "moved at once to agree with all the measurements.")

    def current_poses(self) -> Array:
        if self.values_now is None:
            return np.asarray(self.dr_path)
        order = np.argsort(self.values_now.pose_keys)
        return np.asarray(self.values_now.poses)[order]

    def sections(self) -> Sections:
        poses = self.current_poses()
        vals, prob = self.values_now, self.problem
        nan = float("nan")
        nums = {"poses": float(len(poses)), "landmarks": float(len(vals.point_keys)) if vals is not None else nan,
                "factors": float(prob.graph.num_factors) if prob is not None else nan,
                "iteration": float(self.iteration), "cost": self.cost, "ate_initial_m": self.initial_ate,
                "ate_now_m": ate(poses, self.true_poses).rmse_m if prob is not None else nan,
                "omega_nonzero_blocks": float(self.omega_nnz[0]), "omega_blocks": float(self.omega_nnz[1])}
        true_path = np.asarray(self.sim.to_log().true_poses)[:, :2] if prob is None else self.true_poses[:, :2]
        out: Sections = [("NUMS", np.array([nums[k] for k in self.scalars])), ("WALL", self.sim.world.walls),
                         ("TLMK", self.sim.world.landmarks), ("TPOS", self.sim.pose),
                         ("TPTH", downsample(true_path)), ("EPTH", downsample(poses[:, :2])), ("EPOS", poses[-1])]
        if vals is not None and prob is not None:
            pts = np.asarray(vals.points)
            lm_by_id = pts[np.searchsorted(vals.point_keys, prob.obs_ids)] if len(pts) else pts
            seg_obs = np.hstack([poses[prob.obs_steps, :2], lm_by_id])
            out += [("ELMK", pts), ("GNOD", poses[:, :2]), ("GEDG", seg_obs[:: max(1, len(seg_obs) // 1500)]),
                    ("GHST", downsample(np.asarray(self.dr_path)[:, :2]))]
            if self.omega is not None:
                out.append(("HEAT", self.omega))
        return out
