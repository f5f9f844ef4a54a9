"""The challenge-scale warehouse: back-to-back racks in identical aisles, pallets in bays, forklifts on the roads.

Plan view (x along the racks, y across them)::

    +----------------------------------------------------------+  perimeter road (road_m wide) all round
    |  [rack block]  cross  [rack block]  cross  [rack block]  |  aisles + 1 rack rows, each cut into
    |  ------------------- aisle centre line ----------------  |  cross_aisles + 1 blocks by cross-aisles
    |  [rack block]  cross  [rack block]  cross  [rack block]  |  (road_m wide)
    +----------------------------------------------------------+

A rack row is ``rack_depth_m`` deep: a thin back panel on its centre line and a row of uprights (0.1 m square
posts, one every ``bay_m``) along each face. The bays between uprights hold pallets (1.2 x 1.0 m boxes) on either
side of the panel, so the lidar sees a pallet face in a full bay and the panel behind an empty one. Uprights are
the point landmarks of this world.

Everything fixed (walls, panels, uprights, markers) follows from the config alone; the pallets and the forklift
routes come from the rng. A *flight* is one day: flight ``f`` starts from flight ``f - 1``'s pallets and moves
``relocate_fraction`` of them to empty bays, with a generator seeded by ``(world draw, f)``, so every
``(seed, flight)`` pair gives the same world and the racks never change between flights.

Bad requests (more aisles than fit, more pallets than bays, ...) raise ``ValueError`` naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.config import check_positive, check_probability
from slam2d.sim.world import MovingObject, World, box_walls

Array = NDArray[np.float64]

UPRIGHT_M = 0.1
PALLET_SIZE_M = (1.2, 1.0)  # along the rack (x), into the bay (y)
FORKLIFT_SIZE_M = (2.0, 1.0)  # length, width
MIN_AISLE_M = 3.0  # a forklift (1 m wide) and a drone pass each other
#: most flights: the pallets of flight f are found by replaying f relocations (~2 ms each), so 10,000 (27 years of
#: daily flights) takes ~20 s to build; beyond, a mistyped flight would build for hours
MAX_FLIGHT = 10_000


@dataclass(frozen=True, slots=True, kw_only=True)
class WarehouseConfig:
    """Geometry and contents of the challenge warehouse (``warehouse-challenge`` scenario)."""

    width_m: float = 100.0
    """extent along the racks (m)."""
    depth_m: float = 100.0
    """extent across the racks (m)."""
    aisles: int = 14
    """aisles between rack rows (there are aisles + 1 rows)."""
    cross_aisles: int = 2
    """cross-aisles cutting every rack row into cross_aisles + 1 blocks."""
    road_m: float = 4.0
    """width of the perimeter road and of each cross-aisle (m)."""
    rack_depth_m: float = 2.4
    """depth of a back-to-back rack row (m); each half holds one pallet deep."""
    bay_m: float = 2.7
    """distance between uprights along a rack face (m)."""
    pallets: int = 600
    """pallets in the bays (at most the number of bays)."""
    relocate_fraction: float = 0.1
    """fraction of the pallets moved to other bays between consecutive flights."""
    flight: int = 0
    """flight (day) index: same racks, pallets relocated flight times since flight 0."""
    floor_markers: bool = False
    """put ID'd markers on the floor along every aisle and road (read by the downward camera)."""
    marker_spacing_m: float = 10.0
    """distance between floor markers along a centre line (m)."""

    def __post_init__(self) -> None:
        check_positive(self, "width_m", "depth_m", "road_m", "rack_depth_m", "bay_m", "marker_spacing_m")
        check_probability(self, "relocate_fraction")
        for n, lo in (("aisles", 1), ("cross_aisles", 0), ("pallets", 0), ("flight", 0)):
            if getattr(self, n) < lo:
                raise ValueError(f"WarehouseConfig.{n} must be >= {lo} (got {getattr(self, n)})")
        if self.flight > MAX_FLIGHT:
            raise ValueError(f"WarehouseConfig.flight must be <= {MAX_FLIGHT} (got {self.flight}): each flight's "
                             "pallets are found by replaying every relocation since flight 0")
        if self.road_m < FORKLIFT_SIZE_M[0] + 1.0:
            raise ValueError(f"WarehouseConfig.road_m must be >= {FORKLIFT_SIZE_M[0] + 1.0} m so a forklift can "
                             f"turn (got {self.road_m})")
        if self.bay_m < PALLET_SIZE_M[0] + UPRIGHT_M + 0.1:
            raise ValueError(f"WarehouseConfig.bay_m must be >= {PALLET_SIZE_M[0] + UPRIGHT_M + 0.1} m to hold a "
                             f"pallet (got {self.bay_m})")
        if self.rack_depth_m < 2 * PALLET_SIZE_M[1] + 0.2:
            raise ValueError(f"WarehouseConfig.rack_depth_m must be >= {2 * PALLET_SIZE_M[1] + 0.2} m (two pallets "
                             f"back to back; got {self.rack_depth_m})")
        aisle = self.aisle_width_m
        if aisle < MIN_AISLE_M:
            most = int((self.depth_m - 2 * self.road_m - self.rack_depth_m) // (self.rack_depth_m + MIN_AISLE_M))
            raise ValueError(f"WarehouseConfig.aisles = {self.aisles} does not fit: aisles would be {aisle:.2f} m wide "
                             f"(< {MIN_AISLE_M} m) in a {self.depth_m} m deep warehouse; at most {max(most, 0)} fit")
        if self.bays_per_face_per_block < 1:
            raise ValueError(f"WarehouseConfig.cross_aisles = {self.cross_aisles} does not fit: rack blocks would be "
                             f"{self.block_length_m:.2f} m long, shorter than one {self.bay_m} m bay")
        if self.pallets > self.bay_count:
            raise ValueError(f"WarehouseConfig.pallets = {self.pallets} does not fit: the racks have "
                             f"{self.bay_count} bays")
        moved, empty = round(self.relocate_fraction * self.pallets), self.bay_count - self.pallets
        if self.flight > 0 and moved > empty:
            raise ValueError(f"WarehouseConfig.relocate_fraction = {self.relocate_fraction} moves {moved} pallets "
                             f"between flights, but only {empty} bays are empty")

    @property
    def aisle_width_m(self) -> float:
        racks = self.aisles + 1
        return (self.depth_m - 2 * self.road_m - racks * self.rack_depth_m) / self.aisles

    @property
    def block_length_m(self) -> float:
        return (self.width_m - 2 * self.road_m - self.cross_aisles * self.road_m) / (self.cross_aisles + 1)

    @property
    def bays_per_face_per_block(self) -> int:
        return int((self.block_length_m - UPRIGHT_M) // self.bay_m)

    @property
    def bay_count(self) -> int:
        """Pallet slots: two faces per rack row, one pallet per bay per face."""
        return (self.aisles + 1) * (self.cross_aisles + 1) * 2 * self.bays_per_face_per_block

    def rack_rows_y(self) -> Array:
        """(aisles + 1,) lower edge y of each rack row."""
        step = self.rack_depth_m + self.aisle_width_m
        return np.asarray(self.road_m + step * np.arange(self.aisles + 1), dtype=np.float64)

    def aisle_centres_y(self) -> Array:
        """(aisles,) y of each aisle's centre line."""
        return self.rack_rows_y()[:-1] + self.rack_depth_m + 0.5 * self.aisle_width_m

    def cross_centres_x(self) -> Array:
        """(cross_aisles + 2,) x of the cross-aisle centre lines, the two end roads included."""
        inner = self.road_m + (self.block_length_m + self.road_m) * np.arange(1, self.cross_aisles + 1) \
            - 0.5 * self.road_m
        return np.concatenate([[0.5 * self.road_m], inner, [self.width_m - 0.5 * self.road_m]])

    def road_centres_y(self) -> Array:
        """y of every line a forklift may drive along x: the two perimeter roads and the aisles."""
        return np.concatenate([[0.5 * self.road_m], self.aisle_centres_y(), [self.depth_m - 0.5 * self.road_m]])

    def block_x0(self) -> Array:
        """(cross_aisles + 1,) x of the left end of each rack block."""
        return np.asarray(self.road_m + (self.block_length_m + self.road_m) * np.arange(self.cross_aisles + 1),
                          dtype=np.float64)

    def rack_footprints(self) -> Array:
        """(R, 4) [x0, y0, x1, y1] of every rack block (uprights, panel and pallets lie inside)."""
        xs, ys = self.block_x0(), self.rack_rows_y()
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        x, y = gx.ravel(), gy.ravel()
        return np.stack([x, y, x + self.block_length_m, y + self.rack_depth_m], axis=-1)


@dataclass(frozen=True)
class WarehouseLayout:
    """Built warehouse: the world, the drone's lawnmower route and start pose, pallet slots, markers."""

    world: World
    waypoints: Array
    initial_pose: Array
    slot_centres: Array
    """(S, 2) centre of every pallet slot."""
    occupied: NDArray[np.int64]
    """indices into ``slot_centres`` of the slots holding a pallet (sorted)."""
    markers: Array
    """(M, 2) floor marker positions (empty without floor markers); the id of marker ``i`` is ``i``."""


def slot_centres(cfg: WarehouseConfig) -> Array:
    """(S, 2) pallet slot centres: every bay on both faces of every rack block, in a fixed order."""
    nb = cfg.bays_per_face_per_block
    slack = cfg.block_length_m - UPRIGHT_M - nb * cfg.bay_m
    bay_cx = 0.5 * slack + UPRIGHT_M + cfg.bay_m * (np.arange(nb) + 0.5) - 0.5 * UPRIGHT_M
    half = 0.5 * cfg.rack_depth_m
    face_cy = np.array([half - 0.5 * PALLET_SIZE_M[1] - 0.05, half + 0.5 * PALLET_SIZE_M[1] + 0.05])
    bx, ry, f, b = np.meshgrid(cfg.block_x0(), cfg.rack_rows_y(), face_cy, bay_cx, indexing="ij")
    return np.stack([(bx + b).ravel(), (ry + f).ravel()], axis=-1)


def uprights(cfg: WarehouseConfig) -> Array:
    """(U, 2) upright centres: one every bay along both faces of every block (bays + 1 per face)."""
    nb = cfg.bays_per_face_per_block
    slack = cfg.block_length_m - UPRIGHT_M - nb * cfg.bay_m
    ux = 0.5 * slack + 0.5 * UPRIGHT_M + cfg.bay_m * np.arange(nb + 1)
    uy = np.array([0.5 * UPRIGHT_M, cfg.rack_depth_m - 0.5 * UPRIGHT_M])
    bx, ry, f, u = np.meshgrid(cfg.block_x0(), cfg.rack_rows_y(), uy, ux, indexing="ij")
    return np.stack([(bx + u).ravel(), (ry + f).ravel()], axis=-1)


def boxes_to_segments(centres: Array, size: tuple[float, float]) -> Array:
    """(K, 2) box centres of one axis-aligned size -> (4K, 4) outline segments."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    hx, hy = 0.5 * size[0], 0.5 * size[1]
    corners = c[:, None, :] + np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])  # (K,4,2)
    return np.concatenate([corners, np.roll(corners, -1, axis=1)], axis=-1).reshape(-1, 4)


def static_structure(cfg: WarehouseConfig) -> Array:
    """Outer walls, back panels and uprights as (W, 4) segments: identical for every seed and flight."""
    panels = np.array([[x0, y0 + 0.5 * cfg.rack_depth_m, x1, y0 + 0.5 * cfg.rack_depth_m]
                       for x0, y0, x1, _ in cfg.rack_footprints()])
    return np.vstack([box_walls(0, 0, cfg.width_m, cfg.depth_m), panels,
                      boxes_to_segments(uprights(cfg), (UPRIGHT_M, UPRIGHT_M))])


def pallet_slots(cfg: WarehouseConfig, rng: np.random.Generator) -> NDArray[np.int64]:
    """Occupied slot indices for ``cfg.flight``: a fresh fill on flight 0, then one relocation per flight."""
    n_slots = cfg.bay_count
    base = int(rng.integers(2**62))
    occupied = np.sort(rng.choice(n_slots, size=cfg.pallets, replace=False))
    for f in range(1, cfg.flight + 1):
        r = np.random.default_rng(np.random.SeedSequence([base, f]))
        n_move = round(cfg.relocate_fraction * cfg.pallets)  # validated: never more than the empty bays
        free = np.setdiff1d(np.arange(n_slots), occupied)
        leave = r.choice(occupied, size=n_move, replace=False)
        arrive = r.choice(free, size=n_move, replace=False)
        occupied = np.sort(np.concatenate([np.setdiff1d(occupied, leave), arrive]))
    return occupied.astype(np.int64)


def forklift_routes(cfg: WarehouseConfig, count: int, rng: np.random.Generator) -> tuple[MovingObject, ...]:
    """``count`` forklifts, each driving a random rectangle of roads: along two aisles (or perimeter roads) joined
    by two cross-aisles, at 1.0-2.5 m/s, facing where it drives."""
    ys, xs = cfg.road_centres_y(), cfg.cross_centres_x()
    out = []
    for _ in range(count):
        i, j = np.sort(rng.choice(len(ys), size=2, replace=False))
        a, b = np.sort(rng.choice(len(xs), size=2, replace=False))
        loop = np.array([[xs[a], ys[i]], [xs[b], ys[i]], [xs[b], ys[j]], [xs[a], ys[j]]])
        if rng.random() < 0.5:
            loop = loop[::-1].copy()
        start = int(rng.integers(4))
        out.append(MovingObject(np.roll(loop, -start, axis=0), speed_mps=float(rng.uniform(1.0, 2.5)),
                                size_m=FORKLIFT_SIZE_M, heading_aligned=True,
                                phase_m=float(rng.uniform(0.0, 100.0))))
    return tuple(out)


def floor_markers(cfg: WarehouseConfig) -> Array:
    """(M, 2) markers every ``marker_spacing_m`` along every aisle and perimeter road, plus one at every crossing
    of an aisle with a cross-aisle (the places where a drone turns)."""
    if not cfg.floor_markers:
        return np.zeros((0, 2))
    ys, xs = cfg.road_centres_y(), cfg.cross_centres_x()
    along = np.arange(xs[0], xs[-1] + 1e-9, cfg.marker_spacing_m)
    pts = np.vstack([np.stack(np.meshgrid(along, ys, indexing="ij"), axis=-1).reshape(-1, 2),
                     np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)])
    # drop near-duplicates (a spacing point that falls on a crossing)
    keep = np.ones(len(pts), dtype=bool)
    d = np.hypot(*(pts[:, None] - pts[None]).transpose(2, 0, 1))
    keep &= ~np.any(np.triu(d < 0.5 * cfg.marker_spacing_m, 1), axis=0)
    return pts[keep]


def lawnmower_route(cfg: WarehouseConfig) -> Array:
    """Down every aisle in turn, alternating direction, joined along the end roads; then back the same way."""
    x_lo, x_hi = cfg.cross_centres_x()[[0, -1]]
    route: list[list[float]] = []
    for k, y in enumerate(cfg.road_centres_y()[:-1]):
        xa, xb = (x_lo, x_hi) if k % 2 == 0 else (x_hi, x_lo)
        route += [[xa, y], [xb, y]]
    return np.array(route + route[::-1][1:-1])


def build_warehouse(cfg: WarehouseConfig, forklifts: int, rng: np.random.Generator) -> WarehouseLayout:
    """The whole warehouse for ``cfg`` (flight included) with ``forklifts`` forklifts."""
    slots = slot_centres(cfg)
    occupied = pallet_slots(cfg, rng)
    # forklift routes differ per flight (a different day's traffic), from their own generator
    traffic = np.random.default_rng(np.random.SeedSequence([int(rng.integers(2**62)), cfg.flight]))
    movers = forklift_routes(cfg, forklifts, traffic)
    walls = np.vstack([static_structure(cfg), boxes_to_segments(slots[occupied], PALLET_SIZE_M)])
    posts = uprights(cfg)
    markers = floor_markers(cfg)
    world = World(posts, np.arange(len(posts)), walls, moving=movers, bounds=(0.0, 0.0, cfg.width_m, cfg.depth_m),
                  floor_markers=markers)
    route = lawnmower_route(cfg)
    return WarehouseLayout(world, route, np.array([route[0, 0], route[0, 1], 0.0]), slots, occupied, markers)
