"""The warehouse design challenge, live: a drone flies the small warehouse from a saved map (relocalise, then track)
or from a cold start, with the lifelong lidar session (``--estimator lidar-lifelong``: static and dynamic layers),
and the page draws what the session exposes.

The saved map is built once per (seed, process) by :func:`slam2d.maps.store.snapshot_from_truth` from flight 1
(``warehouse.flight=0``) flown with true poses, its static layer by the layers' own persistence rule, so the page
starts in seconds; the benchmark (``benchmarks/warehouse_flights.py``) uses the estimator's own cold-start map instead
(minutes). The live flight is ``warehouse.flight`` = the chosen flight - 1 (pallets relocated since the map), started
at a seed-drawn step along the route, so the relocaliser does not know where it is.

Scan points are drawn by the label the estimator gave them (static, pending, dynamic); the forklift outlines are the
simulator's truth, drawn so that the labels can be checked by eye, and the share of the points on a forklift that the
estimator labelled dynamic is counted against the same truth.
"""

from __future__ import annotations

import threading
import time
from functools import lru_cache
from typing import Any

import numpy as np

from slam2d.config import with_overrides
from slam2d.frontend.relocalise import RelocaliseConfig
from slam2d.geometry import se2
from slam2d.graph.lidar_config import LifelongLidarConfig
from slam2d.graph.lidar_session import LidarSession, LidarSessionConfig
from slam2d.maps.layers import DYNAMIC, STATIC, LayersConfig
from slam2d.maps.occupancy import OccupancyGrid
from slam2d.maps.store import MapSnapshot, sim_world_id, snapshot_from_truth
from slam2d.models.lidar import scan_to_points
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator, simulate, spawn_streams
from slam2d.sim.world import segment_distances
from slam2d.web.params import Param
from slam2d.web.sessions.base import Array, Sections, Session, downsample, seed_param

#: the small warehouse of ``benchmarks/warehouse_flights.py`` (its SMALL world): 40 x 30 m, 3 aisles, 10 Hz
SMALL = {"warehouse.width_m": "40", "warehouse.depth_m": "30", "warehouse.aisles": "3",
         "warehouse.cross_aisles": "1", "warehouse.pallets": "40", "dt_s": "0.1", "steps": "3000"}
DEFAULT_FORKLIFTS = 2
#: the live flight starts this many route steps in, at most (drawn from the seed); skipping costs ~3 ms a step
MAX_START_STEP = 1000
GRID_EVERY_S = 3.0  # the live static layer is redrawn at most every this many simulated seconds (it re-rasterises)
SURVEY_SIGMA_M = 0.01  # the floor markers' survey error per axis (m), as in benchmarks/warehouse_shift.py
ON_FORKLIFT_M = 0.15  # a scan point this close to a forklift's true outline is a point on a forklift
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
    "forklifts": "forklifts (simulator)",
    "static_cells": "static layer: occupied cells",
    "dynamic_points": "scan points labelled dynamic (last scan)",
    "forklift_points": "scan points on a forklift (truth, last scan)",
    "forklift_dynamic_pct": "of those, labelled dynamic (%)",
    "dynamic_cells": "dynamic layer: cells above 0.5",
    "promoted": "cells promoted into the static layer",
    "demoted": "cells demoted out of it",
    "marker_fixes": "floor-marker fixes",
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


#: saved_map's builds of the same seed wait for each other (two tabs opening a new seed at once built it twice,
#: 13-20 s each); a fixed set of locks, so that the seeds asked for cannot grow it
_BUILD_LOCKS = tuple(threading.Lock() for _ in range(8))


def saved_map(seed: int) -> MapSnapshot:
    """Flight 1's map from its true poses (with floor markers and the static layer), built once per seed and
    process (the two newest seeds are kept)."""
    with _BUILD_LOCKS[seed % len(_BUILD_LOCKS)]:
        return _build_saved_map(seed)


@lru_cache(maxsize=2)
def _build_saved_map(seed: int) -> MapSnapshot:
    # a scan every 4th step (0.48 m of travel): keyframes are kept every 1 m anyway, and it builds 4x faster
    return snapshot_from_truth(simulate(with_overrides(scenario(0, DEFAULT_FORKLIFTS, True), {"lidar.every": "4"}),
                                        seed), layers=LayersConfig())


def coarse(prob: Array, factor: int) -> Array:
    """Block maximum of a probability image over ``factor`` x ``factor`` cells (thin walls stay visible; the frame
    stays small). Shapes: (R,C) -> (ceil(R/f), ceil(C/f))."""
    r, c = prob.shape
    pad = np.full((-(-r // factor) * factor, -(-c // factor) * factor), 0.5)
    pad[:r, :c] = prob
    return np.asarray(pad.reshape(pad.shape[0] // factor, factor, pad.shape[1] // factor, factor).max(axis=(1, 3)))


class WarehouseSession(Session):
    """One drone in the small warehouse: the lifelong lidar session (relocalise against the saved map, or cold
    start)."""

    page = "warehouse"
    title = "the warehouse design challenge"
    scalars = tuple(WAREHOUSE_LABELS)
    labels = WAREHOUSE_LABELS

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("start", "start", "choice", "saved map", choices=("saved map", "cold start"), live=False,
                  help="saved map: unknown start, relocalise first; cold start: a new map from the true start pose"),
            Param("floor_markers", "floor markers (downward camera)", "bool", True, live=False,
                  help="markers on the floor, their positions surveyed to 1 cm: they pick the aisle when "
                       "relocalising and correct the tracked pose when the camera reads one"),
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
        survey = self.sim.world.marker_survey(SURVEY_SIGMA_M, np.random.default_rng([seed, 17])) if markers else ()
        self.est = LidarSession(LidarSessionConfig(lidar=LifelongLidarConfig(surveyed_markers=survey),
                                                   relocalise=reloc), prior=prior,
                                world_id=sim_world_id(self.sim.metadata()))
        self.est.reset(self.sim.pose.copy(), rng=spawn_streams(seed)["estimator"])
        self._acc = 0.0
        self._step_s: list[float] = []
        self._scan_local: Array = np.zeros((0, 2))
        self._true_path: list[Array] = [self.sim.pose[:2].copy()]
        self._grid: OccupancyGrid | None = None
        self._grid_at = -np.inf
        self._grid_changes = -1
        self._scan_time = self.sim.time_s
        self._image: tuple[object, Array, Array, float] | None = None

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def rows(self) -> list[str]:
        reloc = ("hypotheses", "evidence", "margin", "accepted_step", "decide_s", "map_keyframes")
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
            self._scan_time = self.sim.time_s
        self._true_path.append(self.sim.pose[:2].copy())

    def static_layer(self) -> OccupancyGrid | MapSnapshot | None:
        """The static layer to draw: the saved map's while relocalising, then the session's own live layer
        (re-rasterised at most every ``GRID_EVERY_S`` simulated seconds, and only when cells joined or left it)."""
        if not self.est.relocalised:
            return self.prior
        lay = self.est.lidar.map_layers()
        if not lay.integrations:  # a cold start before its first scan: no layer yet
            return None
        changes = lay.promoted + lay.demoted
        if changes != self._grid_changes and self.sim.time_s - self._grid_at >= GRID_EVERY_S:
            self._grid = lay.static_grid()
            self._grid_at, self._grid_changes = self.sim.time_s, changes
        return self._grid

    def labelled_scan(self) -> tuple[Array, Array, Array]:
        """The last scan's points in the map frame split by the estimator's labels: (static, pending, dynamic). While
        relocalising, every point is pending (nothing is labelled yet) and drawn from the best hypothesis."""
        pose = self.est.estimate().pose
        if not self.est.relocalised or not self.est.lidar.map_layers().integrations:
            return np.zeros((0, 2)), se2.transform_points(pose, self._scan_local), np.zeros((0, 2))
        pts, labels = self.est.lidar.last_labels()
        world = se2.transform_points(pose, pts)
        return world[labels == STATIC], world[(labels != STATIC) & (labels != DYNAMIC)], world[labels == DYNAMIC]

    def forklift_labels(self) -> tuple[int, float]:
        """Points of the last scan that lie on a forklift (the simulator's outlines at the scan's time, points placed
        at the TRUE pose so that an estimation error does not move them), and the percentage of those the estimator
        labelled dynamic (NaN when none lie on a forklift or nothing is labelled yet)."""
        fork = [m.segments(self._scan_time) for m in self.sim.world.moving]
        if not fork or not self.est.relocalised or not self.est.lidar.map_layers().integrations:
            return 0, float("nan")
        pts, labels = self.est.lidar.last_labels()
        on = segment_distances(se2.transform_points(self.sim.pose, pts), np.vstack(fork)).min(axis=1) < ON_FORKLIFT_M
        n = int(on.sum())
        return n, 100.0 * float(np.mean(labels[on] == DYNAMIC)) if n else float("nan")

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
        live = self.est.relocalised
        stats = lid.layer_stats() if live else None
        static_pts, pending_pts, dynamic_pts = self.labelled_scan() if has_pose else (np.zeros((0, 2)),) * 3
        on_fork, fork_pct = self.forklift_labels()
        dyn_cells = lid.map_layers().dynamic_points(self.sim.time_s) if live else np.zeros((0, 2))
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
            "keyframes": float(stats.keyframes) if stats is not None else 0.0,
            "forklifts": float(len(self.sim.world.moving)),
            "static_cells": float(cells),
            "dynamic_points": float(len(dynamic_pts)) if live else nan,
            "forklift_points": float(on_fork) if live else nan,
            "forklift_dynamic_pct": fork_pct,
            "dynamic_cells": float(len(dyn_cells)) if live else nan,
            "promoted": float(stats.promoted) if stats is not None else nan,
            "demoted": float(stats.demoted) if stats is not None else nan,
            "marker_fixes": float(stats.marker_fixes) if stats is not None else nan,
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
            out += [(name, pts) for name, pts in (("SCAN", static_pts), ("SPND", pending_pts),
                                                  ("SDYN", dynamic_pts), ("DYNL", dyn_cells)) if len(pts)]
        if deciding and rel is not None and len(rel.hyp):
            out.append(("HYPO", rel.hyp))
        if rel is not None and rel.history:
            hist = np.array([[h["time_s"], h["hypotheses"]] for h in rel.history], dtype=np.float64)
            out.append(("HHIS", downsample(hist - [self.start_time, 0.0])))
        if est.trajectory is not None and len(est.trajectory):
            out.append(("EPTH", downsample(est.trajectory[:, :2])))
        return out
