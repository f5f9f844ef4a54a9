"""Lifelong map layers for a lidar estimator: a persistent static layer and an ephemeral dynamic layer.

Both layers share one grid (row = y, column = x, like :class:`~slam2d.maps.occupancy.OccupancyGrid`) that grows in
``grow_margin_m`` steps when the robot reaches new ground, so memory follows the mapped area, never the time.

**Static layer** (walls, racks, parked pallets): per cell a clamped log-odds (``+hit`` at a beam's endpoint, ``-miss``
in the cells a beam crossed, never within ``endpoint_guard_cells`` of its end) and a *sighting streak*: the time the
cell's current run of hits began, and the time of its last hit; a gap longer than ``max_gap_s`` starts a new streak.
**Persistence rule:** a cell enters the static layer when its log-odds reaches ``occupied_logodds`` *and* its streak
has lasted ``persist_s`` (it was hit again and again for that long); it leaves when pass-through evidence drives its
log-odds below 0. A forklift (2 m long, >= 1 m/s) covers a cell for about 2 s and then clears it, so its streaks
stay short; a wall or a pallet that was moved into a bay keeps being hit for as long as it is in view and is
promoted after ``persist_s``; a pallet taken away is seen through and demoted. Nothing is ever added to the static
layer from a single glimpse, and points labelled dynamic raise only the evidence, never the layer itself.

**Dynamic layer** (forklifts, pallets not yet persistent): the time each cell was last hit by a point labelled
dynamic; its occupancy decays as ``exp(-age / dynamic_decay_s)`` (computed when asked: no per-scan sweep of the
grid), and a beam passing through a cell clears it at once.

**Labels** of a scan's points (:meth:`MapLayers.classify`): ``STATIC`` within ``dynamic_distance_m`` of the static
layer; ``DYNAMIC`` otherwise if its cell was known free (log-odds <= ``free_logodds``) now or when its current streak
began (something appeared where the robot had seen through); ``PENDING`` otherwise (unexplored ground: a wall seen
for the first time waits for its persistence).

**Localisation** (:meth:`MapLayers.match`): Gauss-Newton on the static layer's truncated distance field (bilinear, a
Cauchy weight, dynamic points excluded by the caller): a few vectorised gathers per iteration, no KD-tree, no loop
over points. The field is refreshed only around cells that joined or left the static layer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_positive
from slam2d.geometry import se2
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid

Array = NDArray[np.float64]

STATIC, PENDING, DYNAMIC = 0, 1, 2
"""point labels of :meth:`MapLayers.classify`."""


@dataclass(frozen=True, slots=True, kw_only=True)
class LayersConfig:
    """Static/dynamic layer settings (see the module docstring for the rules)."""

    resolution_m: float = 0.1
    """cell side of both layers (m)."""
    hit_logodds: float = 0.85
    """log-odds added to a beam's endpoint cell."""
    miss_logodds: float = 0.4
    """log-odds removed from every cell a beam crossed."""
    min_logodds: float = -2.0
    """lower clamp (a free cell can still become occupied)."""
    max_logodds: float = 3.5
    """upper clamp (an occupied cell can still be cleared)."""
    occupied_logodds: float = 1.5
    """a cell needs this much evidence to enter the static layer."""
    free_logodds: float = -0.5
    """a cell at or below this is known free."""
    persist_s: float = 5.0
    """a cell that was known free when its streak began (something appeared there: a forklift, a pallet put down)
    enters the static layer after a streak of sightings this long (s)."""
    new_persist_s: float = 0.5
    """a cell never seen free before (unexplored ground: a wall seen for the first time) needs a streak this long
    (s): two sightings at least, so that one noisy beam is not a wall, short enough that thin uprights (hit by
    one beam now and then from afar) make it into the map while the robot passes."""
    max_gap_s: float = 1.5
    """a gap between two hits longer than this starts a new streak (s)."""
    endpoint_guard_cells: int = 2
    """a beam clears nothing within this many cells of its endpoint (range noise, grazing beams)."""
    miss_beam_stride: int = 2
    """free space is traced along every this-many-th beam (the cost of an update is in the tracing)."""
    field_max_m: float = 1.0
    """the distance field is truncated here (m): the basin of convergence of :meth:`MapLayers.match`."""
    field_refresh_every: int = 10
    """cells that joined or left the static layer refresh the field at most every this many integrations."""
    dynamic_distance_m: float = 0.3
    """a point farther than this from the static layer is not explained by it (m)."""
    dynamic_decay_s: float = 2.0
    """time constant of the dynamic layer's decay (s)."""
    match_iterations: int = 12
    """Gauss-Newton iterations of :meth:`MapLayers.match` (it stops earlier on a tiny step)."""
    prior_sigma_xy_m: float = 0.03
    """:meth:`MapLayers.match` keeps the pose near its guess (odometry) with this standard deviation (m): along
    a corridor or a row of identical bays the scan alone does not fix the position."""
    prior_sigma_theta_rad: float = 0.01
    """... and this one in heading (rad)."""
    range_sigma_m: float = 0.05
    """standard deviation of a point's distance to the static layer, weighing the scan against the prior (m)."""
    match_cauchy_m: float = 0.1
    """scale of the Cauchy weight of a point's distance in :meth:`MapLayers.match` (m)."""
    inlier_m: float = 0.1
    """a matched point closer than this to the static layer counts as an inlier (m)."""
    grow_margin_m: float = 10.0
    """the grid grows by at least this much beyond what is needed (m)."""

    def __post_init__(self) -> None:
        check_positive(self, "resolution_m", "hit_logodds", "miss_logodds", "max_logodds", "occupied_logodds",
                       "persist_s", "new_persist_s", "max_gap_s", "field_max_m", "dynamic_distance_m", "dynamic_decay_s",
                       "match_cauchy_m", "inlier_m", "grow_margin_m",
                       "prior_sigma_xy_m", "prior_sigma_theta_rad", "range_sigma_m")
        if not self.min_logodds < self.free_logodds < 0:
            raise ValueError(f"LayersConfig needs min_logodds < free_logodds < 0 (got {self.min_logodds}, "
                             f"{self.free_logodds})")
        if self.occupied_logodds > self.max_logodds:
            raise ValueError(f"LayersConfig.occupied_logodds ({self.occupied_logodds}) must be <= max_logodds "
                             f"({self.max_logodds})")
        for n in ("miss_beam_stride", "field_refresh_every", "match_iterations"):
            if getattr(self, n) < 1:
                raise ValueError(f"LayersConfig.{n} must be >= 1 (got {getattr(self, n)})")
        if self.endpoint_guard_cells < 0:
            raise ValueError(f"LayersConfig.endpoint_guard_cells must be >= 0 (got {self.endpoint_guard_cells})")


@dataclass(frozen=True)
class FieldMatch:
    """Result of :meth:`MapLayers.match`: pose (3,), covariance (3,3), inliers (count of points within
    ``inlier_m``), points used, iterations run, and whether every direction was constrained."""

    pose: Array
    covariance: Array
    inliers: int
    points: int
    iterations: int
    constrained: bool


class MapLayers:
    """The static and dynamic layers on one growing grid (see the module docstring)."""

    _FILL: ClassVar[dict[str, float | bool]] = {"logodds": 0.0, "streak": -np.inf, "last_hit": -np.inf,
                                                "static": False, "appeared": False, "dyn_seen": -np.inf}

    def __init__(self, config: LayersConfig | None = None) -> None:
        self.config = config or LayersConfig()
        self.origin = np.zeros(2)
        self.shape = (0, 0)
        self.logodds = np.zeros((0, 0), np.float32)
        self.streak = np.zeros((0, 0), np.float32)  # time the cell's current run of hits began
        self.last_hit = np.zeros((0, 0), np.float32)
        self.static = np.zeros((0, 0), bool)
        self.appeared = np.zeros((0, 0), bool)  # the current streak began in a cell known free
        self.dyn_seen = np.zeros((0, 0), np.float32)  # last time a dynamic point hit the cell
        self.field = np.zeros((0, 0), np.float32)  # distance to the nearest static cell (m), truncated
        self.integrations = 0
        self.promoted = 0
        self.demoted = 0
        self._dirty: list[int] | None = None  # [row0, col0, row1, col1] of cells whose static flag changed
        self._since_refresh = 0

    # ------------------------------------------------------------------ geometry
    @property
    def resolution(self) -> float:
        return self.config.resolution_m

    def cell_index(self, xy: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Flat cell indices of points (K,2) and whether each lies inside the grid."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        ij = np.floor((p - self.origin) / self.resolution).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < self.shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < self.shape[0])
        return np.where(inside, ij[:, 1] * self.shape[1] + ij[:, 0], 0), inside

    def cell_centres(self, flat: NDArray[np.int64]) -> Array:
        """World centres (K,2) of flat cell indices."""
        r, c = np.divmod(np.asarray(flat, dtype=np.int64), self.shape[1])
        return self.origin + (np.stack([c, r], axis=-1) + 0.5) * self.resolution

    def _ensure(self, lo: Array, hi: Array) -> None:
        """Grow every array so that the box [lo, hi] lies inside the grid (cells stay aligned)."""
        res = self.resolution
        cur_lo = self.origin
        cur_hi = self.origin + np.array([self.shape[1], self.shape[0]]) * res
        if self.shape[0] and np.all(lo >= cur_lo) and np.all(hi < cur_hi):
            return
        m = self.config.grow_margin_m
        if not self.shape[0]:
            new_lo = np.floor((lo - m) / res) * res
            new_hi = hi + m
        else:
            new_lo = np.where(lo < cur_lo, cur_lo - np.ceil((cur_lo - lo + m) / res) * res, cur_lo)
            new_hi = np.where(hi >= cur_hi, hi + m, cur_hi)
        shape = (int(np.ceil((new_hi[1] - new_lo[1]) / res)), int(np.ceil((new_hi[0] - new_lo[0]) / res)))
        if shape[0] * shape[1] > 50_000_000:
            raise ValueError(f"MapLayers: a grid of {shape} cells is too large; raise LayersConfig.resolution_m")
        off = np.rint((cur_lo - new_lo) / res).astype(np.int64)  # (col, row) offset of the old grid
        for name, fill in self._FILL.items():
            old = getattr(self, name)
            new = np.full(shape, fill, dtype=old.dtype)
            if old.size:
                new[off[1]:off[1] + old.shape[0], off[0]:off[0] + old.shape[1]] = old
            setattr(self, name, new)
        fm = self.config.field_max_m
        field = np.full(shape, fm, dtype=np.float32)
        if self.field.size:
            field[off[1]:off[1] + self.field.shape[0], off[0]:off[0] + self.field.shape[1]] = self.field
        self.field = field
        if self._dirty is not None:
            self._dirty = [self._dirty[0] + off[1], self._dirty[1] + off[0], self._dirty[2] + off[1],
                           self._dirty[3] + off[0]]
        self.origin, self.shape = new_lo, shape

    # ------------------------------------------------------------------ labelling
    def classify(self, pose: ArrayLike, points: ArrayLike) -> NDArray[np.int8]:
        """Labels (K,) ``STATIC`` / ``PENDING`` / ``DYNAMIC`` of robot-frame points (K,2) seen from ``pose``."""
        world = se2.transform_points(np.asarray(pose, dtype=np.float64), np.asarray(points, dtype=np.float64))
        out = np.full(len(world), PENDING, dtype=np.int8)
        if not self.shape[0]:
            return out
        flat, inside = self.cell_index(world)
        f, lo, app = self.field.ravel()[flat], self.logodds.ravel()[flat], self.appeared.ravel()[flat]
        near = inside & (f <= self.config.dynamic_distance_m)
        dyn = inside & ~near & ((lo <= self.config.free_logodds) | app)
        out[near] = STATIC
        out[dyn] = DYNAMIC
        return out

    # ------------------------------------------------------------------ updates
    def integrate(self, pose: ArrayLike, points: ArrayLike, labels: ArrayLike, time_s: float, *,
                  bootstrap: bool = False) -> None:
        """Add one scan: robot-frame endpoints (K,2) of beams that hit, their labels (K,), seen from ``pose`` at
        ``time_s``. ``bootstrap`` puts every hit into the static layer at once (the very first scan: there is no
        map to localise against yet)."""
        cfg = self.config
        pose = np.asarray(pose, dtype=np.float64)
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        lab = np.asarray(labels, dtype=np.int8)
        world = se2.transform_points(pose, pts)
        if not len(world):
            return
        self._ensure(np.minimum(world.min(axis=0), pose[:2]), np.maximum(world.max(axis=0), pose[:2]))
        t = np.float32(time_s)
        lo, st, last = self.logodds.ravel(), self.static.ravel(), self.last_hit.ravel()
        # free space: samples every cell along the traced beams, stopping short of the endpoint
        res = self.resolution
        sub = world[:: cfg.miss_beam_stride]
        d = sub - pose[:2]
        r = np.hypot(d[:, 0], d[:, 1])
        reach = r - (cfg.endpoint_guard_cells + 0.5) * res
        n = int(np.ceil(max(float(reach.max()), 0.0) / res))
        if n > 0:
            s = (np.arange(n) + 0.5) * res
            keep = s[None, :] < reach[:, None]
            u = d / np.maximum(r, 1e-9)[:, None]
            samples = pose[:2] + (u[:, None, :] * s[None, :, None])[keep]
            miss, ok = self.cell_index(samples)
            miss = miss[ok]
            lo[miss] = np.maximum(lo[miss] - cfg.miss_logodds, cfg.min_logodds)
            gone = miss[st[miss] & (lo[miss] < 0.0)]
            if gone.size:
                st[gone] = False
                self.demoted += int(np.unique(gone).size)
                self._mark_dirty(gone)
            self.dyn_seen.ravel()[miss] = -np.inf  # seen through: nothing there now
        # hits: evidence, sighting streaks, promotion
        hit, _ = self.cell_index(world)
        before = lo[hit]
        fresh = (t - last[hit]) > cfg.max_gap_s
        streak = self.streak.ravel()
        streak[hit[fresh]] = t
        self.appeared.ravel()[hit[fresh]] = before[fresh] <= cfg.free_logodds
        last[hit] = t
        lo[hit] = np.minimum(before + cfg.hit_logodds, cfg.max_logodds)
        need = np.where(self.appeared.ravel()[hit], cfg.persist_s, cfg.new_persist_s)
        ready = (lo[hit] >= cfg.occupied_logodds) & ((t - streak[hit]) >= need)
        new = hit[~st[hit] & (ready | bootstrap)]
        if new.size:
            st[new] = True
            self.promoted += int(np.unique(new).size)
            self._mark_dirty(new)
        dyn = hit[lab == DYNAMIC]
        self.dyn_seen.ravel()[dyn] = t
        self.integrations += 1
        self._since_refresh += 1
        if self._dirty is not None and (bootstrap or self._since_refresh >= cfg.field_refresh_every):
            self.refresh_field()

    def _mark_dirty(self, flat: NDArray[np.int64]) -> None:
        r, c = np.divmod(flat, self.shape[1])
        box = [int(r.min()), int(c.min()), int(r.max()), int(c.max())]
        if self._dirty is not None:
            box = [min(box[0], self._dirty[0]), min(box[1], self._dirty[1]), max(box[2], self._dirty[2]),
                   max(box[3], self._dirty[3])]
        self._dirty = box

    def refresh_field(self) -> None:
        """Recompute the distance field around the cells whose static flag changed since the last refresh."""
        from scipy.ndimage import distance_transform_edt

        self._since_refresh = 0
        if self._dirty is None:
            return
        r0, c0, r1, c1 = self._dirty
        self._dirty = None
        fm = self.config.field_max_m
        m = int(np.ceil(fm / self.resolution)) + 1
        ny, nx = self.shape
        # cells within m of a change may change; their nearest static cell lies within m of them
        a0, b0, a1, b1 = max(r0 - m, 0), max(c0 - m, 0), min(r1 + m + 1, ny), min(c1 + m + 1, nx)
        e0, f0, e1, f1 = max(a0 - m, 0), max(b0 - m, 0), min(a1 + m, ny), min(b1 + m, nx)
        occ = self.static[e0:e1, f0:f1]
        if occ.any():
            dist = distance_transform_edt(~occ) * self.resolution
            dist = np.minimum(dist, fm).astype(np.float32)
        else:
            dist = np.full(occ.shape, fm, dtype=np.float32)
        self.field[a0:a1, b0:b1] = dist[a0 - e0:a1 - e0, b0 - f0:b1 - f0]

    # ------------------------------------------------------------------ localisation
    def match(self, points: ArrayLike, guess: ArrayLike) -> FieldMatch:
        """Align robot-frame points (N,2) to the static layer from ``guess``: Gauss-Newton on the bilinear
        distance field, Cauchy-weighted; points on the field's plateau (far from everything) pull nothing."""
        cfg = self.config
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        g = np.asarray(guess, dtype=np.float64)
        x = g.copy()
        prior = np.diag([cfg.prior_sigma_xy_m**-2, cfg.prior_sigma_xy_m**-2, cfg.prior_sigma_theta_rad**-2])
        scale = cfg.range_sigma_m**-2
        res, ny, nx = self.resolution, self.shape[0], self.shape[1]
        field = self.field
        h = np.zeros((3, 3))
        f = np.zeros(0)
        it = 0
        for it in range(1, cfg.match_iterations + 1):  # noqa: B007 - iteration count is reported
            c, s = np.cos(x[2]), np.sin(x[2])
            qx = c * p[:, 0] - s * p[:, 1] + x[0]
            qy = s * p[:, 0] + c * p[:, 1] + x[1]
            u = (qx - self.origin[0]) / res - 0.5
            v = (qy - self.origin[1]) / res - 0.5
            j0, i0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
            ok = (j0 >= 0) & (j0 < nx - 1) & (i0 >= 0) & (i0 < ny - 1)
            j0, i0 = np.where(ok, j0, 0), np.where(ok, i0, 0)
            fu, fv = u - j0, v - i0
            f00, f01 = field[i0, j0], field[i0, j0 + 1]
            f10, f11 = field[i0 + 1, j0], field[i0 + 1, j0 + 1]
            f = (1 - fv) * ((1 - fu) * f00 + fu * f01) + fv * ((1 - fu) * f10 + fu * f11)
            gx = ((1 - fv) * (f01 - f00) + fv * (f11 - f10)) / res
            gy = ((1 - fu) * (f10 - f00) + fu * (f11 - f01)) / res
            f = np.where(ok, f, cfg.field_max_m)
            w = np.where(ok & (f < cfg.field_max_m), 1.0 / (1.0 + (f / cfg.match_cauchy_m) ** 2), 0.0)
            jt = gx * (-s * p[:, 0] - c * p[:, 1]) + gy * (c * p[:, 0] - s * p[:, 1])
            jac = np.stack([gx, gy, jt], axis=-1)
            wj = jac * w[:, None]
            h = scale * (jac.T @ wj)
            e = x - g
            e[2] = float(np.arctan2(np.sin(e[2]), np.cos(e[2])))
            b = scale * (wj.T @ f) + prior @ e
            try:
                dx = -np.linalg.solve(h + prior, b)
            except np.linalg.LinAlgError:
                break
            x = x + dx
            x[2] = float(np.arctan2(np.sin(x[2]), np.cos(x[2])))
            if np.hypot(dx[0], dx[1]) < 1e-4 and abs(dx[2]) < 1e-5:
                break
        inl = int(np.count_nonzero(f < cfg.inlier_m))
        eig = np.linalg.eigvalsh(h) if np.all(np.isfinite(h)) else np.zeros(3)
        constrained = bool(eig[0] > 1e-6 * max(eig[-1], 1e-12) and eig[0] > 1.0)
        cov = np.asarray(np.linalg.inv(h + prior), np.float64)
        return FieldMatch(x, cov, inl, len(p), it, constrained)

    # ------------------------------------------------------------------ views
    def static_cells(self) -> NDArray[np.int64]:
        """Flat indices of the static layer's cells."""
        return np.flatnonzero(self.static.ravel())

    def static_points(self) -> Array:
        """(N,2) centres of the static layer's cells."""
        return self.cell_centres(self.static_cells())

    def dynamic_occupancy(self, time_s: float) -> NDArray[np.float32]:
        """The dynamic layer at ``time_s``: exp(-age / dynamic_decay_s) of each cell's last dynamic hit (0: none)."""
        age = np.float32(time_s) - self.dyn_seen
        with np.errstate(over="ignore", invalid="ignore"):
            out = np.exp(-np.maximum(age, 0) / np.float32(self.config.dynamic_decay_s))
        return np.where(np.isfinite(self.dyn_seen), out, 0).astype(np.float32)

    def dynamic_points(self, time_s: float, threshold: float = 0.5) -> Array:
        """(N,2) centres of the dynamic layer's cells whose occupancy at ``time_s`` is above ``threshold``."""
        return self.cell_centres(np.flatnonzero(self.dynamic_occupancy(time_s).ravel() > threshold))

    def static_grid(self) -> OccupancyGrid:
        """The static layer as an occupancy grid: its cells occupied, known-free cells free, the rest unknown."""
        res = self.resolution
        x0, y0 = self.origin
        grid = OccupancyGrid((x0, y0, x0 + (self.shape[1] - 0.5) * res, y0 + (self.shape[0] - 0.5) * res),
                             OccupancyConfig(resolution_m=res))
        free = self.logodds <= self.config.free_logodds
        grid.logodds = np.where(self.static, self.config.max_logodds, np.where(free, self.logodds, 0.0)).astype(float)
        grid.observed = self.static | free
        return grid

    def nbytes(self) -> int:
        """Bytes held by the grids."""
        return sum(getattr(self, n).nbytes for n in (*self._FILL, "field"))


@dataclass(frozen=True, slots=True)
class LayerStats:
    """Lifelong-mode counters of an estimator: keyframes, cells in the static layer, cells promoted into / demoted
    out of it so far, points labelled dynamic in the last scan and in all, bytes of the layer grids, tracking
    failures."""

    keyframes: int = 0
    static_cells: int = 0
    promoted: int = 0
    demoted: int = 0
    dynamic_points_last: int = 0
    dynamic_points_total: int = 0
    grid_bytes: int = 0
    tracking_failures: int = 0


class PoseBuffer:
    """Poses (3,) appended one at a time into fixed 4096-row blocks: 24 bytes a pose, no per-pose object."""

    BLOCK = 4096

    def __init__(self) -> None:
        self._blocks: list[Array] = []
        self._n = 0

    def append(self, pose: Array) -> None:
        if self._n % self.BLOCK == 0:
            self._blocks.append(np.empty((self.BLOCK, 3)))
        self._blocks[-1][self._n % self.BLOCK] = pose
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def array(self) -> Array:
        return np.concatenate(self._blocks)[: self._n] if self._blocks else np.zeros((0, 3))
