"""Per-connection sessions: each browser tab owns one simulator and one estimator on the server.

A session receives validated commands (keys, parameters, actions), advances its simulation by wall-clock time and
produces frame sections (see ``frames.py``). Every number a page shows is computed here by library calls; the
browser only draws.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.estimator import Estimate, Estimator, GraphView, SupportsGraphView, SupportsLoopClosure
from slam2d.eval.trajectory import ate
from slam2d.geometry import se2
from slam2d.lab.registry import estimator_names, get_spec, make_estimator
from slam2d.log import Step
from slam2d.models.lidar import LidarConfig, scan_to_points
from slam2d.models.motion import MotionNoise, odometry_factor
from slam2d.models.sensors import SensorConfig, range_bearing_inverse, range_bearing_inverse_jacobians
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.simulator import Simulator
from slam2d.sim.trajectory import AutoExplorer, WaypointFollower
from slam2d.web.backends import ESTIMATOR_LABELS, optional_module
from slam2d.web.params import CommandError, Param

Array = NDArray[np.float64]
Sections = list[tuple[str, Any]]

#: the keys a page may send, and what they do to the (v, w) command
DRIVE_KEYS = ("ArrowUp", "ArrowDown", "ArrowLeft", "ArrowRight")
#: particle-count config fields a FastSLAM-like estimator may use (the slider sets whichever exists)
PARTICLE_FIELDS = ("num_particles", "n_particles", "particles")
MAX_PATH_POINTS = 1500
HEAT_MAX = 96
#: wall time one frame may spend stepping the simulation and estimator before the frame goes out anyway
STEP_BUDGET_S = 0.05


def _downsample(points: Array, limit: int = MAX_PATH_POINTS) -> Array:
    """At most ``limit`` rows, evenly spaced, always keeping the last one (the current pose)."""
    n = len(points)
    if n <= limit:
        return points
    idx = np.unique(np.concatenate([np.linspace(0, n - 1, limit - 1).astype(np.int64), [n - 1]]))
    return points[idx]


def abs_correlation(cov: Array, limit: int = HEAT_MAX) -> Array:
    """|correlation| of a covariance matrix, block-averaged to at most ``limit`` x ``limit``. Shapes: (n,n) -> (m,m).

    Correlation rather than covariance, so the colour scale does not depend on units (m vs rad) and the growing
    off-diagonal blocks that make EKF-SLAM work are visible.
    """
    c = np.asarray(cov, dtype=np.float64)
    d = np.sqrt(np.clip(np.diag(c), 1e-300, None))
    corr = np.abs(c / d[:, None] / d[None, :])
    n = corr.shape[0]
    if n <= limit:
        return corr
    edges = np.linspace(0, n, limit + 1).astype(np.int64)
    # block sums via cumulative sums in both axes, then divide by block areas
    cs = np.zeros((n + 1, n + 1))
    cs[1:, 1:] = corr.cumsum(0).cumsum(1)
    s = cs[edges[1:]][:, edges[1:]] - cs[edges[:-1]][:, edges[1:]] - cs[edges[1:]][:, edges[:-1]] + \
        cs[edges[:-1]][:, edges[:-1]]
    sizes = np.diff(edges)
    return s / (sizes[:, None] * sizes[None, :])


def observation_covariances(pose: Array, z: Array, r_obs: Array) -> Array:
    """World-frame covariance of the landmarks placed by observations: ``G_z R G_z^T``.

    Shapes: pose (3,), z (K,2), r_obs (2,2) -> (K,2,2).
    """
    if len(z) == 0:
        return np.zeros((0, 2, 2))
    _, gz = range_bearing_inverse_jacobians(np.broadcast_to(pose, (len(z), 3)), z)
    return gz @ r_obs @ np.swapaxes(gz, -1, -2)


class Session:
    """Base class: parameters, validation of commands, hello message. Subclasses advance and draw."""

    page = "base"
    title = "session"
    scalars: tuple[str, ...] = ()

    def __init__(self, params: Sequence[Param], seed: int = 0) -> None:
        self.params = {p.name: p for p in params}
        self.values: dict[str, Any] = {p.name: p.default for p in params}
        if "seed" in self.values:
            self.values["seed"] = int(seed)
        self.notices: list[str] = []
        self.actions: tuple[tuple[str, str], ...] = ()
        self.keys_down: set[str] = set()

    # --- commands -----------------------------------------------------------------------------------------------
    def apply(self, msg: Mapping[str, Any]) -> dict[str, Any] | None:
        """Apply one validated command; returns an optional reply. Raises CommandError for bad commands."""
        kind = msg.get("type")
        if kind == "key":
            key, down = msg.get("key"), msg.get("down")
            if key not in DRIVE_KEYS or not isinstance(down, bool):
                raise CommandError(f"key command needs key in {list(DRIVE_KEYS)} and down true/false (got {dict(msg)})")
            (self.keys_down.add if down else self.keys_down.discard)(str(key))
            return None
        if kind == "param":
            name = msg.get("name")
            if not isinstance(name, str) or name not in self.params:
                raise CommandError(f"unknown parameter {name!r}; valid parameters: {sorted(self.params)}")
            if "value" not in msg:
                raise CommandError(f"parameter command for {name!r} has no value")
            value = self.params[name].coerce(msg["value"])
            old = self.values[name]
            self.values[name] = value
            try:
                self.on_param(name, value, old)
            except (ValueError, TypeError) as e:
                self.values[name] = old
                raise CommandError(f"cannot set {name!r} to {value!r}: {e}") from None
            return self.state()
        if kind == "action":
            name = msg.get("name")
            valid = [a for a, _ in self.actions]
            if name not in valid:
                raise CommandError(f"unknown action {name!r}; valid actions: {valid}")
            self.on_action(str(name))
            return self.state()
        if kind == "ping":
            return {"type": "pong"}
        raise CommandError(f"unknown command type {kind!r}; valid types: key, param, action, ping")

    def on_param(self, name: str, value: Any, old: Any) -> None:
        """React to a parameter change (values[name] is already set)."""

    def on_action(self, name: str) -> None:
        """React to a button."""

    # --- output -------------------------------------------------------------------------------------------------
    def hello(self) -> dict[str, Any]:
        return {**self.state(), "type": "hello", "page": self.page, "title": self.title,
                "scalars": list(self.scalars), "params": [p.describe() for p in self.params.values()],
                "actions": [{"name": a, "label": lab} for a, lab in self.actions]}

    def state(self) -> dict[str, Any]:
        """What changes with commands but not every frame: values, notices, drawing bounds."""
        return {"type": "state", "values": dict(self.values), "notices": list(self.notices),
                "bounds": list(self.bounds())}

    def bounds(self) -> tuple[float, float, float, float]:
        return (0.0, 0.0, 10.0, 10.0)

    def advance(self, wall_dt_s: float) -> None:
        """Advance by ``wall_dt_s`` seconds of wall-clock time."""

    def sections(self) -> Sections:
        return []


# -------------------------------------------------------------------------------------------------------------------
# the simulator-backed session (pages 0, 2, 5, 6, 7, 8, 9)


def _sim_params(estimators: list[str], default_estimator: str, *, scenario: str, drive: str, controls: set[str],
                speed: float) -> list[Param]:
    all_params = [
        Param("estimator", "estimator", "choice", default_estimator, choices=tuple(estimators), live=False,
              help="which registered back end estimates the map and the pose"),
        Param("scenario", "world", "choice", scenario, choices=tuple(sorted(SCENARIOS)), live=False),
        Param("landmarks", "landmarks", "int", 0, lo=0, hi=2000, step=1, live=False,
              help="0 = the world's default count (room, loop and grid worlds)"),
        Param("seed", "seed", "int", 0, lo=0, hi=2**31 - 1, step=1, live=False),
        Param("drive", "driving", "choice", drive, choices=("keys", "explore", "route")),
        Param("steps_per_s", "simulation speed (steps/s)", "float", speed, lo=1.0, hi=60.0, step=1.0),
        Param("sensor_range_m", "sensor range (m)", "float", 8.0, lo=1.0, hi=100.0, step=0.5),
        Param("obs_noise", "observation noise (x default)", "float", 1.0, lo=0.1, hi=10.0, step=0.1, live=False,
              help="multiplies the range (0.1 m) and bearing (0.02 rad) standard deviations"),
        Param("motion_noise", "odometry noise (x default variance)", "float", 1.0, lo=0.0, hi=20.0, step=0.1,
              live=False, help="multiplies every odometry noise variance; 0 = perfect odometry"),
        Param("particles", "particles", "int", 50, lo=1, hi=2000, step=1, live=False),
        Param("obs_ellipses", "observation ellipses", "bool", False),
        Param("loop_closure", "loop closure", "bool", True, live=False,
              help="the estimator's loop_closure switch (only back ends that have one)"),
        Param("wrong_association", "break it: 50% wrong landmark ids", "bool", False, live=False,
              help="half of the reported landmark ids are replaced by another landmark's id"),
        Param("few_landmarks", "break it: only 1/5 of landmarks", "bool", False, live=False,
              help="only a random fifth of the landmarks ever report observations"),
        Param("paused", "paused", "bool", False),
    ]
    return [p for p in all_params if p.name in controls]


class SimSession(Session):
    """A live :class:`Simulator` plus a registered estimator, driven by keys, auto-explore or the scenario route."""

    page = "sim"
    scalars = ("step", "time_s", "landmarks_seen", "landmarks_mapped", "landmarks_tentative", "state_dim",
               "ate_rmse_m", "pose_error_m", "n_eff", "particles", "resamples", "loops_accepted", "est_ms", "true_x",
               "true_y", "true_theta")

    def __init__(self, *, page: str, title: str, seed: int = 0, prefer: Sequence[str] = (), scenario: str = "room",
                 drive: str = "keys", controls: Sequence[str] = (), speed: float = 10.0, heat: bool = False,
                 need_note: str = "", notes: Sequence[str] = ()) -> None:
        self.page, self.title = page, title
        names = estimator_names()
        wanted = [n for n in prefer if n in names]
        default = wanted[0] if wanted else "dead-reckoning"
        ctl = set(controls) | {"seed", "paused"}
        super().__init__(_sim_params(names, default, scenario=scenario, drive=drive, controls=ctl, speed=speed),
                         seed=seed)
        self.values.setdefault("estimator", default)
        self.values.setdefault("scenario", scenario)
        self.values.setdefault("landmarks", 0)
        self.values.setdefault("drive", drive)
        self.values.setdefault("steps_per_s", speed)
        self.values.setdefault("sensor_range_m", 8.0)
        self.values.setdefault("obs_noise", 1.0)
        self.values.setdefault("motion_noise", 1.0)
        self.values.setdefault("particles", 50)
        self.values.setdefault("obs_ellipses", False)
        for k, v in (("loop_closure", True), ("wrong_association", False), ("few_landmarks", False)):
            self.values.setdefault(k, v)
        self.heat = heat
        self.actions = (("reset", "reset"), ("step", "one step"))
        if page == "loop":
            self.actions += (("close_loop", "close loop now"),)
        self.prefer = tuple(prefer)
        self.need_note = need_note
        self.static_notes = list(notes)
        self.error: str | None = None
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
        return ScenarioConfig(name=name, sensor=sensor, motion=motion, lidar=LidarConfig(enabled=False), **extra)

    def _estimator_overrides(self, name: str) -> dict[str, Any]:
        fields = {f.name for f in dataclasses.fields(get_spec(name).config_cls)}
        out: dict[str, Any] = {f: int(self.values["particles"]) for f in PARTICLE_FIELDS if f in fields}
        if self.heat and "snapshot_full_cov" in fields:  # the EKF copies its full P only when asked (O(N^2))
            out["snapshot_full_cov"] = True
        if "loop_closure" in self.params and "loop_closure" in fields:
            out["loop_closure"] = bool(self.values["loop_closure"])
        return out

    def _build(self) -> None:
        """(Re)start the simulator and estimator from the current values (same seed: same world and noise)."""
        self.sim = Simulator(self._scenario_config(), seed=int(self.values["seed"]))
        name = str(self.values["estimator"])
        self.start_error: str | None = None
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
        self.explorer = AutoExplorer(float(self.sim.config.speed_mps or 1.0), self.sim.rng["driver"])
        self.route = WaypointFollower(self.sim.waypoints, float(self.sim.config.speed_mps or 1.0))
        self.true_path: list[Array] = [self.sim.pose.copy()]
        self.est_path: list[Array] = [np.asarray(self.snap.pose, dtype=np.float64).copy()]
        self.seen: set[int] = set()
        self.last_step: Step | None = None
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
        names = estimator_names()
        notes = []
        missing = [p for p in self.prefer if p not in names]
        if self.prefer and len(missing) == len(self.prefer):
            what = " or ".join(ESTIMATOR_LABELS.get(p, repr(p)) for p in self.prefer)
            notes.append(f"not available yet: {what}. "
                         f"Showing '{self.values['estimator']}' instead{self.need_note}.")
        if self.heat and self.snap.full_cov is None:
            notes.append(f"covariance heat map: estimator '{self.values['estimator']}' does not report a full "
                         "covariance (Estimate.full_cov).")
        if self.page == "fastslam" and not self._estimator_overrides(str(self.values["estimator"])):
            notes.append(f"particle-count slider: estimator '{self.values['estimator']}' has no particle-count "
                         f"setting (looked for {list(PARTICLE_FIELDS)}).")
        est_fields = {f.name for f in dataclasses.fields(get_spec(str(self.values["estimator"])).config_cls)}
        if "loop_closure" in self.params and "loop_closure" not in est_fields:
            notes.append(f"loop-closure switch: estimator '{self.values['estimator']}' has no loop_closure setting, "
                         "so the toggle changes nothing for it.")
        notes.extend(self.static_notes)
        if self.start_error:
            notes.append(self.start_error)
        if self.error:
            notes.append(self.error)
        self.notices = notes

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    # --- commands -----------------------------------------------------------------------------------------------
    def on_param(self, name: str, value: Any, old: Any) -> None:
        p = self.params[name]
        if name == "sensor_range_m":
            # range only limits what the simulator reports; estimators do not use it, so it changes live
            self.sim.config = dataclasses.replace(
                self.sim.config, sensor=dataclasses.replace(self.sim.config.sensor, max_range_m=float(value)))
        elif not p.live and value != old:
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
        fn = self.est.close_loop_now
        obs = self.last_step.observations
        try:
            ok = bool(fn(obs.z[obs.landmark_id != -2]))
        except Exception as e:
            self.notices.append(f"close loop failed: {type(e).__name__}: {e}")
            return
        self.snap = self.est.estimate()
        self.notices.append("close loop: accepted — the correction spread along the trajectory" if ok else
                            "close loop: no verified loop from here (drive back near the start and try again)")

    # --- simulation ---------------------------------------------------------------------------------------------
    def command(self) -> tuple[float, float]:
        drive = self.values["drive"]
        segs = self.sim.world.segments_at(self.sim.time_s)
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
        self.true_path.append(self.sim.pose.copy())
        self.est_path.append(np.asarray(self.snap.pose, dtype=np.float64).copy())

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
        """ATE (after SE(2) alignment) of the estimated against the true path, via ``slam2d.eval.trajectory.ate``."""
        n = len(self.true_path)
        if self._ate_cache[0] != n:
            value = ate(self.trajectory(), np.asarray(self.true_path)).rmse_m if n >= 2 else 0.0
            self._ate_cache = (n, value)
        return self._ate_cache[1]

    def numbers(self) -> dict[str, float]:
        snap = self.snap
        sd = snap.state_dim
        parts = snap.particles.poses if snap.particles is not None else None
        n_eff = snap.particles.n_eff if snap.particles is not None else None
        tent = snap.tentative_landmarks
        pose = self.sim.pose
        return {
            "step": float(self.sim.index),
            "time_s": float(self.sim.time_s),
            "landmarks_seen": float(len(self.seen)),
            "landmarks_mapped": float(len(snap.landmarks)),
            "landmarks_tentative": float(len(tent)) if tent is not None else float("nan"),
            "resamples": float(self.resamples),
            "loops_accepted": float(snap.diagnostics.loops_accepted)
            if isinstance(self.est, SupportsLoopClosure) else float("nan"),
            "state_dim": float(sd) if sd is not None else float("nan"),
            "ate_rmse_m": self.ate_rmse(),
            "pose_error_m": float(np.hypot(*(np.asarray(snap.pose)[:2] - pose[:2]))),
            "n_eff": float(n_eff) if n_eff is not None else float("nan"),
            "particles": float(len(parts)) if parts is not None else float("nan"),
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
            ("TPTH", _downsample(np.asarray(self.true_path)[:, :2])),
            ("EPOS", np.asarray(snap.pose)),
            ("EPTH", _downsample(self.trajectory()[:, :2])),
        ]
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
        parts = snap.particles.poses if snap.particles is not None else None
        if parts is not None and len(parts):
            out.append(("PART", np.asarray(parts, dtype=np.float64).reshape(-1, np.asarray(parts).shape[-1])[:, :3]))
        if self.heat:
            h = self.heat_matrix()
            if h is not None:
                out.append(("HEAT", h))
        if self.page in ("graph", "loop") and isinstance(self.est, SupportsGraphView):
            out.extend(_graph_view_sections(self.est.graph_view()))
        return out


def _lookup(keys: NDArray[np.int64], values: Array, query: NDArray[np.int64]) -> Array:
    """Rows of ``values`` whose ``keys`` equal ``query`` (each must exist). Shapes: (N,),(N,d),(Q,) -> (Q,d)."""
    order = np.argsort(keys, kind="stable")
    pos = np.clip(np.searchsorted(keys, query, sorter=order), 0, max(len(keys) - 1, 0))
    idx = order[pos]
    if len(query) and not np.array_equal(keys[idx], query):
        raise KeyError("graph edge refers to an unknown variable")
    return values[idx]


def _graph_view_sections(view: GraphView) -> Sections:
    """Segments for a back end's ``graph_view()``: poses/points with keys, edges per factor kind as key pairs."""
    pk = view.pose_keys
    poses = view.poses[:, :2]
    qk = view.point_keys
    pts = view.points
    segs = []
    for kind, keys in view.edges.items():
        if kind not in ("between", "range_bearing", "point", "bearing", "range"):
            continue  # unary factors (priors, GPS) have no edge to draw
        k = np.asarray(keys, dtype=np.int64).reshape(-1, 2)
        if kind == "between":
            segs.append(np.hstack([_lookup(pk, poses, k[:, 0]), _lookup(pk, poses, k[:, 1])]))
        else:
            segs.append(np.hstack([_lookup(pk, poses, k[:, 0]), _lookup(qk, pts, k[:, 1])]))
    edges = np.vstack(segs) if segs else np.zeros((0, 4))
    return [("GNOD", poses), ("GEDG", edges[:: max(1, len(edges) // 3000)])]


class AssociationSession(Session):
    """A frozen moment: landmarks, a robot whose believed pose is off by a sampled error, and its observations.

    Candidates are predicted from the believed pose with ``S = H_p P H_p^T + R`` (the map is taken as known, so the
    whole ambiguity comes from pose uncertainty and sensor noise), and the chosen method assigns observations.
    """

    page = "association"
    title = "data association"
    scalars = ("observations", "matched", "correct", "wrong", "new_or_clutter", "precision", "recall", "joint_nis")

    def __init__(self, seed: int = 0) -> None:
        from slam2d.association import METHODS
        from slam2d.web.backends import associate_function

        self._associate = associate_function()
        methods = METHODS if self._associate is not None else ("known",)
        params = [
            Param("method", "method", "choice", "mahalanobis" if "mahalanobis" in methods else methods[0],
                  choices=tuple(methods)),
            Param("pose_sigma_m", "pose uncertainty (m)", "float", 0.3, lo=0.0, hi=2.0, step=0.05,
                  help="standard deviation of the believed robot position; heading sigma is this / 5 m (rad)"),
            Param("landmarks", "landmarks", "int", 40, lo=2, hi=300, step=1),
            Param("obs_noise", "observation noise (x default)", "float", 1.0, lo=0.1, hi=10.0, step=0.1),
            Param("seed", "seed", "int", 0, lo=0, hi=2**31 - 1, step=1),
        ]
        super().__init__(params, seed)
        self.actions = (("scramble", "scramble"),)
        self.rng = np.random.default_rng(int(self.values["seed"]))
        self.notices = [] if self._associate is not None else [
            "not available yet: slam2d.association.associate (nn, mahalanobis, jcbb and ransac); only the "
            "'known' oracle (slam2d.association.associate_known) can be shown."]
        self._draw_scene()

    def bounds(self) -> tuple[float, float, float, float]:
        return (0.0, 0.0, 16.0, 12.0)

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if name == "seed":
            self.rng = np.random.default_rng(int(value))
            self._draw_scene()
        elif name in ("landmarks", "pose_sigma_m", "obs_noise"):
            self._draw_scene()
        else:
            self._associate_now()

    def on_action(self, name: str) -> None:
        self._draw_scene()

    def _draw_scene(self) -> None:
        from slam2d.models.sensors import sense_landmarks

        rng = self.rng
        n = int(self.values["landmarks"])
        self.landmarks = rng.uniform([0.5, 0.5], [15.5, 11.5], size=(n, 2))
        self.true_pose = np.array([8.0, 6.0, rng.uniform(-np.pi, np.pi)])
        s = float(self.values["pose_sigma_m"])
        self.pose_cov = np.diag([s * s, s * s, (s / 5.0) ** 2]) + 1e-12 * np.eye(3)
        self.belief = self.true_pose + rng.multivariate_normal(np.zeros(3), self.pose_cov)
        k = float(self.values["obs_noise"])
        base = SensorConfig()
        self.sensor = dataclasses.replace(base, max_range_m=6.0, range_std_m=base.range_std_m * k,
                                          bearing_std_rad=base.bearing_std_rad * k)
        z, ids, _ = sense_landmarks(self.true_pose, self.landmarks, np.arange(n), self.sensor, rng)
        from slam2d.log import Observations

        self.obs = Observations(z[:, 0], z[:, 1], ids.astype(np.int64))
        self._associate_now()

    def candidates(self) -> Any:
        from slam2d.association import Candidates, joint_innovation_covariance
        from slam2d.models.sensors import range_bearing, range_bearing_jacobians

        # every landmark within reach of the belief (range plus a margin for the pose error) is a candidate
        zp = range_bearing(self.belief, self.landmarks)
        near = np.flatnonzero(zp[:, 0] <= self.sensor.max_range_m + 3.0)
        hp, hl = range_bearing_jacobians(np.broadcast_to(self.belief, (len(near), 3)), self.landmarks[near])
        # the map is known exactly (rows=None): only the pose is uncertain
        s, s_joint = joint_innovation_covariance(hp, hl, self.pose_cov, None, self.sensor.covariance)
        return Candidates(near.astype(np.int64), zp[near], s, s_joint)

    def _associate_now(self) -> None:
        from slam2d.association import AssociationConfig, associate_known

        cands = self.candidates()
        method = str(self.values["method"])
        self.notices = [n for n in self.notices if not n.startswith("association method")]
        try:
            if method == "known":
                res = associate_known(self.obs, cands)
            else:
                assert self._associate is not None
                res = self._associate(self.obs, cands, AssociationConfig(method=method),  # type: ignore[arg-type]
                                      rng=self.rng)
        except Exception as e:  # show the failure on the page instead of losing the session
            self.notices.append(f"association method {method!r} failed: {type(e).__name__}: {e}")
            from slam2d.association import CLUTTER, AssociationResult

            res = AssociationResult(np.full(len(self.obs), CLUTTER, dtype=np.int64), np.full(len(self.obs), np.nan))
        self.result = res
        self.cands = cands

    def numbers(self) -> dict[str, float]:
        a = np.asarray(self.result.assignment)
        truth = self.obs.landmark_id
        matched = a >= 0
        correct = matched & (a == truth)
        reachable = np.isin(truth, self.cands.ids)
        n_match = int(matched.sum())
        return {"observations": float(len(a)), "matched": float(n_match), "correct": float(correct.sum()),
                "wrong": float(n_match - int(correct.sum())), "new_or_clutter": float((~matched).sum()),
                "precision": float(correct.sum() / n_match) if n_match else float("nan"),
                "recall": float(correct.sum() / reachable.sum()) if reachable.any() else float("nan"),
                "joint_nis": float(self.result.joint_nis)}

    def sections(self) -> Sections:
        nums = self.numbers()
        a = np.asarray(self.result.assignment)
        obs_xy = range_bearing_inverse(np.broadcast_to(self.belief, (len(self.obs), 3)), self.obs.z) \
            if len(self.obs) else np.zeros((0, 2))
        m = a >= 0
        lines = np.hstack([obs_xy[m], self.landmarks[a[m]], (a[m] == self.obs.landmark_id[m])[:, None]]) \
            if m.any() else np.zeros((0, 5))
        return [
            ("NUMS", np.array([nums[k] for k in self.scalars])),
            ("TLMK", self.landmarks),
            ("TPOS", self.true_pose),
            ("EPOS", self.belief),
            ("PCOV", self.pose_cov[:2, :2].reshape(1, 4)),
            ("OBSV", obs_xy),
            ("MTCH", lines),
            ("NEWO", obs_xy[~m]),
        ]


# -------------------------------------------------------------------------------------------------------------------
# map representations (page 1) and pages whose back end is still missing


class MapsSession(Session):
    """The room driven along its route with known poses: the landmark map and the lidar points seen so far.

    Occupancy grid and topological map layers appear once ``slam2d.maps`` provides them.
    """

    page = "maps"
    title = "map representations"
    scalars = ("step", "landmarks", "scan_points", "walls", "places", "connections")

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("layer", "representation", "choice", "landmarks",
                  choices=("landmarks", "points", "occupancy", "topology")),
            Param("seed", "seed", "int", 0, lo=0, hi=2**31 - 1, step=1),
            Param("paused", "paused", "bool", False),
        ]
        super().__init__(params, seed)
        self.actions = (("reset", "reset"),)
        self._build()

    def _build(self) -> None:
        cfg = ScenarioConfig(name="room", lidar=LidarConfig(beams=91, every=2))
        self.sim = Simulator(cfg, seed=int(self.values["seed"]))
        self.route = WaypointFollower(self.sim.waypoints, float(self.sim.config.speed_mps or 1.0))
        self.points = np.zeros((0, 2))
        self._acc = 0.0
        self.grid: Any = None
        self.grid_error: str | None = None
        self.topo_mod = optional_module("slam2d.maps.topology")
        self.topo_error: str | None = None
        self.topo: Any = None
        self._topo_at = -1.0
        occ = optional_module("slam2d.maps.occupancy")
        if occ is not None:
            try:
                self.grid = occ.OccupancyGrid(self.sim.world.bounds, occ.OccupancyConfig(resolution_m=0.2))
            except Exception as e:  # an interface that changed: say so on the page
                self.grid_error = f"occupancy grid could not be built: {type(e).__name__}: {e}"
        self._update_notices()

    def _update_notices(self) -> None:
        layer = self.values["layer"]
        self.notices = []
        if layer == "occupancy" and self.grid is None:
            self.notices.append(self.grid_error or "not available yet: occupancy grid (slam2d.maps.occupancy)")
        if layer == "topology" and (self.topo_mod is None or self.grid is None):
            self.notices.append(self.topo_error or "not available yet: topological map (slam2d.maps.topology, "
                                                   "built from the occupancy grid)")

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if name == "seed":
            self._build()
        self._update_notices()

    def on_action(self, name: str) -> None:
        self._build()

    def advance(self, wall_dt_s: float) -> None:
        if self.values["paused"]:
            return
        self._acc += wall_dt_s * 10.0
        n = min(int(self._acc), 8)
        self._acc = 0.0 if n == 8 else self._acc - n
        for _ in range(n):
            v, w = self.route.command(self.sim.pose, self.sim.world.walls)
            step = self.sim.step(v, w)
            if step.scan is not None:
                local = scan_to_points(step.scan.ranges_m, step.scan.angles_rad, step.scan.max_range_m)
                pts = se2.transform_points(self.sim.pose, local)
                # keep one point per 5 cm cell so the map stays small however long it runs
                merged = np.vstack([self.points, pts])
                _, keep = np.unique(np.round(merged / 0.05).astype(np.int64), axis=0, return_index=True)
                self.points = merged[np.sort(keep)]
                if self.grid is not None:
                    try:
                        self.grid.update(self.sim.pose, step.scan.ranges_m, step.scan.angles_rad,
                                         step.scan.max_range_m)
                    except Exception as e:
                        self.grid, self.grid_error = None, f"occupancy grid update failed: {type(e).__name__}: {e}"
                        self._update_notices()

    def sections(self) -> Sections:
        topo = self.topo if self.values["layer"] == "topology" else None
        nums = {"step": float(self.sim.index), "landmarks": float(len(self.sim.world.landmarks)),
                "scan_points": float(len(self.points)), "walls": float(len(self.sim.world.walls)),
                "places": float(len(topo.places)) if topo is not None else float("nan"),
                "connections": float(len(topo.edges)) if topo is not None else float("nan")}
        out: Sections = [("NUMS", np.array([nums[k] for k in self.scalars])), ("WALL", self.sim.world.walls),
                         ("TPOS", self.sim.pose)]
        if self.values["layer"] == "landmarks":
            out.append(("TLMK", self.sim.world.landmarks))
        elif self.values["layer"] == "points":
            out.append(("SCAN", self.points))
        elif self.values["layer"] == "occupancy" and self.grid is not None:
            out.append(("GRID", self.grid.probability()))
            out.append(("GRDM", np.array([*self.grid.origin, self.grid.resolution])))
        elif self.values["layer"] == "topology":
            topo = self.topology()
            if topo is not None:
                places = np.asarray(topo.places, dtype=np.float64).reshape(-1, 2)
                edges = np.asarray(topo.edges, dtype=np.int64).reshape(-1, 2)
                out += [("GNOD", places), ("GEDG", np.hstack([places[edges[:, 0]], places[edges[:, 1]]]))]
        return out

    def topology(self) -> Any:
        """The topological map of the grid so far (recomputed at most once per simulated second: skeletons cost)."""
        if self.topo_mod is None or self.grid is None:
            return None
        if self.sim.time_s - self._topo_at >= 1.0 or self.topo is None:
            try:
                self.topo = self.topo_mod.topology_from_grid(self.grid)
                self._topo_at = self.sim.time_s
            except Exception as e:
                self.topo_mod, self.topo_error = None, f"topological map failed: {type(e).__name__}: {e}"
                self._update_notices()
                return None
        return self.topo


class NoticeSession(Session):
    """A page whose back end has not landed: it shows the world and says exactly what is missing."""

    scalars = ()

    def __init__(self, *, page: str, title: str, missing: str, seed: int = 0) -> None:
        super().__init__([], seed)
        self.page, self.title = page, title
        self.sim = Simulator(ScenarioConfig(name="room", lidar=LidarConfig(enabled=False)), seed=seed)
        self.notices = [f"not available yet: {missing}"]

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def sections(self) -> Sections:
        return [("NUMS", np.zeros(0)), ("WALL", self.sim.world.walls), ("TLMK", self.sim.world.landmarks),
                ("TPOS", self.sim.pose)]


class FeaturesSession(Session):
    """Harris corners on an image of the room (its walls rasterised into a grid), against the true wall corners.

    Uses ``slam2d.frontend.features`` (detector, pixel/world conversion, precision/recall) and
    ``slam2d.maps.occupancy`` (rasterising the walls); until both exist the page says so.
    """

    page = "features"
    title = "feature extraction"
    scalars = ("corners_found", "true_corners", "precision", "recall")

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("threshold_rel", "threshold (x strongest response)", "float", 0.1, lo=0.0, hi=1.0, step=0.01),
            Param("sigma_px", "window sigma (pixels)", "float", 1.0, lo=0.5, hi=4.0, step=0.1),
            Param("image_noise", "image noise (std)", "float", 0.0, lo=0.0, hi=0.5, step=0.01),
            Param("seed", "seed", "int", 0, lo=0, hi=2**31 - 1, step=1),
        ]
        super().__init__(params, seed)
        self.actions = (("renoise", "new noise"),)
        self.sim = Simulator(ScenarioConfig(name="room", lidar=LidarConfig(enabled=False)), seed=seed)
        self.feat = optional_module("slam2d.frontend.features")
        self.occ = optional_module("slam2d.maps.occupancy")
        walls = self.sim.world.walls
        # a corner is a wall endpoint; each appears twice (two walls meet there)
        self.truth = np.unique(np.round(np.vstack([walls[:, :2], walls[:, 2:]]), 6), axis=0)
        self.detected = np.zeros((0, 2))
        self.score: Any = None
        self.rng = np.random.default_rng(int(self.values["seed"]))
        self.base: Array | None = None
        if self.feat is None or self.occ is None:
            missing = [m for m, mod in (("slam2d.frontend.features", self.feat), ("slam2d.maps.occupancy", self.occ))
                       if mod is None]
            self.notices = [f"not available yet: corner detection on a room image (needs {' and '.join(missing)})"]
            return
        try:
            self.grid = self.occ.OccupancyGrid(self.sim.world.bounds, self.occ.OccupancyConfig(resolution_m=0.1))
            self.base = self.occ.rasterize_segments(self.grid, walls).astype(np.float64)
        except Exception as e:
            self.notices = [f"room image could not be built: {type(e).__name__}: {e}"]
            return
        self._renoise()

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def _renoise(self) -> None:
        if self.base is None:
            return
        self.image = np.clip(self.base + self.rng.standard_normal(self.base.shape) * float(self.values["image_noise"]),
                             0.0, 1.0)
        self._detect()

    def _detect(self) -> None:
        assert self.feat is not None
        self.notices = [n for n in self.notices if not n.startswith("corner detection failed")]
        try:
            cfg = self.feat.HarrisConfig(threshold_rel=float(self.values["threshold_rel"]),
                                         sigma_px=float(self.values["sigma_px"]))
            rc = self.feat.harris_corners(self.image, cfg)
            self.detected = self.feat.pixels_to_world(self.grid, rc)
            self.score = self.feat.match_points(self.detected, self.truth, tolerance=0.3)
        except Exception as e:
            self.notices.append(f"corner detection failed: {type(e).__name__}: {e}")
            self.detected, self.score = np.zeros((0, 2)), None

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if self.base is None:
            return
        if name == "seed":
            self.rng = np.random.default_rng(int(value))
        if name in ("seed", "image_noise"):
            self._renoise()
        else:
            self._detect()

    def on_action(self, name: str) -> None:
        self._renoise()

    def sections(self) -> Sections:
        sc = self.score
        nums = [float(len(self.detected)), float(len(self.truth)),
                float(sc.precision) if sc is not None else float("nan"),
                float(sc.recall) if sc is not None else float("nan")]
        out: Sections = [("NUMS", np.array(nums)), ("WALL", self.sim.world.walls)]
        if self.base is not None:
            out += [("GRID", self.image), ("GRDM", np.array([*self.grid.origin, self.grid.resolution])),
                    ("TCOR", self.truth), ("FEAT", self.detected)]
        return out


def block_average(mat: Array, limit: int = HEAT_MAX) -> Array:
    """Average ``mat`` (n,n) over an at most ``limit`` x ``limit`` grid of blocks (identity when n <= limit)."""
    m = np.asarray(mat, dtype=np.float64)
    n = m.shape[0]
    if n <= limit:
        return m
    edges = np.linspace(0, n, limit + 1).astype(np.int64)
    cs = np.zeros((n + 1, n + 1))
    cs[1:, 1:] = m.cumsum(0).cumsum(1)
    s = cs[edges[1:]][:, edges[1:]] - cs[edges[:-1]][:, edges[1:]] - cs[edges[1:]][:, edges[:-1]] + \
        cs[edges[:-1]][:, edges[:-1]]
    sizes = np.diff(edges)
    return s / (sizes[:, None] * sizes[None, :])


class GraphSession(Session):
    """Batch graph SLAM on the drive so far: build the factor graph, then watch Gauss-Newton iterate.

    The robot drives the room's route (odometry and known-id range-bearing observations are recorded); "optimize"
    builds a :class:`slam2d.graph.FactorGraph` (odometry ``between`` factors, ``range_bearing`` factors), starts from
    the dead-reckoned poses and first-sighting landmarks, and runs one Gauss-Newton iteration per animation tick.
    """

    page = "graph"
    title = "graph SLAM"
    scalars = ("poses", "landmarks", "factors", "iteration", "cost", "ate_initial_m", "ate_now_m",
               "omega_nonzero_blocks", "omega_blocks")

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("steps", "drive length (steps)", "int", 150, lo=10, hi=600, step=10, live=False),
            Param("motion_noise", "odometry noise (x default variance)", "float", 4.0, lo=0.1, hi=20.0, step=0.1,
                  live=False),
            Param("seed", "seed", "int", 0, lo=0, hi=2**31 - 1, step=1, live=False),
        ]
        super().__init__(params, seed)
        self.actions = (("optimize", "optimize"), ("reset", "reset"))
        self.graph_mod = optional_module("slam2d.graph")
        self._build()

    def _build(self) -> None:
        cfg = ScenarioConfig(name="room", motion=MotionNoise().scaled(float(self.values["motion_noise"])),
                             lidar=LidarConfig(enabled=False))
        self.sim = Simulator(cfg, seed=int(self.values["seed"]))
        self.route = WaypointFollower(self.sim.waypoints, float(self.sim.config.speed_mps or 1.0))
        self.dr = make_estimator("dead-reckoning", log_metadata=self.sim.metadata())
        self.dr.reset(self.sim.initial_pose, rng=self.sim.rng["estimator"])
        self.dr_path: list[Array] = [self.sim.initial_pose.copy()]
        self.values_now: Any = None
        self.optimizer: Any = None
        self.iteration = 0
        self.cost = float("nan")
        self.converged = False
        self.factors = 0
        self.edges = np.zeros((0, 4))
        self.omega: Array | None = None
        self.omega_nnz = (0, 0)
        self._acc = 0.0
        self.notices = [] if self.graph_mod is not None else ["not available yet: graph SLAM back end (slam2d.graph)"]

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if value != old:
            self._build()

    def on_action(self, name: str) -> None:
        if name == "reset":
            self._build()
        elif name == "optimize" and self.graph_mod is not None and self.values_now is None:
            try:
                self._make_graph()
            except Exception as e:
                self.notices = [f"graph could not be built: {type(e).__name__}: {e}"]

    def _make_graph(self) -> None:
        g: Any = self.graph_mod
        log = self.sim.to_log()
        t = log.num_steps
        noise = self.sim.config.motion
        graph = g.FactorGraph()
        # odometry: z = pose t+1 in the frame of pose t, information in the factor's error frame
        graph.add_between(np.arange(t), np.arange(1, t + 1), *odometry_factor(log.odometry, noise))
        keep = log.obs_id >= 0
        steps, ids = log.obs_step[keep], log.obs_id[keep]
        z = np.column_stack([log.obs_range_m[keep], log.obs_bearing_rad[keep]])
        graph.add_range_bearing(steps, ids, z, np.linalg.inv(self.sim.config.sensor.covariance))
        poses = np.asarray(self.dr_path)
        lm_ids, first = np.unique(ids, return_index=True)
        init_lm = range_bearing_inverse(poses[steps[first]], z[first])
        self.values_now = g.Values(np.arange(t + 1), poses, lm_ids, init_lm)
        self.optimizer = g.Optimizer(graph, g.OptimizerConfig(method="gn", max_iterations=1))
        self.factors = t + len(ids)
        self.lm_ids, self.obs_pairs, self.n_poses = lm_ids, (steps, ids), t + 1
        # structure of the information matrix: one block per variable pair joined by a factor (and the diagonal)
        v = t + 1 + len(lm_ids)
        lm_index = t + 1 + np.searchsorted(lm_ids, ids)
        blocks = np.eye(v, dtype=bool)
        blocks[np.arange(t), np.arange(1, t + 1)] = blocks[np.arange(1, t + 1), np.arange(t)] = True
        blocks[steps, lm_index] = blocks[lm_index, steps] = True
        self.omega = block_average(blocks.astype(np.float64))
        self.omega_nnz = (int(blocks.sum()), v * v)
        assert log.true_poses is not None
        self.initial_ate = ate(poses, log.true_poses).rmse_m

    def advance(self, wall_dt_s: float) -> None:
        if self.values_now is None:
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
        # one Gauss-Newton iteration every 0.4 s, so the correction can be watched spreading
        self._acc += wall_dt_s
        if self._acc < 0.4:
            return
        self._acc = 0.0
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
        if self.iteration >= 20 or (prev == prev and prev - self.cost <= 1e-6 * max(prev, 1e-12)):
            self.converged = True

    def current_poses(self) -> Array:
        if self.values_now is None:
            return np.asarray(self.dr_path)
        order = np.argsort(self.values_now.pose_keys)
        return np.asarray(self.values_now.poses)[order]

    def sections(self) -> Sections:
        poses = self.current_poses()
        truth = np.asarray(self.sim.to_log().true_poses) if self.values_now is not None else None
        ate_now = ate(poses, truth).rmse_m if truth is not None else float("nan")
        n_lm = len(self.values_now.point_keys) if self.values_now is not None else 0
        nums = {"poses": float(len(poses)), "landmarks": float(n_lm), "factors": float(self.factors),
                "iteration": float(self.iteration), "cost": self.cost,
                "ate_initial_m": self.initial_ate if self.values_now is not None else float("nan"),
                "ate_now_m": ate_now, "omega_nonzero_blocks": float(self.omega_nnz[0]),
                "omega_blocks": float(self.omega_nnz[1])}
        out: Sections = [("NUMS", np.array([nums[k] for k in self.scalars])), ("WALL", self.sim.world.walls),
                         ("TLMK", self.sim.world.landmarks), ("TPOS", self.sim.pose),
                         ("EPTH", _downsample(poses[:, :2])), ("EPOS", poses[-1])]
        if self.values_now is not None:
            pts = np.asarray(self.values_now.points)
            lm_by_id = pts[np.searchsorted(self.values_now.point_keys, self.lm_ids)] if len(pts) else pts
            steps, ids = self.obs_pairs
            seg_obs = np.hstack([poses[steps, :2], lm_by_id[np.searchsorted(self.lm_ids, ids)]])
            out += [("ELMK", pts), ("GNOD", poses[:, :2]), ("GEDG", seg_obs[:: max(1, len(seg_obs) // 1500)])]
            if self.omega is not None:
                out.append(("HEAT", self.omega))
        return out
