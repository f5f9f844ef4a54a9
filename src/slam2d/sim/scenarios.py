"""Scenario catalogue: each builds a :class:`World`, a driver's waypoints and a start pose from a config and an rng.

* ``room``: a 20 x 14 m room with a pillar and ~30 landmarks; the robot drives two laps (the default scenario).
* ``loop``: a 4 m wide corridor around a 60 x 40 m block: a 200 m loop that returns to its start.
* ``warehouse``: identical shelf rows whose posts form repeating landmark patterns, with forklifts driving the aisles
  (40 x 30 m, up to 3 forklifts: small and fast, used by the tests and the lab).
* ``warehouse-challenge``: the lesson's design challenge at full scale (``slam2d.sim.warehouse``): 100 x 100 m, 14
  identical aisles of back-to-back racks, 600 pallets that move between flights, 20 forklifts on the aisles and
  cross-aisles, a 30 Hz / 30 m / 360-beam lidar and optional floor markers; every size is a config field.
* ``grid``: landmarks on a regular grid (any count) and a circular drive, for scaling studies.
* ``scramble``: tight clusters of landmarks along a loop, neighbours 0.2-0.6 m apart (a few sensor standard
  deviations, often inside one another's 99 % gate), so that a small pose error confuses nearest neighbour; the
  data-association test bed.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from slam2d.config import check_nonnegative, check_positive
from slam2d.models.floor_markers import FloorCameraConfig
from slam2d.models.lidar import LidarConfig
from slam2d.models.motion import MotionNoise
from slam2d.models.sensors import SensorConfig
from slam2d.sim.warehouse import WarehouseConfig, build_warehouse
from slam2d.sim.world import MovingObject, World, box_walls

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class ScenarioConfig:
    """Everything that defines a simulated run except the seed. ``None`` means "the scenario's default"."""

    name: str = "room"
    """scenario name; see ``slam2d.sim.SCENARIOS``."""
    steps: int | None = None
    """number of steps to simulate."""
    dt_s: float | None = None
    """time between steps (s)."""
    speed_mps: float | None = None
    """cruise speed of the robot (m/s)."""
    landmarks: int | None = None
    """number of landmarks (room, loop, grid)."""
    moving_objects: int | None = None
    """number of forklifts (warehouse)."""
    driver: Literal["waypoints", "explore"] = "waypoints"
    """how the robot is steered: the scenario's route, or wandering with wall avoidance."""
    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """range-bearing landmark sensor."""
    lidar: LidarConfig = field(default_factory=LidarConfig)
    """lidar (scans are skipped in worlds without walls). A scenario may preset some fields (warehouse-challenge:
    360 beams all round, 30 m); a field left at the library default takes the scenario's preset value."""
    camera: FloorCameraConfig = field(default_factory=FloorCameraConfig)
    """downward camera reading floor markers (only in worlds that have them)."""
    warehouse: WarehouseConfig = field(default_factory=WarehouseConfig)
    """layout of the warehouse-challenge scenario (size, aisles, pallets, flight, floor markers)."""
    gps_every: int = 0
    """take a GPS fix every this many steps (0: no GPS)."""
    gps_std_m: float = 0.5
    """GPS noise standard deviation per axis (m)."""

    def __post_init__(self) -> None:
        if self.name not in SCENARIOS:
            raise ValueError(f"unknown scenario {self.name!r}; valid scenarios: {sorted(SCENARIOS)}")
        for n in ("steps", "landmarks", "moving_objects"):
            v = getattr(self, n)
            if v is not None and v < (0 if n == "moving_objects" else 1):
                raise ValueError(f"ScenarioConfig.{n} must be >= {0 if n == 'moving_objects' else 1} (got {v})")
        for n in ("dt_s", "speed_mps"):
            if getattr(self, n) is not None:
                check_positive(self, n)
        check_positive(self, "gps_std_m")
        check_nonnegative(self, "gps_every")
        spec = SCENARIOS[self.name]
        for n in ("landmarks", "moving_objects"):
            if getattr(self, n) is not None and (why := self.refuse_override(n)):
                raise ValueError(why)
        wh = self.warehouse
        if spec.floor_markers:  # only the marker fields apply to this layout
            wh = dataclasses.replace(wh, floor_markers=False, marker_spacing_m=WarehouseConfig().marker_spacing_m)
        if wh != WarehouseConfig() and (why := self.refuse_override("warehouse")):
            raise ValueError(why)
        if spec.check is not None:
            spec.check(self)
        check_memory(self)

    def refuse_override(self, path: str) -> str | None:
        """Why the field ``path`` (dotted) cannot be set for this scenario, or None. Asked by
        :func:`slam2d.config.with_overrides` before the nested configs check their values, so a warehouse value given
        to the room is refused as such, not for a layout it does not make."""
        spec = SCENARIOS[self.name]
        top, _, leaf = path.partition(".")
        if top in ("landmarks", "moving_objects") and top not in spec.defaults:
            return f"ScenarioConfig.{top} cannot be set for scenario {self.name!r}"
        if top == "warehouse" and not spec.uses_warehouse \
                and not (spec.floor_markers and leaf in ("floor_markers", "marker_spacing_m")):
            return (f"ScenarioConfig.warehouse cannot be set for scenario {self.name!r} (only for "
                    f"{sorted(k for k, s in SCENARIOS.items() if s.uses_warehouse)})")
        return None

    def resolved(self) -> ScenarioConfig:
        """This config with every ``None`` replaced by the scenario's default."""
        spec = SCENARIOS[self.name]
        updates: dict[str, Any] = {k: v for k, v in spec.defaults.items() if getattr(self, k) is None}
        if spec.lidar:
            base = LidarConfig()
            preset = {k: v for k, v in spec.lidar.items() if getattr(self.lidar, k) == getattr(base, k)}
            updates["lidar"] = dataclasses.replace(self.lidar, **preset)
        return dataclasses.replace(self, **updates)


#: environment variable that raises (or lowers) the memory a simulated run may ask for, in MB
MEMORY_ENV = "SLAM2D_MAX_MEMORY_MB"
DEFAULT_MAX_MEMORY_MB = 4096.0
#: observations of real landmarks one step can hold at most, for the estimate (the sensor's range limits them)
_VISIBLE_PER_STEP = 500
#: bytes per beam of one simulated scan: the culled caster's (beam, segment) pairs and their arithmetic (measured
#: 330-560 B in the room and the warehouses)
_BYTES_PER_BEAM = 640.0
#: bytes per landmark of building the room (rejection sampling of 4n points against the route; measured ~850 B)
_ROOM_BYTES_PER_LANDMARK = 1024.0
#: bytes per wall segment of building the challenge warehouse (outlines, stacking, tile index; measured ~220 B)
_BYTES_PER_WALL = 256.0


def _layout_bytes(cfg: ScenarioConfig) -> tuple[float, float, float]:
    """(landmarks, bytes to build the layout, bytes of one step's floor-marker temporaries and of the readings the
    whole log holds) of the layout ``cfg`` asks for: arithmetic on the config, no allocation."""
    spec = SCENARIOS[cfg.name]
    lms = float(cfg.landmarks if cfg.landmarks is not None else spec.defaults.get("landmarks", 1000))
    steps = float(cfg.steps if cfg.steps is not None else spec.defaults.get("steps", 1000))
    wh = cfg.warehouse
    build, markers, lines = (_ROOM_BYTES_PER_LANDMARK * lms if cfg.name == "room" else 0.0), 0.0, 0.0
    if spec.uses_warehouse:  # uprights are the landmarks; walls: panels, 4 per upright and per pallet
        blocks = (wh.aisles + 1.0) * (wh.cross_aisles + 1.0)
        lms = blocks * 2.0 * (wh.bays_per_face_per_block + 1.0)
        build = _BYTES_PER_WALL * (4.0 * lms + 4.0 * wh.pallets + blocks + 4.0) + 64.0 * lms
        if wh.floor_markers:
            rows, cols = wh.aisles + 2.0, wh.cross_aisles + 2.0
            markers = rows * ((wh.width_m - wh.road_m) // wh.marker_spacing_m + 1.0 + cols)
            build += 40.0 * markers * markers  # the pairwise distances that drop near-duplicates
            lines = 2.0
    elif spec.floor_markers and wh.floor_markers:  # the small warehouse: 5 aisle lines, 32 m each
        markers = 5.0 * (32.0 // wh.marker_spacing_m + 1.0)
        build, lines = 16.0 * markers, 1.0
    # a reading per marker within the camera's footprint on the lines under it, every read_every steps
    seen = min(markers, lines * (2.0 * cfg.camera.footprint_radius_m / wh.marker_spacing_m + 1.0))
    return lms, build, 64.0 * markers + 24.0 * seen * steps / cfg.camera.read_every


def estimate_memory_bytes(cfg: ScenarioConfig) -> tuple[float, float]:
    """Rough upper bounds (bytes) of the simulated log and of one step's temporaries: steps, landmarks, clutter,
    descriptors, lidar beams and moving objects. Pure arithmetic on the config (no allocation)."""
    spec = SCENARIOS[cfg.name]
    steps = float(cfg.steps if cfg.steps is not None else spec.defaults.get("steps", 1000))
    lms, build, markers = _layout_bytes(cfg)
    movers = float(cfg.moving_objects if cfg.moving_objects is not None else spec.defaults.get("moving_objects", 0))
    per_obs = 8.0 * (4 + cfg.sensor.descriptor_dim)
    obs_per_step = min(lms, _VISIBLE_PER_STEP) * cfg.sensor.detection_prob + cfg.sensor.clutter_rate + movers
    scans = (steps / cfg.lidar.every) * cfg.lidar.beams * 8.0 if cfg.lidar.enabled else 0.0
    landmark_bytes = lms * (64.0 + 8.0 * cfg.sensor.descriptor_dim)
    total = steps * (obs_per_step * per_obs + 200.0 + 16.0 * movers) + scans + landmark_bytes
    # one step: every landmark's range and bearing, the clutter draws and their descriptors, a scan
    step = 8.0 * (lms * (8 + cfg.sensor.descriptor_dim) + obs_per_step * (4 + cfg.sensor.descriptor_dim)) \
        + _BYTES_PER_BEAM * cfg.lidar.beams
    # building the layout comes before the first step; its temporaries count like a step's
    return total + markers, max(step + markers, build)


def memory_limit_mb() -> float:
    """``$SLAM2D_MAX_MEMORY_MB`` or the default (4096 MB)."""
    raw = os.environ.get(MEMORY_ENV, "")
    try:
        return float(raw) if raw else DEFAULT_MAX_MEMORY_MB
    except ValueError:
        raise ValueError(f"{MEMORY_ENV} must be a number of MB (got {raw!r})") from None


def check_memory(cfg: ScenarioConfig) -> None:
    """ValueError (before anything is allocated) when the run would need more than ``$SLAM2D_MAX_MEMORY_MB``
    (default 4096 MB) by :func:`estimate_memory_bytes`; the message names the fields that dominate."""
    limit_mb = memory_limit_mb()
    total, step = estimate_memory_bytes(cfg)
    need_mb = max(total, step) / 2**20
    if not need_mb <= limit_mb:  # also catches inf / nan
        raise ValueError(
            f"ScenarioConfig: this run would need about {need_mb:.3g} MB (steps={cfg.steps}, "
            f"landmarks={cfg.landmarks}, sensor.clutter_rate={cfg.sensor.clutter_rate:g}, "
            f"sensor.descriptor_dim={cfg.sensor.descriptor_dim}, lidar.beams={cfg.lidar.beams}{_layout_fields(cfg)}), "
            f"over the limit of {limit_mb:g} MB; set {MEMORY_ENV} to allow it")


def _layout_fields(cfg: ScenarioConfig) -> str:
    """The warehouse fields that size the layout, for the memory message (empty where they do not apply)."""
    spec, wh = SCENARIOS[cfg.name], cfg.warehouse
    out = f", warehouse.width_m={wh.width_m:g}, warehouse.aisles={wh.aisles}" if spec.uses_warehouse else ""
    if wh.floor_markers and (spec.uses_warehouse or spec.floor_markers):
        out += f", warehouse.marker_spacing_m={wh.marker_spacing_m:g}"
    return out


@dataclass(frozen=True)
class Layout:
    """What a scenario builder returns."""

    world: World
    waypoints: Array
    initial_pose: Array


@dataclass(frozen=True)
class ScenarioSpec:
    name: str
    description: str
    defaults: dict[str, float | int]
    build: Callable[[ScenarioConfig, np.random.Generator], Layout]
    check: Callable[[ScenarioConfig], None] | None = None
    """raises ValueError naming the field when a config asks for more than the layout can hold."""
    lidar: dict[str, Any] | None = None
    """lidar fields this scenario presets (see ``ScenarioConfig.lidar``)."""
    uses_warehouse: bool = False
    """whether ``ScenarioConfig.warehouse`` applies."""
    floor_markers: bool = False
    """whether the floor-marker fields of ``ScenarioConfig.warehouse`` (and only those) apply."""


def _random_landmarks(rng: np.random.Generator, n: int, box: tuple[float, float, float, float],
                      keep: Callable[[Array], NDArray[np.bool_]]) -> Array:
    """Rejection-sample ``n`` points in ``box`` that satisfy ``keep``."""
    out: list[Array] = []
    while sum(len(o) for o in out) < n:
        p = rng.uniform(box[:2], box[2:], size=(4 * n, 2))
        out.append(p[keep(p)])
    return np.vstack(out)[:n]


def _dist_to_polyline(p: Array, poly: Array) -> Array:
    """Distance from points (K,2) to a closed polyline (P,2)."""
    a = poly
    b = np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("kpi,pi->kp", p[:, None] - a[None], ab) / np.sum(ab * ab, axis=1), 0, 1)
    proj = a[None] + t[..., None] * ab[None]
    return np.min(np.hypot(*(p[:, None] - proj).transpose(2, 0, 1)), axis=1)


def _room(cfg: ScenarioConfig, rng: np.random.Generator) -> Layout:
    route = np.array([[3.0, 3.0], [17.0, 3.0], [17.0, 11.0], [3.0, 11.0]])
    pillar = (9.0, 6.0, 11.0, 8.0)
    walls = np.vstack([box_walls(0, 0, 20, 14), box_walls(*pillar)])

    def keep(p: Array) -> NDArray[np.bool_]:
        in_pillar = (p[:, 0] > pillar[0] - 0.3) & (p[:, 0] < pillar[2] + 0.3) & (p[:, 1] > pillar[1] - 0.3) & (
            p[:, 1] < pillar[3] + 0.3)
        return (_dist_to_polyline(p, route) > 0.8) & ~in_pillar

    lm = _random_landmarks(rng, int(cfg.landmarks or 30), (0.7, 0.7, 19.3, 13.3), keep)
    world = World(lm, np.arange(len(lm)), walls, bounds=(0, 0, 20, 14))
    return Layout(world, route, np.array([3.0, 3.0, 0.0]))


def _loop(cfg: ScenarioConfig, rng: np.random.Generator) -> Layout:
    w, h = 60.0, 40.0
    route = np.array([[w, 0.0], [w, h], [0.0, h], [0.0, 0.0]])
    walls = np.vstack([box_walls(-2, -2, w + 2, h + 2), box_walls(2, 2, w - 2, h - 2)])
    n = int(cfg.landmarks or 100)
    perimeter = 2 * (w + h)
    s = (np.arange(n) // 2 + 0.5) * perimeter / ((n + 1) // 2) + rng.uniform(-0.8, 0.8, n)
    side = np.where(np.arange(n) % 2 == 0, 1.5, -1.5) + rng.uniform(-0.2, 0.2, n)
    # walk the centreline rectangle (0,0)->(w,0)->(w,h)->(0,h) and offset to the left (+) or right (-)
    s = np.mod(s, perimeter)
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=float)
    lengths = np.array([w, h, w, h])
    k = np.minimum(np.searchsorted(np.cumsum(lengths), s, side="right"), 3)
    start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])[k]
    d = (np.roll(corners, -1, axis=0) - corners)[k] / lengths[k, None]
    normal = np.stack([-d[:, 1], d[:, 0]], axis=-1)
    lm = corners[k] + d * (s - start)[:, None] + normal * side[:, None]
    world = World(lm, np.arange(n), walls, bounds=(-2, -2, w + 2, h + 2))
    return Layout(world, route, np.array([0.0, 0.0, 0.0]))


def _warehouse(cfg: ScenarioConfig, rng: np.random.Generator) -> Layout:
    shelves_y = [6.0, 12.0, 18.0, 24.0]
    walls = [box_walls(0, 0, 40, 30)]
    posts = []
    for y in shelves_y:
        walls.append(box_walls(8, y, 32, y + 1))
        for x in np.arange(8.0, 32.1, 4.0):
            posts += [[x, y - 0.2], [x, y + 1.2]]
    lm = np.array(posts)
    aisles = [3.0, 9.5, 15.5, 21.5, 27.5]  # one forklift fits in each of the three inner aisles (_check_warehouse)
    route = []
    for i, y in enumerate(aisles):
        xs = [4.0, 36.0] if i % 2 == 0 else [36.0, 4.0]
        route += [[xs[0], y], [xs[1], y]]
    route_arr = np.array(route + route[::-1][1:-1])
    movers = tuple(
        MovingObject(np.array([[6.0, y + 0.9], [34.0, y + 0.9]]), speed_mps=0.8 + 0.1 * i)
        for i, y in enumerate(aisles[1:4][: int(cfg.moving_objects if cfg.moving_objects is not None else 3)])
    )
    markers = np.zeros((0, 2))
    if cfg.warehouse.floor_markers:  # along every aisle's centre line, from its start every marker_spacing_m
        along = np.arange(4.0, 36.0 + 1e-9, cfg.warehouse.marker_spacing_m)
        markers = np.stack(np.meshgrid(along, aisles, indexing="ij"), axis=-1).reshape(-1, 2)
    world = World(lm, np.arange(len(lm)), np.vstack(walls), moving=movers, bounds=(0, 0, 40, 30),
                  floor_markers=markers)
    return Layout(world, route_arr, np.array([4.0, 3.0, 0.0]))


def _check_warehouse(cfg: ScenarioConfig) -> None:
    if cfg.moving_objects is not None and cfg.moving_objects > 3:
        raise ValueError(f"ScenarioConfig.moving_objects = {cfg.moving_objects} does not fit the 'warehouse' layout "
                         "(3 inner aisles, one forklift each); use scenario 'warehouse-challenge' for more")


def _warehouse_challenge(cfg: ScenarioConfig, rng: np.random.Generator) -> Layout:
    built = build_warehouse(cfg.warehouse, int(cfg.moving_objects if cfg.moving_objects is not None else 20), rng)
    return Layout(built.world, built.waypoints, built.initial_pose)


def _check_warehouse_challenge(cfg: ScenarioConfig) -> None:
    w = cfg.warehouse
    roads = len(w.road_centres_y()) * w.width_m + len(w.cross_centres_x()) * w.depth_m
    most = int(roads // 10.0)  # one forklift per 10 m of road keeps traffic plausible
    if cfg.moving_objects is not None and cfg.moving_objects > most:
        raise ValueError(f"ScenarioConfig.moving_objects = {cfg.moving_objects} does not fit: this warehouse has "
                         f"{roads:.0f} m of roads, room for at most {most} forklifts (one per 10 m)")


def _grid(cfg: ScenarioConfig, rng: np.random.Generator) -> Layout:
    n = int(cfg.landmarks or 100)
    side = int(np.ceil(np.sqrt(n)))
    spacing = 4.0
    ij = np.stack(np.unravel_index(np.arange(n), (side, side)), axis=-1).astype(float)
    lm = ij * spacing + rng.uniform(-0.5, 0.5, size=(n, 2))
    extent = (side - 1) * spacing
    centre = np.array([extent / 2, extent / 2])
    radius = max(4.0, 0.35 * extent)
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    route = centre + radius * np.stack([np.cos(a), np.sin(a)], axis=-1)
    world = World(lm, np.arange(n), np.zeros((0, 4)), bounds=(-2, -2, extent + 2, extent + 2))
    start = np.array([route[0, 0], route[0, 1], np.pi / 2])
    return Layout(world, np.roll(route, -1, axis=0), start)


def _cluster_points(rng: np.random.Generator, centre: Array, n: int, radius_m: float, min_sep_m: float,
                    keep: Callable[[Array], NDArray[np.bool_]]) -> Array:
    """``n`` points in a disc around ``centre``, pairwise at least ``min_sep_m`` apart and satisfying ``keep``
    (greedy rejection)."""
    pts: list[Array] = []
    while len(pts) < n:
        r = radius_m * np.sqrt(rng.random())
        a = rng.uniform(-np.pi, np.pi)
        p = centre + r * np.array([np.cos(a), np.sin(a)])
        if keep(p[None])[0] and all(np.hypot(*(p - q)) >= min_sep_m for q in pts):
            pts.append(p)
        elif len(pts) and rng.random() < 0.002:  # the disc is full: start over (never loops forever)
            pts = []
    return np.array(pts)


def _scramble(cfg: ScenarioConfig, rng: np.random.Generator) -> Layout:
    # a 16 x 10 m loop; clusters of 6 landmarks sit 2.5 m off the route, alternately inside and outside, at least
    # 3 m from the corners; no landmark is closer than 1.5 m to the route, so range-bearing linearisation holds
    route = np.array([[4.0, 4.0], [20.0, 4.0], [20.0, 14.0], [4.0, 14.0]])
    lengths = np.array([16.0, 10.0, 16.0, 10.0])
    n = int(cfg.landmarks or 48)
    per_cluster, margin = 6, 3.0
    n_clusters = int(np.ceil(n / per_cluster))
    # clusters per leg in proportion to its usable length (largest remainder)
    share = n_clusters * (lengths - 2 * margin) / np.sum(lengths - 2 * margin)
    per_leg = np.floor(share).astype(int)
    per_leg[np.argsort(share - per_leg)[::-1][: n_clusters - per_leg.sum()]] += 1
    centres: list[Array] = []
    for leg in range(4):
        a, b = route[leg], route[(leg + 1) % 4]
        d = (b - a) / lengths[leg]
        normal = np.array([-d[1], d[0]])  # points into the loop
        for k in range(per_leg[leg]):
            along = margin + (k + 0.5) * (lengths[leg] - 2 * margin) / per_leg[leg]
            side = 2.5 if len(centres) % 2 == 0 else -2.5
            centres.append(a + d * along + normal * side)

    def keep(p: Array) -> NDArray[np.bool_]:
        return _dist_to_polyline(p, route) >= 1.5

    lm = np.vstack([_cluster_points(rng, c, per_cluster, 0.7, 0.2, keep) for c in centres])[:n]
    world = World(lm, np.arange(n), np.zeros((0, 4)), bounds=(0.0, 0.0, 24.0, 18.0))
    return Layout(world, route, np.array([4.0, 4.0, 0.0]))


SCENARIOS: dict[str, ScenarioSpec] = {
    "room": ScenarioSpec("room", "20 x 14 m room, ~30 landmarks, two laps", dict(steps=450, dt_s=0.2, speed_mps=1.0,
                                                                                  landmarks=30), _room),
    "loop": ScenarioSpec("loop", "200 m corridor loop that returns to its start",
                         dict(steps=460, dt_s=0.25, speed_mps=2.0, landmarks=100), _loop),
    "warehouse": ScenarioSpec("warehouse", "repetitive shelf aisles with moving forklifts",
                              dict(steps=600, dt_s=0.2, speed_mps=1.2, moving_objects=3), _warehouse,
                              check=_check_warehouse, floor_markers=True),
    "warehouse-challenge": ScenarioSpec(
        "warehouse-challenge", "100 x 100 m, 14 identical aisles, pallets moved between flights, 20 forklifts",
        dict(steps=1800, dt_s=1.0 / 30.0, speed_mps=1.2, moving_objects=20), _warehouse_challenge,
        check=_check_warehouse_challenge,
        # 360 beams evenly all round (no duplicate beam at +-pi), 30 m: the challenge's lidar at 30 Hz (dt_s)
        lidar=dict(beams=360, fov_rad=2 * np.pi * 359 / 360, max_range_m=30.0), uses_warehouse=True),
    "grid": ScenarioSpec("grid", "landmarks on a grid (any count), circular drive; for scaling",
                         dict(steps=300, dt_s=0.2, speed_mps=1.5, landmarks=100), _grid),
    "scramble": ScenarioSpec("scramble", "clusters of landmarks closer than the association gates; data association",
                             dict(steps=300, dt_s=0.2, speed_mps=1.0, landmarks=48), _scramble),
}


def register_scenario(spec: ScenarioSpec) -> None:
    """Add a scenario to the catalogue (used by modules that define special-purpose worlds)."""
    SCENARIOS[spec.name] = spec
