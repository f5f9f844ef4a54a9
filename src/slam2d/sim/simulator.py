"""The simulator: true motion, noisy odometry, landmark/lidar/GPS sensing, step by step, deterministic per seed.

Randomness comes from named streams spawned from one seed (``STREAMS``): the world layout, the motion noise, the
landmark sensor, clutter, lidar, GPS and the driver each have their own generator, so switching one sensor on or off
never changes another's noise. New streams are only ever appended to ``STREAMS``.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.config import to_dict, with_overrides
from slam2d.geometry import se2
from slam2d.log import DYNAMIC_ID, Log, MarkerReadings, Observations, Scan, Step
from slam2d.models.floor_markers import sense_floor_markers
from slam2d.models.motion import sample_odometry, velocity_increment
from slam2d.models.sensors import range_bearing, sense_clutter, sense_landmarks, visible
from slam2d.sim.raycast import simulate_scan_culled
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.trajectory import AutoExplorer, WaypointFollower
from slam2d.sim.world import World

Array = NDArray[np.float64]

STREAMS = ("world", "motion", "sensor", "clutter", "lidar", "gps", "driver", "descriptors", "dynamic", "estimator",
           "markers")


def spawn_streams(seed: int) -> dict[str, np.random.Generator]:
    """One independent generator per name in ``STREAMS``, all derived from ``seed``."""
    children = np.random.SeedSequence(seed).spawn(len(STREAMS))
    return {name: np.random.default_rng(c) for name, c in zip(STREAMS, children, strict=True)}


def _version() -> str:
    try:
        return importlib.metadata.version("slam2d")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0+unknown"


class Simulator:
    """A live simulation: call :meth:`step` with a (v, w) command; :meth:`to_log` returns everything so far.

    The web lab drives this directly from key presses; :func:`simulate` drives it with the scenario's driver.
    """

    def __init__(self, config: ScenarioConfig | None = None, seed: int = 0, world: World | None = None,
                 record: bool = True) -> None:
        self.config = (config or ScenarioConfig()).resolved()
        self.seed = int(seed)
        self.rng = spawn_streams(self.seed)
        layout = SCENARIOS[self.config.name].build(self.config, self.rng["world"])
        base_world = world or layout.world
        if self.config.sensor.descriptor_dim > 0 and base_world.descriptors is None:
            desc = self.rng["descriptors"].random((len(base_world.landmarks), self.config.sensor.descriptor_dim))
            base_world = dataclasses.replace(base_world, descriptors=desc)
        self.world = base_world
        self.waypoints = layout.waypoints
        self.initial_pose = layout.initial_pose.astype(np.float64)
        self.pose = self.initial_pose.copy()
        self.record = record
        """keep every step for :meth:`to_log`; False streams (memory stays flat over a long shift)."""
        self.time_s = 0.0
        self.index = 0
        self._has_scan = self.config.lidar.enabled and len(self.world.walls) > 0
        self._rec: dict[str, list[Any]] = {k: [] for k in ("odom", "stamps", "poses", "obs_step", "z", "ids", "desc",
                                                            "gps_step", "gps", "scan_step", "scan", "dyn",
                                                            "marker_step", "marker_xy", "marker_id")}
        self._rec["stamps"].append(0.0)
        self._rec["poses"].append(self.pose.copy())
        self._rec["dyn"].append(self.world.moving_positions(0.0))

    def driver(self) -> WaypointFollower | AutoExplorer:
        """The scenario's driver for this config (waypoints or auto-explore)."""
        if self.config.driver == "explore":
            return AutoExplorer(float(self.config.speed_mps or 1.0), self.rng["driver"])
        return WaypointFollower(self.waypoints, float(self.config.speed_mps or 1.0))

    def step(self, v: float, w: float) -> Step:
        """Drive (v, w) for one time step and sense; returns what an estimator may see (no truth)."""
        cfg = self.config
        dt = float(cfg.dt_s or 0.1)
        u_true = velocity_increment(np.array([v, w]), dt)
        self.pose = se2.compose(self.pose, u_true)
        self.time_s += dt
        self.index += 1
        odom = sample_odometry(u_true, cfg.motion, self.rng["motion"])

        z, ids, desc = sense_landmarks(self.pose, self.world.landmarks, self.world.landmark_ids, cfg.sensor,
                                       self.rng["sensor"], self.world.descriptors)
        zc, dc = sense_clutter(cfg.sensor, self.rng["clutter"])
        parts_z, parts_id, parts_d = [z, zc], [ids, np.full(len(zc), -1, dtype=np.int64)], [desc, dc]
        dyn = self.world.moving_positions(self.time_s)
        if len(dyn):
            zd_true = range_bearing(self.pose, dyn)
            keep = visible(zd_true, cfg.sensor)
            noise = self.rng["dynamic"].standard_normal(zd_true.shape) * [cfg.sensor.range_std_m,
                                                                            cfg.sensor.bearing_std_rad]
            parts_z.append((zd_true + noise)[keep])
            parts_id.append(np.full(int(keep.sum()), DYNAMIC_ID, dtype=np.int64))
            parts_d.append(self.rng["dynamic"].random((int(keep.sum()), cfg.sensor.descriptor_dim))
                           if cfg.sensor.descriptor_dim else None)
        z_all = np.vstack(parts_z)
        id_all = np.concatenate(parts_id)
        d_all = np.vstack([d for d in parts_d if d is not None]) if cfg.sensor.descriptor_dim else None
        obs = Observations(z_all[:, 0], z_all[:, 1], id_all, d_all)

        gps = None
        if cfg.gps_every and self.index % cfg.gps_every == 0:
            gps = self.pose[:2] + self.rng["gps"].standard_normal(2) * cfg.gps_std_m
        scan = None
        if self._has_scan and self.index % cfg.lidar.every == 0:
            near = self.world.segments_near(self.time_s, self.pose[:2], cfg.lidar.max_range_m)
            ranges = simulate_scan_culled(self.pose, near, cfg.lidar, self.rng["lidar"])
            scan = Scan(ranges, cfg.lidar.angles(), cfg.lidar.max_range_m)
        markers = None
        if len(self.world.floor_markers) and self.index % cfg.camera.read_every == 0:
            xy, mid = sense_floor_markers(self.pose, self.world.floor_markers, cfg.camera, self.rng["markers"])
            markers = MarkerReadings(xy, mid)

        step = Step(self.index, self.time_s, dt, odom, obs, gps, scan, markers)
        if not self.record:
            return step
        r = self._rec
        r["odom"].append(odom)
        r["stamps"].append(self.time_s)
        r["poses"].append(self.pose.copy())
        r["obs_step"].append(np.full(len(obs), self.index, dtype=np.int64))
        r["z"].append(z_all)
        r["ids"].append(id_all)
        if d_all is not None:
            r["desc"].append(d_all)
        if gps is not None:
            r["gps_step"].append(self.index)
            r["gps"].append(gps)
        if scan is not None:
            r["scan_step"].append(self.index)
            r["scan"].append(scan.ranges_m)
        r["dyn"].append(dyn)
        if markers is not None:
            r["marker_step"].append(np.full(len(markers), self.index, dtype=np.int64))
            r["marker_xy"].append(markers.xy_m)
            r["marker_id"].append(markers.ids)
        return step

    def metadata(self) -> dict[str, Any]:
        """Seed, full resolved config, sensor/motion parameters and versions (recorded in every Log)."""
        cfg = to_dict(self.config)
        return {
            "source": "simulator",
            "scenario": self.config.name,
            "seed": self.seed,
            "config": cfg,
            "motion": cfg["motion"],
            "sensor": cfg["sensor"],
            "units": {"length": "m", "angle": "rad", "time": "s"},
            "slam2d_version": _version(),
            "numpy_version": np.__version__,
        }

    def to_log(self) -> Log:
        """Everything simulated so far as a :class:`Log` (with ground truth)."""
        if not self.record:
            raise ValueError("this Simulator was made with record=False: it streams steps and keeps no Log")
        r = self._rec
        t = len(r["odom"])
        z = np.vstack(r["z"]) if r["z"] else np.zeros((0, 2))
        has_scan = bool(r["scan"])
        has_dyn = len(self.world.moving) > 0
        has_markers = len(self.world.floor_markers) > 0
        return Log(
            stamps_s=np.asarray(r["stamps"], dtype=np.float64),
            odometry=np.asarray(r["odom"], dtype=np.float64).reshape(t, 3),
            obs_step=np.concatenate(r["obs_step"]) if r["obs_step"] else np.zeros(0, dtype=np.int64),
            obs_range_m=z[:, 0].copy(),
            obs_bearing_rad=z[:, 1].copy(),
            obs_id=np.concatenate(r["ids"]) if r["ids"] else np.zeros(0, dtype=np.int64),
            initial_pose=self.initial_pose.copy(),
            obs_descriptor=np.vstack(r["desc"]) if r["desc"] else None,
            true_poses=np.asarray(r["poses"], dtype=np.float64),
            true_landmarks=self.world.landmarks.copy(),
            true_landmark_ids=self.world.landmark_ids.astype(np.int64),
            walls=self.world.walls.copy(),
            gps_step=np.asarray(r["gps_step"], dtype=np.int64) if r["gps"] else None,
            gps_xy=np.asarray(r["gps"], dtype=np.float64) if r["gps"] else None,
            scan_step=np.asarray(r["scan_step"], dtype=np.int64) if has_scan else None,
            scan_ranges_m=np.asarray(r["scan"], dtype=np.float64) if has_scan else None,
            scan_angles_rad=self.config.lidar.angles() if has_scan else None,
            scan_max_range_m=self.config.lidar.max_range_m if has_scan else 0.0,
            dynamic_xy=np.asarray(r["dyn"], dtype=np.float64) if has_dyn else None,
            marker_step=np.concatenate([np.zeros(0, np.int64), *r["marker_step"]]) if has_markers else None,
            marker_xy_m=np.vstack([np.zeros((0, 2)), *r["marker_xy"]]) if has_markers else None,
            marker_id=np.concatenate([np.zeros(0, np.int64), *r["marker_id"]]) if has_markers else None,
            true_markers=self.world.floor_markers.copy() if has_markers else None,
            metadata=self.metadata(),
        )


def simulate(scenario: str | ScenarioConfig = "room", seed: int = 0, **overrides: Any) -> Log:
    """Simulate a whole scenario with its driver and return the :class:`Log`.

    ``overrides`` are config fields by dotted path or unambiguous leaf name, e.g. ``landmarks=1000, steps=200`` or
    ``range_std_m=0.2``; they are validated like the config itself.
    """
    cfg = ScenarioConfig(name=scenario) if isinstance(scenario, str) else scenario
    if overrides:
        cfg = with_overrides(cfg, overrides)
    sim = Simulator(cfg, seed)
    driver = sim.driver()
    for _ in range(int(sim.config.steps or 0)):
        v, w = driver.command(sim.pose, sim.world.segments_at(sim.time_s))
        sim.step(v, w)
    return sim.to_log()
