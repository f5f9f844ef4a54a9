"""Pages 1 and 3: map representations of one room, and corner features on an image of it."""

from __future__ import annotations

from typing import Any

import numpy as np

from slam2d.frontend.features import HarrisConfig, PointMatchScore, harris_corners, match_points, pixels_to_world
from slam2d.geometry import se2
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid, rasterize_segments
from slam2d.maps.topology import TopologicalMap, topology_from_grid
from slam2d.models.lidar import LidarConfig, scan_to_points
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator
from slam2d.sim.trajectory import WaypointFollower
from slam2d.web.params import Param
from slam2d.web.sessions.base import Array, Sections, Session, seed_param

MAPS_LABELS = {
    "step": "step",
    "landmarks": "landmarks",
    "scan_points": "lidar points kept (5 cm cells)",
    "walls": "wall segments",
    "places": "places (topology nodes)",
    "connections": "connections",
}

FEATURES_LABELS = {
    "corners_found": "corners found",
    "true_corners": "true corners",
    "precision": "precision (found that are real)",
    "recall": "recall (real that are found)",
}


class MapsSession(Session):
    """The room driven along its route with known poses: the same world as landmarks, lidar points, an occupancy
    grid and a topological map."""

    page = "maps"
    title = "map representations"
    scalars = ("step", "landmarks", "scan_points", "walls", "places", "connections")
    labels = MAPS_LABELS

    def __init__(self, seed: int = 0, *, page: str = "maps", title: str = "map representations",
                 layer: str = "landmarks") -> None:
        self.page, self.title = page, title
        params = [
            Param("layer", "representation", "choice", layer,
                  choices=("landmarks", "points", "occupancy", "topology")),
            seed_param(),
            Param("paused", "paused", "bool", False),
        ]
        super().__init__(params, seed)
        self.actions = (("reset", "reset"),)
        self._layers_seen = {layer}
        self._build()

    def _build(self) -> None:
        cfg = ScenarioConfig(name="room", lidar=LidarConfig(beams=91, every=2))
        self.sim = Simulator(cfg, seed=int(self.values["seed"]))
        self.route = WaypointFollower(self.sim.waypoints, float(self.sim.config.speed_mps or 1.0))
        self.points = np.zeros((0, 2))
        self._acc = 0.0
        self.grid = OccupancyGrid(self.sim.world.bounds, OccupancyConfig(resolution_m=0.2))
        self.topo: TopologicalMap | None = None
        self._topo_at = -1.0

    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.sim.world.bounds)  # type: ignore[return-value]

    def rows(self) -> list[str]:
        extra = ["places", "connections"] if self.values["layer"] == "topology" else []
        return ["step", "landmarks", "scan_points", "walls", *extra]

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if name == "seed":
            self._build()
        if name == "layer":
            self._layers_seen.add(str(value))
            self._watch_task()

    def _watch_task(self) -> None:
        """maps: every representation shown; connections: the scans shown as an occupancy grid."""
        layers = self.params["layer"].choices
        if self.page == "maps" and self._layers_seen >= set(layers):
            rows, cols = self.grid.shape
            self.complete_task(f"Done: one drive, {len(layers)} maps. The landmark list holds "
                               f"{len(self.sim.world.landmarks)} points, the scan map {len(self.points)} points, the "
                               f"grid {rows} x {cols} cells; the topology keeps only places and their connections.")
        elif self.page == "connections" and "occupancy" in self._layers_seen:
            occ, free = int(self.grid.occupied().sum()), int(self.grid.free().sum())
            self.complete_task(f"Done: {occ} cells occupied and {free} free so far, built from the same scans as the "
                               "points: each beam clears the cells it passed and marks the one it hit.")

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
                self.grid.update(self.sim.pose, step.scan.ranges_m, step.scan.angles_rad, step.scan.max_range_m)

    def topology(self) -> TopologicalMap:
        """The topological map of the grid so far (recomputed at most once per simulated second: skeletons cost)."""
        if self.topo is None or self.sim.time_s - self._topo_at >= 1.0:
            self.topo = topology_from_grid(self.grid)
            self._topo_at = self.sim.time_s
        return self.topo

    def sections(self) -> Sections:
        layer = self.values["layer"]
        topo = self.topology() if layer == "topology" else None
        nums = {"step": float(self.sim.index), "landmarks": float(len(self.sim.world.landmarks)),
                "scan_points": float(len(self.points)), "walls": float(len(self.sim.world.walls)),
                "places": float(len(topo.places)) if topo is not None else float("nan"),
                "connections": float(len(topo.edges)) if topo is not None else float("nan")}
        out: Sections = [("NUMS", np.array([nums[k] for k in self.scalars])), ("WALL", self.sim.world.walls),
                         ("TPOS", self.sim.pose)]
        if layer == "landmarks":
            out.append(("TLMK", self.sim.world.landmarks))
        elif layer == "points":
            out.append(("SCAN", self.points))
        elif layer == "occupancy":
            out.append(("GRID", self.grid.probability()))
            out.append(("GRDM", np.array([*self.grid.origin, self.grid.resolution])))
        elif topo is not None:
            places = np.asarray(topo.places, dtype=np.float64).reshape(-1, 2)
            edges = np.asarray(topo.edges, dtype=np.int64).reshape(-1, 2)
            out += [("GNOD", places), ("GEDG", np.hstack([places[edges[:, 0]], places[edges[:, 1]]]))]
        return out


class FeaturesSession(Session):
    """Harris corners (:func:`slam2d.frontend.features.harris_corners`) on an image of the room (its walls
    rasterised into a grid), scored against the true wall corners."""

    page = "features"
    title = "feature extraction"
    scalars = ("corners_found", "true_corners", "precision", "recall")
    labels = FEATURES_LABELS

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("threshold_rel", "threshold (× strongest response)", "float", 0.1, lo=0.0, hi=1.0, step=0.01),
            Param("sigma_px", "window sigma (pixels)", "float", 1.0, lo=0.5, hi=4.0, step=0.1),
            # some noise by default: on a clean image every corner is equally strong and the threshold hardly matters
            Param("image_noise", "image noise (std)", "float", 0.2, lo=0.0, hi=0.5, step=0.01),
            seed_param(),
        ]
        super().__init__(params, seed)
        self.actions = (("renoise", "new noise"),)
        self._low: tuple[float, int, float, float] | None = None
        self.sim = Simulator(ScenarioConfig(name="room", lidar=LidarConfig(enabled=False)), seed=seed)
        walls = self.sim.world.walls
        # a corner is a wall endpoint; each appears twice (two walls meet there)
        self.truth = np.unique(np.round(np.vstack([walls[:, :2], walls[:, 2:]]), 6), axis=0)
        self.rng = np.random.default_rng(int(self.values["seed"]))
        # a 1 m margin: walls on the world's edge must lie inside the image, with room for the detector's window
        x0, y0, x1, y1 = self.sim.world.bounds
        self.grid = OccupancyGrid((x0 - 1.0, y0 - 1.0, x1 + 1.0, y1 + 1.0), OccupancyConfig(resolution_m=0.1))
        self.base: Array = rasterize_segments(self.grid, walls).astype(np.float64)
        self._renoise()

    def bounds(self) -> tuple[float, float, float, float]:
        x0, y0, x1, y1 = (float(b) for b in self.sim.world.bounds)
        return (x0 - 1.0, y0 - 1.0, x1 + 1.0, y1 + 1.0)

    def _renoise(self) -> None:
        noise = self.rng.standard_normal(self.base.shape) * float(self.values["image_noise"])
        self.image = np.clip(self.base + noise, 0.0, 1.0)
        self._detect()

    def _detect(self) -> None:
        cfg = HarrisConfig(threshold_rel=float(self.values["threshold_rel"]), sigma_px=float(self.values["sigma_px"]))
        self.detected: Array = pixels_to_world(self.grid, harris_corners(self.image, cfg))
        self.score: PointMatchScore = match_points(self.detected, self.truth, tolerance=0.3)

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if name == "seed":
            self.rng = np.random.default_rng(int(value))
        if name in ("seed", "image_noise"):
            self._renoise()
        else:
            self._detect()
        if name == "threshold_rel":
            self._watch_task(float(value))

    def _watch_task(self, threshold: float) -> None:
        """The threshold slid from low (<= 0.05) to high (>= 0.3): quote what it did to precision and recall."""
        sc = self.score
        if threshold <= 0.05:
            self._low = (threshold, len(self.detected), sc.precision, sc.recall)
        elif threshold >= 0.3 and self._low is not None:
            t0, n0, p0, r0 = self._low
            self.complete_task(f"Done: threshold {t0:g} -> {threshold:g}: corners found {n0} -> {len(self.detected)}, "
                               f"precision {p0:.2f} -> {sc.precision:.2f}, recall {r0:.2f} -> {sc.recall:.2f}. A "
                               "higher threshold keeps only strong responses: fewer false corners, and past some "
                               "point real ones are lost too.")

    def on_action(self, name: str) -> None:
        self._renoise()

    def sections(self) -> Sections:
        sc = self.score
        nums = [float(len(self.detected)), float(len(self.truth)), float(sc.precision), float(sc.recall)]
        return [("NUMS", np.array(nums)), ("WALL", self.sim.world.walls), ("GRID", self.image),
                ("GRDM", np.array([*self.grid.origin, self.grid.resolution])), ("TCOR", self.truth),
                ("FEAT", self.detected)]
