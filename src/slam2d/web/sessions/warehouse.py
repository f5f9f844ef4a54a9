"""The warehouse design challenge, live: a drone flies the small warehouse from a saved map (relocalise, then track)
or from a cold start, and the page draws what the lidar session exposes.

The saved map is built once per (seed, process) by :func:`slam2d.maps.store.snapshot_from_truth` from flight 1
(``warehouse.flight=0``) flown with true poses, so the page starts in seconds; the benchmark
(``benchmarks/warehouse_flights.py``) uses the estimator's own cold-start map instead (minutes). The live flight is
``warehouse.flight`` = the chosen flight - 1 (pallets relocated since the map), started at a seed-drawn step along
the route, so the relocaliser does not know where it is.

What the library does not expose yet is not drawn as if it did: the lidar estimator on main does not label scan
points as dynamic, so every scan point has one colour and the forklifts are drawn as the simulator's truth outlines.
"""

from __future__ import annotations

import time
from functools import lru_cache
from typing import Any

import numpy as np

from slam2d.config import with_overrides
from slam2d.frontend.relocalise import RelocaliseConfig
from slam2d.geometry import se2
from slam2d.graph.lidar_session import LidarSession, LidarSessionConfig
from slam2d.maps.occupancy import OccupancyGrid
from slam2d.maps.store import MapSnapshot, sim_world_id, snapshot_from_truth
from slam2d.models.lidar import scan_to_points
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator, simulate, spawn_streams
from slam2d.web.params import Param
from slam2d.web.sessions.base import Array, Sections, Session, downsample, seed_param

#: the small warehouse of ``benchmarks/warehouse_flights.py`` (its SMALL world): 40 x 30 m, 3 aisles, 10 Hz
SMALL = {"warehouse.width_m": "40", "warehouse.depth_m": "30", "warehouse.aisles": "3",
         "warehouse.cross_aisles": "1", "warehouse.pallets": "40", "dt_s": "0.1", "steps": "3000"}
DEFAULT_FORKLIFTS = 2
#: the live flight starts this many route steps in, at most (drawn from the seed); skipping costs ~3 ms a step
MAX_START_STEP = 1000
GRID_EVERY_S = 3.0  # a cold start's map is redrawn at most every this many simulated seconds (it re-rasterises)
MAX_STEPS_PER_FRAME = 3
DRAW_CELL_M = 0.2  # the static layer is sent at this cell size at most (block maximum)

WAREHOUSE_LABELS = {
    "step": "step",
    "time_s": "flight time (s)",
    "hypotheses": "relocalisation hypotheses",
    "evidence": "evidence scans in the window",
    "margin": "winner's margin over the best rival (nats)",
    "accepted_step": "relocalised at step",
    "decide_s": "time to relocalise (s of motion)",
    "error_m": "position error vs truth (m)",
    "error_deg": "heading error vs truth (deg)",
    "map_keyframes": "keyframes in the saved map",
    "keyframes": "keyframes in the estimator",
    "map_loops": "loops into the saved map",
    "forklifts": "forklifts (simulator)",
    "static_cells": "static layer: occupied cells",
    "step_ms": "estimator time per step, last 50 (ms)",
    "step_ms_max": "slowest of the last 50 steps (ms)",
}


def scenario(flight: int, forklifts: int, markers: bool) -> ScenarioConfig:
    return with_overrides(ScenarioConfig(name="warehouse-challenge"),
                          {**SMALL, "moving_objects": str(forklifts), "warehouse.flight": str(flight),
                           "warehouse.floor_markers": "true" if markers else "false"})


@lru_cache(maxsize=1)
def max_forklifts() -> int:
    """The most forklifts the small layout holds, as the scenario's own validation decides (not a copy of its rule)."""
    best = 0
    for n in range(0, 201):
        try:
            scenario(0, n, False)
        except ValueError:
            break
        best = n
    return best


@lru_cache(maxsize=2)
def saved_map(seed: int) -> MapSnapshot:
    """Flight 1's map from its true poses (with floor markers), built once per seed and process."""
    # a scan every 4th step (0.48 m of travel): keyframes are kept every 1 m anyway, and it builds 4x faster
    return snapshot_from_truth(simulate(with_overrides(scenario(0, DEFAULT_FORKLIFTS, True), {"lidar.every": "4"}),
                                        seed))


def coarse(prob: Array, factor: int) -> Array:
    """Block maximum of a probability image over ``factor`` x ``factor`` cells (thin walls stay visible; the frame
    stays small). Shapes: (R,C) -> (ceil(R/f), ceil(C/f))."""
    r, c = prob.shape
    pad = np.full((-(-r // factor) * factor, -(-c // factor) * factor), 0.5)
    pad[:r, :c] = prob
    return np.asarray(pad.reshape(pad.shape[0] // factor, factor, pad.shape[1] // factor, factor).max(axis=(1, 3)))


class WarehouseSession(Session):
    """One drone in the small warehouse: the lidar session (relocalise against the saved map, or cold start)."""

    page = "warehouse"
    title = "the warehouse design challenge"
    scalars = tuple(WAREHOUSE_LABELS)
    labels = WAREHOUSE_LABELS

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("start", "start", "choice", "saved map", choices=("saved map", "cold start"), live=False,
                  help="saved map: unknown start, relocalise first; cold start: a new map from the true start pose"),
            Param("floor_markers", "floor markers (downward camera)", "bool", True, live=False),
            Param("forklifts", "forklifts", "int", DEFAULT_FORKLIFTS, lo=0, hi=max_forklifts(), step=1, live=False),
            Param("flight", "flight (pallets moved since the map)", "int", 2, lo=2, hi=4, step=1, live=False),
            Param("steps_per_s", "simulated steps per second", "float", 10.0, lo=1.0, hi=30.0, step=1.0),
            seed_param(),
            Param("paused", "paused", "bool", False),
        ]
        super().__init__(params, seed)
        self.actions = (("restart", "new start"),)
        self._restarts = 0
        self._build()

    # --- building ----------------------------------------------------------------------------------------------
    def _build(self) -> None:
        v = self.values
        seed = int(v["seed"])
        markers, cold = bool(v["floor_markers"]), v["start"] == "cold start"
        cfg = scenario(int(v["flight"]) - 1, int(v["forklifts"]), markers)
        self.sim = Simulator(cfg, seed=seed, record=False)
        self.driver = self.sim.driver()
        start = int(np.random.default_rng([seed, self._restarts]).integers(0, MAX_START_STEP))
        for _ in range(start):  # fly to the start without the estimator: it wakes up there
            self.sim.step(*self.driver.command(self.sim.pose, self.sim.world.walls))
        self.start_step, self.start_time = self.sim.index, self.sim.time_s
        prior = None if cold else saved_map(seed)
        self.prior = prior
        reloc = RelocaliseConfig(use_markers=markers)
        self.est = LidarSession(LidarSessionConfig(relocalise=reloc), prior=prior,
                                world_id=sim_world_id(self.sim.metadata()))
        self.est.reset(self.sim.pose.copy(), rng=spawn_streams(seed)["estimator"])
        self._acc = 0.0
        self._step_s: list[float] = []
        self._scan_local: Array = np.zeros((0, 2))
        self._true_path: list[Array] = [self.sim.pose[:2].copy()]
        self._grid: OccupancyGrid | None = None
        self._grid_at = -np.inf
        self._grid_keyframes = -1
        self._image: tuple[object, Array, Array, float] | None = None

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def rows(self) -> list[str]:
        reloc = ("hypotheses", "evidence", "margin", "accepted_step", "decide_s", "map_keyframes", "map_loops")
        return [k for k in self.scalars if self.prior is not None or k not in reloc]

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if not self.params[name].live:
            self._build()

    def on_action(self, name: str) -> None:
        self._restarts += 1
        self._build()

    # --- running -----------------------------------------------------------------------------------------------
    def advance(self, wall_dt_s: float) -> None:
        if self.values["paused"]:
            return
        self._acc += wall_dt_s * float(self.values["steps_per_s"])
        n = min(int(self._acc), MAX_STEPS_PER_FRAME)
        self._acc = 0.0 if n == MAX_STEPS_PER_FRAME else self._acc - n
        for _ in range(n):
            self.step_once()

    def step_once(self) -> None:
        step = self.sim.step(*self.driver.command(self.sim.pose, self.sim.world.walls))
        t0 = time.perf_counter()
        self.est.step(step)
        self._step_s.append(time.perf_counter() - t0)
        del self._step_s[:-50]
        if step.scan is not None:
            self._scan_local = scan_to_points(step.scan.ranges_m, step.scan.angles_rad, step.scan.max_range_m)
        self._true_path.append(self.sim.pose[:2].copy())

    def static_layer(self) -> OccupancyGrid | MapSnapshot | None:
        """The static layer to draw: the saved map's, or in a cold start the estimator's grid (re-rasterised at most
        every ``GRID_EVERY_S`` simulated seconds, and only when keyframes were added)."""
        if self.prior is not None:
            return self.prior
        lid = self.est.lidar
        k = len(lid.keyframe_poses)
        if k and k != self._grid_keyframes and self.sim.time_s - self._grid_at >= GRID_EVERY_S:
            self._grid = lid.occupancy_grid()
            self._grid_at, self._grid_keyframes = self.sim.time_s, k
        return self._grid

    # --- drawing -----------------------------------------------------------------------------------------------
    def layer_image(self) -> tuple[Array | None, Array | None, float]:
        """The static layer as a (coarsened) probability image, its placement, and its occupied cell count at full
        resolution; recomputed only when the layer changed."""
        layer = self.static_layer()
        if layer is None:
            return None, None, float("nan")
        if self._image is None or self._image[0] is not layer:
            if isinstance(layer, MapSnapshot):
                prob = 1.0 / (1.0 + np.exp(-layer.occupancy_logodds.astype(np.float64)))
                origin, res = layer.occupancy_origin, float(layer.occupancy_resolution_m)
            else:
                prob, origin, res = layer.probability(), layer.origin, float(layer.resolution)
            f = max(1, round(DRAW_CELL_M / res))
            cells = float((prob > RelocaliseConfig().occupied_probability).sum())
            self._image = (layer, coarse(prob, f), np.array([origin[0], origin[1], res * f]), cells)
        return self._image[1], self._image[2], self._image[3]

    def sections(self) -> Sections:
        est = self.est.estimate()
        rel = self.est.relocaliser
        deciding = rel is not None and not self.est.relocalised
        pose = est.pose
        has_pose = not (deciding and rel is not None and not len(rel.hyp))
        err = se2.local(self.sim.pose, pose) if has_pose else np.full(3, np.nan)
        accepted = self.est.accepted_step
        prob, meta, cells = self.layer_image()
        lid = self.est.lidar
        nan = float("nan")
        nums = {
            "step": float(self.sim.index - self.start_step), "time_s": self.sim.time_s - self.start_time,
            "hypotheses": float(len(rel.hyp)) if deciding and rel is not None else nan,
            "evidence": float(rel.status.evidence) if rel is not None else nan,
            "margin": float(rel.status.margin) if rel is not None else nan,
            "accepted_step": float(accepted - self.start_step) if accepted is not None else nan,
            "decide_s": float(self.est.accepted_time_s - self.start_time)
            if self.est.accepted_time_s is not None else nan,
            "error_m": float(np.hypot(err[0], err[1])), "error_deg": float(np.degrees(abs(err[2]))),
            "map_keyframes": float(len(self.prior.keyframe_poses)) if self.prior is not None else nan,
            "keyframes": float(len(lid.keyframe_poses)) if self.est.relocalised else 0.0,
            "map_loops": float(self.est.map_loops) if self.prior is not None else nan,
            "forklifts": float(len(self.sim.world.moving)),
            "static_cells": float(cells),
            "step_ms": 1e3 * float(np.mean(self._step_s)) if self._step_s else nan,
            "step_ms_max": 1e3 * float(np.max(self._step_s)) if self._step_s else nan,
        }
        out: Sections = [("NUMS", np.array([nums[k] for k in self.scalars])), ("WALL", self.sim.world.walls),
                         ("TPOS", self.sim.pose), ("TPTH", downsample(np.asarray(self._true_path)))]
        if prob is not None and meta is not None:
            out += [("GRID", prob), ("GRDM", meta)]
        fork = [m.segments(self.sim.time_s) for m in self.sim.world.moving]  # a handful of boxes: drawing only
        if fork:
            out.append(("FORK", np.vstack(fork)))
        if has_pose:
            out.append(("EPOS", pose))
            if len(self._scan_local):
                out.append(("SCAN", se2.transform_points(pose, self._scan_local)))
        if deciding and rel is not None and len(rel.hyp):
            out.append(("HYPO", rel.hyp))
        if rel is not None and rel.history:
            hist = np.array([[h["time_s"], h["hypotheses"]] for h in rel.history], dtype=np.float64)
            out.append(("HHIS", downsample(hist - [self.start_time, 0.0])))
        if est.trajectory is not None and len(est.trajectory):
            out.append(("EPTH", downsample(est.trajectory[:, :2])))
        return out
