"""The simulator-backed session (pages 0, 2, 5, 6, 8, 9): a live :class:`Simulator` plus a registered estimator,
driven by the arrow keys, auto-explore or the scenario's route."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from slam2d.estimator import Estimate, Estimator, GraphView, SupportsGraphView, SupportsLoopClosure
from slam2d.eval.trajectory import ate
from slam2d.graph.lidar import LidarSLAM
from slam2d.lab.registry import estimator_names, get_spec, make_estimator
from slam2d.log import Step
from slam2d.models.lidar import LidarConfig
from slam2d.models.motion import MotionNoise
from slam2d.models.sensors import SensorConfig, range_bearing_inverse
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.simulator import Simulator
from slam2d.sim.trajectory import AutoExplorer, WaypointFollower
from slam2d.web.params import Param
from slam2d.web.sessions.base import (
    Array,
    PathBuffer,
    Sections,
    Session,
    abs_correlation,
    downsample,
    observation_covariances,
)

#: wall time one frame may spend stepping the simulation and estimator before the frame goes out anyway
STEP_BUDGET_S = 0.05
#: try-this tasks: the step at which runs are compared; the big loop's "away" and "back" distances from the start
#: and the steps after the return before the correction is reported
TASK_STEP, BIG_LOOP_AWAY_M, BIG_LOOP_NEAR_M, TASK_SETTLE_STEPS = 200, 10.0, 2.0, 20
#: the lidar back end on the simulator page: its worlds, a scan every LIDAR_EVERY steps, its grid rebuilt every
#: LIDAR_GRID_EVERY steps with at most about LIDAR_GRID_CELLS cells
LIDAR_WORLDS = ("room", "warehouse")
LIDAR_EVERY, LIDAR_GRID_EVERY, LIDAR_GRID_CELLS = 2, 20, 40_000
#: poses re-optimised per step by the graph back end on these pages (``GraphSLAMConfig.window``)
GRAPH_WINDOW = 20
#: graph edges drawn at most (about): a long drive's thousands of factors would bury the map; graph nodes drawn at
#: most (evenly spaced; the estimated path runs through all of them)
MAX_EDGES, MAX_NODES = 1500, 500
#: the loop page's "you are back" prompt: after driving farther than AWAY from the start, coming within NEAR of it
RETURN_AWAY_M, RETURN_NEAR_M = 20.0, 6.0
#: particles x the world's landmarks at most (a particle back end keeps an EKF per pair, and copies all when it
#: resamples: 2000 x 2000 took 1.2 GB after 30 steps)
MAX_PARTICLE_LANDMARKS = 200_000

SIM_LABELS = {
    "step": "step", "time_s": "simulated time (s)", "landmarks_seen": "landmarks seen so far",
    "landmarks_mapped": "landmarks in the map", "landmarks_tentative": "tentative landmarks",
    "state_dim": "state dimension", "ate_rmse_m": "trajectory error, ATE RMSE (m)",
    "pose_error_m": "current position error (m)", "n_eff": "effective particles N_eff", "particles": "particles",
    "resamples": "resampling steps", "loops_accepted": "loop closures accepted",
    "est_ms": "estimator time per step (ms)",
    "true_x": "true x (m)", "true_y": "true y (m)", "true_theta": "true heading (rad)",
}


def _sim_params(estimators: list[str], default_estimator: str, *, scenario: str, drive: str, controls: set[str],
                speed: float) -> list[Param]:
    all_params = [
        Param("estimator", "estimator", "choice", default_estimator, choices=tuple(estimators), live=False,
              help="which registered back end estimates the map and the pose"),
        Param("scenario", "world", "choice", scenario, choices=tuple(sorted(SCENARIOS)), live=False),
        Param("landmarks", "landmarks", "int", 0, lo=0, hi=2000, step=1, live=False,
              help="0 = the world's default count (room, loop and grid worlds)"),
        Param("seed", "random seed", "int", 0, lo=0, hi=2**31 - 1, step=1, live=False),
        Param("drive", "driving", "choice", drive, choices=("keys", "explore", "route")),
        Param("steps_per_s", "simulation speed (steps/s)", "float", speed, lo=1.0, hi=60.0, step=1.0),
        Param("sensor_range_m", "sensor range (m)", "float", 8.0, lo=1.0, hi=100.0, step=0.5),
        Param("obs_noise", "observation noise (× default)", "float", 1.0, lo=0.1, hi=10.0, step=0.1, live=False,
              help="multiplies the range (0.1 m) and bearing (0.02 rad) standard deviations"),
        Param("motion_noise", "odometry noise (× default variance)", "float", 1.0, lo=0.0, hi=20.0, step=0.1,
              live=False, help="multiplies every odometry noise variance; 0 = perfect odometry"),
        Param("particles", "particles", "int", 50, lo=1, hi=2000, step=1, live=False),
        Param("obs_ellipses", "observation ellipses", "bool", False),
        Param("view", "show", "choice", "estimate", choices=("estimate", "graph"),
              help="graph: the back end's factor graph (poses, landmarks and the factors between them)"),
        Param("loop_closure", "loop closure", "bool", True, live=False,
              help="the estimator's loop_closure switch (only back ends that have one)"),
        Param("wrong_association", "break it: 50% wrong landmark ids", "bool", False, live=False,
              help="half of the reported landmark ids are replaced by another landmark's id"),
        Param("few_landmarks", "break it: only 1/5 of landmarks", "bool", False, live=False,
              help="only a random fifth of the landmarks ever report observations"),
        Param("paused", "paused", "bool", False),
    ]
    return [p for p in all_params if p.name in controls]


#: values every simulator session has, whether or not the page shows a control for them
_HIDDEN_DEFAULTS: dict[str, Any] = {"landmarks": 0, "sensor_range_m": 8.0, "obs_noise": 1.0, "motion_noise": 1.0,
                                    "particles": 50, "obs_ellipses": False, "view": "estimate", "loop_closure": True,
                                    "wrong_association": False, "few_landmarks": False}


class SimSession(Session):
    """A live :class:`Simulator` plus a registered estimator (``estimator`` must be registered)."""

    page = "sim"
    scalars = tuple(SIM_LABELS)
    labels = SIM_LABELS

    def __init__(self, *, page: str, title: str, estimator: str, seed: int = 0, scenario: str = "room",
                 drive: str = "keys", controls: Sequence[str] = (), speed: float = 10.0, heat: bool = False,
                 graph_view: bool = False, defaults: Mapping[str, Any] | None = None) -> None:
        self.page, self.title = page, title
        names = estimator_names()
        if estimator not in names:
            raise ValueError(f"page {page!r}: estimator {estimator!r} is not registered; valid: {names}")
        ctl = set(controls) | {"seed", "paused"}
        page_defaults = dict(defaults or {})
        params = [dataclasses.replace(p, default=page_defaults[p.name]) if p.name in page_defaults else p
                  for p in _sim_params(names, estimator, scenario=scenario, drive=drive, controls=ctl, speed=speed)]
        super().__init__(params, seed=seed)
        for k, v in {"estimator": estimator, "scenario": scenario, "drive": drive, "steps_per_s": speed,
                     **_HIDDEN_DEFAULTS, **page_defaults}.items():
            self.values.setdefault(k, v)
        self.heat = heat
        self.show_graph = graph_view
        self.actions = (("reset", "reset"), ("step", "one step"))
        if page == "loop":
            self.actions += (("close_loop", "close loop now"),)
        self.error: str | None = None
        self._ate_at: dict[str, float] = {}  # try-this bookkeeping that outlives a restart (estimator, noise)
        self._build()

    # --- construction -------------------------------------------------------------------------------------------
    def _scenario_config(self) -> ScenarioConfig:
        name = str(self.values["scenario"])
        k = float(self.values["obs_noise"])
        base = SensorConfig()
        sensor = dataclasses.replace(base, max_range_m=float(self.values["sensor_range_m"]),
                                     range_std_m=base.range_std_m * k, bearing_std_rad=base.bearing_std_rad * k)
        m = float(self.values["motion_noise"])
        motion = MotionNoise().scaled(m) if m > 0 else MotionNoise(
            alpha_rot_rot=0.0, alpha_rot_trans=0.0, alpha_trans_trans=0.0, alpha_trans_rot=0.0, min_trans_std_m=0.0,
            min_rot_std_rad=0.0)
        landmarks = int(self.values["landmarks"])
        extra: dict[str, Any] = {}
        if landmarks > 0 and "landmarks" in SCENARIOS[name].defaults:
            extra["landmarks"] = landmarks
        # scans only for the lidar back ends, every LIDAR_EVERY steps (scan matching costs more than a step)
        lidar = LidarConfig(every=LIDAR_EVERY) if self._needs_scans(str(self.values["estimator"])) \
            else LidarConfig(enabled=False)
        return ScenarioConfig(name=name, sensor=sensor, motion=motion, lidar=lidar, **extra)

    @staticmethod
    def _needs_scans(name: str) -> bool:  # a lidar back end (lidar, lidar-lifelong): the simulator must scan for it
        return get_spec(name).needs == "scans"

    def _check_particle_budget(self) -> None:
        """ValueError (the command is refused) when a particle back end would exceed ``MAX_PARTICLE_LANDMARKS``."""
        if "particles" not in self._config_fields(str(self.values["estimator"])):
            return
        m = int(self.values["particles"])
        n = len(Simulator(self._scenario_config(), seed=int(self.values["seed"])).world.landmark_ids)
        if m * n > MAX_PARTICLE_LANDMARKS:
            raise ValueError(f"{m} particles x {n} landmarks is more than this page allows "
                             f"({MAX_PARTICLE_LANDMARKS} landmark filters); use at most "
                             f"{max(1, MAX_PARTICLE_LANDMARKS // max(n, 1))} particles in this world, or fewer "
                             "landmarks")

    def _config_fields(self, name: str) -> set[str]:
        return {f.name for f in dataclasses.fields(get_spec(name).config_cls)}

    def _estimator_overrides(self, name: str) -> dict[str, Any]:
        fields = self._config_fields(name)
        out: dict[str, Any] = {}
        if "particles" in fields:
            out["particles"] = int(self.values["particles"])
        if self.heat and "snapshot_full_cov" in fields:  # the EKF copies its full P only when asked (O(N^2))
            out["snapshot_full_cov"] = True
        if "window" in fields:  # graph SLAM: bounded work per step, so a long drive keeps the page's frame rate
            out["window"] = GRAPH_WINDOW
        if "loop_closure" in self.params and "loop_closure" in fields:
            out["loop_closure"] = bool(self.values["loop_closure"])
        return out

    def _build(self) -> None:
        """(Re)start the simulator and estimator from the current values (same seed: same world and noise)."""
        name = str(self.values["estimator"])
        self.start_error: str | None = None
        if self._needs_scans(name) and self.values["scenario"] not in LIDAR_WORLDS:
            self.start_error = (f"estimator '{name}' matches scans against walls: choose the world "
                                f"{' or '.join(LIDAR_WORLDS)}; showing 'dead-reckoning' instead.")
            name = self.values["estimator"] = "dead-reckoning"
        self.sim = Simulator(self._scenario_config(), seed=int(self.values["seed"]))
        self._grid: tuple[int, Array, Array] | None = None  # the lidar map: step built, probabilities, placement
        try:
            self.est: Estimator = make_estimator(name, self._estimator_overrides(name) or None,
                                                 log_metadata=self.sim.metadata())
            self.est.reset(self.sim.initial_pose, rng=self.sim.rng["estimator"])
            self.snap: Estimate = self.est.estimate()
        except Exception as e:  # a back end that cannot start must not break the page: say so, use the baseline
            self.start_error = (f"estimator '{name}' could not be started ({type(e).__name__}: {e}); "
                                "showing 'dead-reckoning' instead.")
            self.values["estimator"] = "dead-reckoning"
            self.est = make_estimator("dead-reckoning", log_metadata=self.sim.metadata())
            self.est.reset(self.sim.initial_pose, rng=self.sim.rng["estimator"])
            self.snap = self.est.estimate()
        speed = float(self.sim.config.speed_mps or 1.0)
        self.explorer = AutoExplorer(speed, self.sim.rng["driver"])
        self.route = WaypointFollower(self.sim.waypoints, speed)
        self.true_path = PathBuffer(self.sim.pose)
        self.est_path = PathBuffer(self.snap.pose)
        self.seen: set[int] = set()
        self.last_step: Step | None = None
        self.ghost: Array | None = None
        self._been_away = False
        self._big_away = False
        self._away_sigma = 0.0
        self._return: tuple[int, Array, float, float, float] | None = None
        # break-it damage (same rules as slam2d.lab.breakit, applied step by step): its own random stream
        self.breakit_rng = np.random.default_rng([int(self.values["seed"]), 0xB4EA])
        ids = self.sim.world.landmark_ids
        self.kept_ids = self.breakit_rng.choice(ids, size=max(1, round(0.2 * len(ids))), replace=False)
        self.est_ms = 0.0
        self.resamples = 0
        self._acc = 0.0
        self._ate_cache: tuple[int, float] = (-1, 0.0)
        self._heat_cache: tuple[int, Array | None] = (-1, None)
        self.error = None
        self._update_notices()

    def _update_notices(self) -> None:
        name = str(self.values["estimator"])
        notes = []
        if self.heat and self.snap.full_cov is None:
            notes.append(f"covariance heat map: estimator '{name}' does not report a full covariance, so there is "
                         "no heat map for it.")
        if self.start_error:
            notes.append(self.start_error)
        if isinstance(self.est, LidarSLAM):
            notes.append(f"lidar: a scan every {LIDAR_EVERY} steps (scan matching costs more than a step); the "
                         f"occupancy grid drawn is rebuilt from the keyframes every {LIDAR_GRID_EVERY} steps.")
        if self.error:
            notes.append(self.error)
        self.notices = notes

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def inactive(self) -> list[str]:
        fields = self._config_fields(str(self.values["estimator"]))
        out: list[str] = [p for p in ("particles", "loop_closure") if p in self.params and p not in fields]
        if "view" in self.params and not isinstance(self.est, SupportsGraphView):
            out.append("view")  # only graph back ends have a graph to show
        return out

    # --- commands -----------------------------------------------------------------------------------------------
    def on_param(self, name: str, value: Any, old: Any) -> None:
        p = self.params[name]
        if name == "sensor_range_m":
            # range only limits what the simulator reports; estimators do not use it, so it changes live
            self.sim.config = dataclasses.replace(
                self.sim.config, sensor=dataclasses.replace(self.sim.config.sensor, max_range_m=float(value)))
        elif not p.live and value != old:
            self._check_particle_budget()
            self._build()

    def on_action(self, name: str) -> None:
        if name == "reset":
            self._build()
        elif name == "step":
            self._step_once()
        elif name == "close_loop":
            self._close_loop()

    def _close_loop(self) -> None:
        """Ask the back end to close a loop from the latest observations now (back ends with ``close_loop_now``)."""
        self.notices = [n for n in self.notices if not n.startswith("close loop")]
        if not isinstance(self.est, SupportsLoopClosure) or self.last_step is None:
            self.notices.append("close loop: drive first; there are no observations yet" if self.last_step is None
                                else f"close loop: estimator '{self.values['estimator']}' cannot close loops on request"
                                )
            return
        obs = self.last_step.observations
        before = self.trajectory().copy()
        ate_before = self.ate_rmse()
        try:
            ok = bool(self.est.close_loop_now(obs.z[obs.landmark_id != -2]))
        except Exception as e:
            self.notices.append(f"close loop failed: {type(e).__name__}: {e}")
            return
        self.snap = self.est.estimate()
        self._ate_cache = (-1, 0.0)  # the back end may have re-estimated the whole trajectory
        if ok:
            self.ghost = before  # drawn faintly: the path before the correction, for before/after
            self.notices = [n for n in self.notices if not n.startswith("try this")]
            moved = float(np.max(np.hypot(*(self.trajectory()[:, :2] - before[:, :2]).T)))
            self.complete_task(f"Done: the closure moved the estimated path by up to {moved:.2f} m (grey: before) "
                               f"and the trajectory error went {ate_before:.3f} -> {self.ate_rmse():.3f} m.")
        self.notices.append("close loop: accepted — the correction spread along the trajectory" if ok else
                            "close loop: no verified loop from here (drive back near the start and try again)")

    # --- simulation ---------------------------------------------------------------------------------------------
    def command(self) -> tuple[float, float]:
        drive = self.values["drive"]
        segs = self.sim.world.solid_segments(self.sim.time_s)
        if drive == "explore":
            return self.explorer.command(self.sim.pose, segs)
        if drive == "route":
            return self.route.command(self.sim.pose, segs)
        k = self.keys_down
        speed = float(self.sim.config.speed_mps or 1.0)
        v = speed * (("ArrowUp" in k) - ("ArrowDown" in k))
        w = 1.0 * (("ArrowLeft" in k) - ("ArrowRight" in k))
        return float(v), float(w)

    def _step_once(self) -> None:
        if self.error:
            return
        v, w = self.command()
        raw = self.sim.step(v, w)
        step = self.damage(raw)
        t0 = time.perf_counter()
        try:
            self.est.step(step)
            self.snap = self.est.estimate()
        except Exception as e:  # a failing back end must not take the server down; show it and stop this session
            self.error = f"estimator '{self.values['estimator']}' failed at step {step.index}: " \
                         f"{type(e).__name__}: {e}"
            self.values["paused"] = True
            self._update_notices()
            return
        self.est_ms = 1e3 * (time.perf_counter() - t0)
        self.resamples += bool(self.snap.particles is not None and self.snap.particles.resampled)
        self.last_step = step
        ids = raw.observations.landmark_id  # "seen" counts what the sensor saw, before any break-it damage
        self.seen.update(int(i) for i in np.unique(ids[ids >= 0]))
        self.true_path.append(self.sim.pose)
        if self.page == "loop":
            self._watch_for_return()
        self.est_path.append(self.snap.pose)
        if self.task is not None and self.task_result is None:
            self._watch_task()

    def _watch_task(self) -> None:
        """Detect the page's try-this task (slam2d.web.tasks) from the run so far."""
        page, i = self.page, self.sim.index
        if page == "problem" and i == TASK_STEP:
            self._ate_at[str(self.values["estimator"])] = self.ate_rmse()
            if "dead-reckoning" in self._ate_at and len(self._ate_at) >= 2:
                rows = ", ".join(f"{k} {v:.3f} m" for k, v in self._ate_at.items())
                self.complete_task(f"Done: trajectory error at step {TASK_STEP}: {rows}. Without landmarks nothing "
                                   "pulls the estimate back, so dead reckoning drifts without bound.")
        elif page == "drift" and i == TASK_STEP // 2:
            noise = float(self.values["motion_noise"])
            self._ate_at[f"{noise:g}"] = self.ate_rmse()
            low = [k for k in self._ate_at if float(k) == 0.0]
            high = [k for k in self._ate_at if float(k) >= 10.0]
            if low and high:
                self.complete_task(f"Done: after {i} steps the ATE is {self._ate_at[low[0]]:.3f} m with no odometry "
                                   f"noise and {self._ate_at[high[0]]:.3f} m with noise x{high[0]}: drift comes only "
                                   "from the noise, and it accumulates.")
        elif page == "fastslam" and self.snap.particles is not None and self.snap.particles.resampled:
            m = len(self.snap.particles.poses)
            if m <= 20:
                self.complete_task(f"Done: at step {i} the weights of the {m} particles were uneven enough (N_eff "
                                   f"{self.snap.particles.n_eff:.1f}, below {m / 2:g}) that the filter resampled: "
                                   "heavy particles were copied, light ones dropped.")
        elif page in ("ekf", "simulator"):
            self._watch_big_loop()

    def _watch_big_loop(self) -> None:
        """The robot left its start by more than BIG_LOOP_AWAY_M and came back within BIG_LOOP_NEAR_M: record the
        estimate, and TASK_SETTLE_STEPS later say what coming back corrected."""
        start = self.true_path[0][:2]
        d = float(np.hypot(*(self.sim.pose[:2] - start)))
        if self._return is None:
            if d > BIG_LOOP_AWAY_M:
                self._big_away = True
                self._away_sigma = max(self._away_sigma, self._position_sigma())
            elif self._big_away and d < BIG_LOOP_NEAR_M:
                self._return = (self.sim.index, self.trajectory().copy(), self._position_sigma(),
                                self.numbers()["pose_error_m"], self.ate_rmse())
            return
        i0, traj0, s0, e0, a0 = self._return
        if self.sim.index - i0 < TASK_SETTLE_STEPS:
            return
        moved = float(np.max(np.hypot(*(self.trajectory()[: len(traj0), :2] - traj0[:, :2]).T)))
        how = (f"the estimated path itself moved by up to {moved:.2f} m: this back end re-estimates the past"
               if moved > 1e-6 else "the path drawn so far did not move: a filter corrects the present pose and "
               "the map, not the past")
        self.complete_task(f"Done: back at the start at step {i0} (position uncertainty, 1 sigma, at most "
                           f"{self._away_sigma:.3f} m while away). Over the next {TASK_SETTLE_STEPS} steps it went "
                           f"{s0:.3f} -> {self._position_sigma():.3f} m and the "
                           f"position error {e0:.3f} -> {self.numbers()['pose_error_m']:.3f} m; {how}.")

    def _position_sigma(self) -> float:
        cov = self.snap.pose_cov
        return float(np.sqrt(np.trace(np.asarray(cov)[:2, :2]) / 2)) if cov is not None else float("nan")

    def _watch_for_return(self) -> None:
        """The loop page's try-this: notice when the robot comes back to where it started after a long drive, and
        point at the button (once per return)."""
        start = self.true_path[0][:2]
        d = float(np.hypot(*(self.sim.pose[:2] - start)))
        if d > RETURN_AWAY_M:
            self._been_away = True
        elif d < RETURN_NEAR_M and self._been_away:
            self._been_away = False
            self.notices = [n for n in self.notices if not n.startswith(("try this", "close loop"))]
            self.notices.append("try this: you are back near the start, with the drift of the whole loop in the "
                                "estimate — press 'close loop now' and watch the blue path bend onto the truth (the "
                                "grey ghost keeps the old one) and the ATE drop.")

    def damage(self, step: Step) -> Step:
        """The break-it toggles: what the estimator is told, not what the world does."""
        obs = step.observations
        if self.values["few_landmarks"]:
            obs = obs.subset(np.isin(obs.landmark_id, self.kept_ids) | (obs.landmark_id < 0))
        if self.values["wrong_association"] and len(obs):
            ids = obs.landmark_id.copy()
            world = np.sort(self.sim.world.landmark_ids)
            pick = np.flatnonzero((ids >= 0) & (self.breakit_rng.random(len(ids)) < 0.5))
            if len(world) >= 2 and len(pick):
                pos = np.searchsorted(world, ids[pick])
                ids[pick] = world[(pos + self.breakit_rng.integers(1, len(world), size=len(pick))) % len(world)]
            obs = dataclasses.replace(obs, landmark_id=ids)
        return step if obs is step.observations else dataclasses.replace(step, observations=obs)

    def advance(self, wall_dt_s: float) -> None:
        if self.values["paused"] or self.error:
            self._acc = 0.0
            return
        self._acc += max(0.0, wall_dt_s) * float(self.values["steps_per_s"])
        n = int(self._acc)
        if n > 8:  # far behind (a stall): drop the backlog instead of bursting ahead of wall time
            n, self._acc = 8, 0.0
        else:
            self._acc -= n
        t0 = time.perf_counter()
        for i in range(n):
            self._step_once()
            if time.perf_counter() - t0 > STEP_BUDGET_S and i + 1 < n:
                # a slow back end: send a frame now and drop the rest (the page stays live; sim time lags)
                self._acc = 0.0
                break

    # --- numbers ------------------------------------------------------------------------------------------------
    def trajectory(self) -> Array:
        """The estimated trajectory: the back end's own (re-estimated) one when it reports it, else pose history."""
        traj = self.snap.trajectory
        if traj is not None and len(traj) == len(self.true_path):
            return np.asarray(traj, dtype=np.float64)
        return np.asarray(self.est_path)

    def ate_rmse(self) -> float:
        """ATE (after SE(2) alignment) against the true path, via ``slam2d.eval.trajectory.ate``; nan if diverged."""
        if self._ate_cache[0] != (n := len(self.true_path)):
            traj = self.trajectory()
            ok = np.isfinite(traj).all()
            self._ate_cache = (n, (ate(traj, np.array(self.true_path)).rmse_m if ok else np.nan) if n > 1 else 0.0)
        return self._ate_cache[1]

    def rows(self) -> Sequence[str]:
        snap = self.snap
        skip = set()
        if snap.particles is None:
            skip |= {"n_eff", "particles", "resamples"}
        if snap.tentative_landmarks is None:
            skip.add("landmarks_tentative")
        if snap.state_dim is None:
            skip.add("state_dim")
        if not isinstance(self.est, SupportsLoopClosure):
            skip.add("loops_accepted")
        if self.values["estimator"] == "dead-reckoning":
            skip |= {"landmarks_mapped"}
        return [s for s in self.scalars if s not in skip]

    def numbers(self) -> dict[str, float]:
        snap = self.snap
        sd = snap.state_dim
        parts = snap.particles.poses if snap.particles is not None else None
        n_eff = snap.particles.n_eff if snap.particles is not None else None
        tent = snap.tentative_landmarks
        pose = self.sim.pose
        nan = float("nan")
        return {
            "step": float(self.sim.index),
            "time_s": float(self.sim.time_s),
            "landmarks_seen": float(len(self.seen)),
            "landmarks_mapped": float(len(snap.landmarks)),
            "landmarks_tentative": float(len(tent)) if tent is not None else nan,
            "state_dim": float(sd) if sd is not None else nan,
            "ate_rmse_m": self.ate_rmse(),
            "pose_error_m": float(np.hypot(*(np.asarray(snap.pose)[:2] - pose[:2]))),
            "n_eff": float(n_eff) if n_eff is not None else nan,
            "particles": float(len(parts)) if parts is not None else nan,
            "resamples": float(self.resamples),
            "loops_accepted": float(snap.diagnostics.loops_accepted) if isinstance(self.est, SupportsLoopClosure)
            else nan,
            "est_ms": self.est_ms,
            "true_x": float(pose[0]), "true_y": float(pose[1]), "true_theta": float(pose[2]),
        }

    def heat_matrix(self) -> Array | None:
        cov = self.snap.full_cov
        if cov is None:
            return None
        if self._heat_cache[0] != self.sim.index:
            self._heat_cache = (self.sim.index, abs_correlation(np.asarray(cov)))
        return self._heat_cache[1]

    def sections(self) -> Sections:
        nums = self.numbers()
        snap = self.snap
        out: Sections = [
            ("NUMS", np.array([nums[k] for k in self.scalars])),
            ("WALL", self.sim.world.walls),
            ("TLMK", self.sim.world.landmarks),
            ("TPOS", self.sim.pose),
            ("TPTH", downsample(np.asarray(self.true_path)[:, :2])),
            ("EPOS", np.asarray(snap.pose)),
            ("EPTH", downsample(self.trajectory()[:, :2])),
        ]
        if "sensor_range_m" in self.params:  # pages where the range is a control draw it around the robot
            out.append(("RNGE", np.array([*self.sim.pose[:2], float(self.sim.config.sensor.max_range_m)])))
        if self.ghost is not None:
            out.append(("GHST", downsample(self.ghost[:, :2])))
        if snap.pose_cov is not None:
            out.append(("PCOV", np.asarray(snap.pose_cov)[:2, :2].reshape(1, 4)))
        if len(snap.landmarks):
            out.append(("ELMK", np.asarray(snap.landmarks).reshape(-1, 2)))
            if snap.landmark_covs is not None:
                out.append(("ECOV", np.asarray(snap.landmark_covs).reshape(-1, 4)))
        if self.last_step is not None:
            obs = self.last_step.observations
            z = obs.z[obs.landmark_id != -2] if len(obs) else np.zeros((0, 2))
            est_pose = np.asarray(snap.pose, dtype=np.float64)
            if len(z):
                out.append(("OBSV", range_bearing_inverse(np.broadcast_to(est_pose, (len(z), 3)), z)))
                if self.values["obs_ellipses"]:
                    out.append(("OCOV", observation_covariances(est_pose, z, self.sim.config.sensor.covariance)
                                .reshape(-1, 4)))
        if snap.particles is not None and len(snap.particles.poses):
            out.append(("PART", np.asarray(snap.particles.poses, dtype=np.float64).reshape(-1, 3)))
        if self.heat:
            h = self.heat_matrix()
            if h is not None:
                out.append(("HEAT", h))
        if isinstance(self.est, LidarSLAM) and self.sim.index > 0:
            out.extend(self._lidar_grid())
        show_graph = self.show_graph or self.values["view"] == "graph"
        if show_graph and isinstance(self.est, SupportsGraphView):
            out.extend(graph_view_sections(self.est.graph_view()))
        return out


    def _lidar_grid(self) -> Sections:
        """The lidar back end's occupancy grid (its public ``occupancy_grid()``), rebuilt every LIDAR_GRID_EVERY
        steps at a resolution that keeps it under LIDAR_GRID_CELLS cells."""
        assert isinstance(self.est, LidarSLAM)
        if self._grid is None or self.sim.index - self._grid[0] >= LIDAR_GRID_EVERY:
            try:
                x0, y0, x1, y1 = self.bounds()
                res = max(0.1, float(np.sqrt((x1 - x0 + 2) * (y1 - y0 + 2) / LIDAR_GRID_CELLS)))
                grid = self.est.occupancy_grid(res)
            except ValueError:  # no keyframe yet
                return []
            self._grid = (self.sim.index, grid.probability(), np.array([*grid.origin, grid.resolution]))
        return [("GRID", self._grid[1]), ("GRDM", self._grid[2])]


def _lookup(keys: np.ndarray, values: Array, query: np.ndarray) -> Array:
    """Rows of ``values`` whose ``keys`` equal ``query`` (each must exist). Shapes: (N,),(N,d),(Q,) -> (Q,d)."""
    order = np.argsort(keys, kind="stable")
    pos = np.clip(np.searchsorted(keys, query, sorter=order), 0, max(len(keys) - 1, 0))
    idx = order[pos]
    if len(query) and not np.array_equal(keys[idx], query):
        raise KeyError("graph edge refers to an unknown variable")
    return values[idx]


def graph_view_sections(view: GraphView) -> Sections:
    """Segments for a back end's ``graph_view()``: poses/points with keys, edges per factor kind as key pairs."""
    pk = view.pose_keys
    poses = view.poses[:, :2]
    segs = []
    # unary factors (priors, GPS) have no edge to draw; beyond MAX_EDGES, every n-th edge (thinned before lookup)
    drawn = {kind: keys for kind, keys in view.edges.items() if kind in ("between", "range_bearing", "point", "bearing",
                                                                        "range")}
    stride = max(1, sum(len(k) for k in drawn.values()) // MAX_EDGES)
    for kind, keys in drawn.items():
        k = np.asarray(keys, dtype=np.int64).reshape(-1, 2)[::stride]
        if kind == "between":
            segs.append(np.hstack([_lookup(pk, poses, k[:, 0]), _lookup(pk, poses, k[:, 1])]))
        else:
            segs.append(np.hstack([_lookup(pk, poses, k[:, 0]), _lookup(view.point_keys, view.points, k[:, 1])]))
    edges = np.vstack(segs) if segs else np.zeros((0, 4))
    return [("GNOD", downsample(poses, MAX_NODES)), ("GEDG", edges)]
