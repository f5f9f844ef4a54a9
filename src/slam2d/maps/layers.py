"""Lifelong map layers for a lidar estimator: a persistent static layer and an ephemeral dynamic layer.

Both layers share one grid (row = y, column = x, like :class:`~slam2d.maps.occupancy.OccupancyGrid`) that grows in
``grow_margin_m`` steps when the robot reaches new ground, so memory follows the mapped area, never the time.

**Static layer** (walls, racks, parked pallets): per cell a clamped log-odds (``+hit`` at a beam's endpoint, ``-miss``
in the cells a beam crossed, never within ``endpoint_guard_cells`` of its end) and a *sighting streak*: the time the
cell's current run of hits began, and the time of its last hit; a gap longer than ``max_gap_s`` starts a new streak.
**Persistence rule:** a cell enters the static layer when its log-odds reaches ``occupied_logodds`` *and* its streak
has lasted ``persist_s`` (5 s) where something appeared on ground seen free, ``new_persist_s`` (2.5 s) on unexplored
ground; it leaves when pass-through evidence drives its log-odds below 0. A forklift (2 m long, >= 1 m/s) covers a
cell for at most about 2 s and then clears it, so its streaks stay short; a wall, or a pallet put into a bay, keeps
being hit for as long as it is in view and is promoted; a pallet taken away is seen through and demoted. Nothing
enters the static layer from a single glimpse. The exception is the start (``bootstrap_s``): the first scan is the
map, and for 10 s unexplored cells need only ``bootstrap_persist_s``, so that the first map is dense while the pose
is still good (a forklift caught then may enter, and leaves once it is seen through).

**Wall footprints** (so that two flights draw the same cells): a hit within a static cell's footprint (half a
cell along its surface, a cell across it, around its mean hit point) is that cell's, not its own, and a beam sees a
static cell through only where it crosses the cell's surface (within 2.5 cells of its mean point) before its
guarded end. A wall on a cell boundary is sampled on both sides of it and grazing beams cross the cells beside it;
without these rules the cells along every wall flickered between flights (benchmarks/warehouse_flights.txt run 4).

**Dynamic layer** (forklifts, pallets not yet persistent): the time each cell was last hit by a point labelled
dynamic; its occupancy decays as ``exp(-age / dynamic_decay_s)`` (computed when asked: no per-scan sweep of the
grid), and a beam passing through a cell clears it at once.

**Labels** of a scan's points (:meth:`MapLayers.classify`): ``STATIC`` within ``dynamic_distance_m`` of the static
layer; ``DYNAMIC`` otherwise if its cell was known free (log-odds <= ``free_logodds``) now or when its current streak
began (something appeared where the robot had seen through); ``PENDING`` otherwise (unexplored ground: a wall seen
for the first time waits for its persistence).

**Localisation** (:meth:`MapLayers.match`): each static cell keeps the running mean of its hits (the map is finer
than its cells) and a normal fitted to its neighbours' means; a nearest-static-cell index (a distance transform,
refreshed only around cells that joined or left the layer) pairs every scan point with a cell by lookup, and
Gauss-Newton minimises point-to-line distances (point-to-point at uprights and corners), Cauchy-weighted, with the
odometry guess as a weak prior; dynamic points are left out by the caller. No KD-tree, no loop over points. (A plain
distance field to cell centres was tried first: half-cell quantisation biased the heading by ~3 mrad a match.)
**Loaded maps**: changes to them wait ``changed_persist_s`` (:mod:`slam2d.maps.layer_changes`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_positive
from slam2d.geometry import se2
from slam2d.maps.layer_changes import changed_mask, hold_removals, load_changes, saved_ages, track_changes
from slam2d.maps.layer_stats import LayerStats, PoseBuffer
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid

__all__ = ["DYNAMIC", "PENDING", "STATIC", "FieldMatch", "LayerStats", "LayersConfig", "MapLayers", "PoseBuffer"]

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
    new_persist_s: float = 2.5
    """a cell never seen free before (unexplored ground: a wall seen for the first time) needs a streak this long
    (s): longer than a forklift's side covers one cell (2 m long at >= 1 m/s), short enough that new walls join
    the map while the robot approaches them."""
    bootstrap_s: float = 10.0
    """for this long after the first scan, unexplored cells need only ``bootstrap_persist_s``: the first map is
    seen from one place (far walls sampled a beam width apart) and a scan matched against it drags a little; cells
    placed quickly, while the pose is still good, keep that early error from being built into the map (s)."""
    changed_persist_s: float = 28800.0
    """from a saved map, a change to it (a pallet put down where it saw free ground, one of its static cells seen
    through) reaches the static layer once it has lasted this long across flights: a shift, as pallets move daily
    (s; :mod:`slam2d.maps.layer_changes`). 30 min promoted pallets moved within a 44-min full-scale flight."""
    bootstrap_persist_s: float = 0.3
    """the streak an unexplored cell needs during ``bootstrap_s`` (s)."""
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
                       "persist_s", "new_persist_s", "changed_persist_s", "max_gap_s", "bootstrap_persist_s",
                       "bootstrap_s", "field_max_m", "dynamic_distance_m", "dynamic_decay_s", "match_cauchy_m",
                       "inlier_m", "grow_margin_m", "prior_sigma_xy_m", "prior_sigma_theta_rad", "range_sigma_m")
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

    # every per-cell array: fill value, dtype, trailing shape
    _FILL: ClassVar[dict[str, tuple[float | bool, type, tuple[int, ...]]]] = {
        "logodds": (0.0, np.float32, ()), "streak": (-np.inf, np.float32, ()), "last_hit": (-np.inf, np.float32, ()),
        "static": (False, bool, ()), "appeared": (False, bool, ()), "dyn_seen": (-np.inf, np.float32, ()),
        "mean": (0.0, np.float32, (2,)), "count": (0.0, np.float32, ()), "field": (np.inf, np.float32, ()),
        "nearest": (-1, np.int32, ()), "normal": (0.0, np.float32, (2,)), "line": (False, bool, ())}

    MEAN_CAP = 100.0
    logodds: NDArray[np.float32]
    streak: NDArray[np.float32]
    last_hit: NDArray[np.float32]
    static: NDArray[np.bool_]
    appeared: NDArray[np.bool_]
    dyn_seen: NDArray[np.float32]
    mean: NDArray[np.float32]
    count: NDArray[np.float32]
    field: NDArray[np.float32]
    nearest: NDArray[np.int32]
    normal: NDArray[np.float32]
    line: NDArray[np.bool_]
    changed_since: NDArray[np.float32]  # loaded maps only (slam2d.maps.layer_changes)
    prior_free: NDArray[np.bool_]
    removed_since: NDArray[np.float32]
    prior_static: NDArray[np.bool_]

    def __init__(self, config: LayersConfig | None = None) -> None:
        self.config = config or LayersConfig()
        self.origin = np.zeros(2)
        self.shape = (0, 0)
        # logodds, streak (time the cell's current run of hits began), last_hit, static, appeared (the current
        # streak began in a cell known free), dyn_seen (last time a dynamic point hit the cell), mean (mean hit
        # offset from the cell centre, m: the map is sub-cell accurate), count (hits in that mean, capped),
        # field (distance to the nearest static cell's mean point, m; inf beyond field_max_m), nearest (flat
        # index of that cell, -1: none), normal and line (its surface normal; line: matched point to line)
        self._fill = dict(self._FILL)  # a loaded map adds the change-tracking arrays (layer_changes.CHANGE_FILL)
        for name, (fill, dtype, trail) in self._fill.items():
            setattr(self, name, np.full((0, 0, *trail), fill, dtype=dtype))
        self.prior_map, self.last_time_s = False, 0.0
        self.pending_ages: dict[str, NDArray[np.float32]] | None = None
        self.integrations = 0
        self.started_s = 0.0
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
        if self.nearest.size:  # flat indices into the old grid -> into the new one
            r, c = np.divmod(self.nearest.astype(np.int64), self.shape[1])
            self.nearest = np.where(self.nearest >= 0, (r + off[1]) * shape[1] + c + off[0], -1).astype(np.int32)
        for name, (fill, dtype, trail) in self._fill.items():
            old = getattr(self, name)
            new: NDArray[Any] = np.full((*shape, *trail), fill, dtype=dtype)
            if old.size:
                new[off[1]:off[1] + old.shape[0], off[0]:off[0] + old.shape[1]] = old
            setattr(self, name, new)
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
        if self.prior_map:  # a change to the loaded map
            dyn |= inside & ~near & np.isfinite(self.changed_since.ravel()[flat])
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
        miss = np.zeros(0, np.int64)
        if n > 0:
            s = (np.arange(n) + 0.5) * res
            keep = s[None, :] < reach[:, None]
            u = d / np.maximum(r, 1e-9)[:, None]
            samples = pose[:2] + (u[:, None, :] * s[None, :, None])[keep]
            miss, ok = self.cell_index(samples)
            beam = np.broadcast_to(np.arange(len(sub))[:, None], keep.shape)[keep][ok]
            miss = miss[ok]
            on = st[miss]  # a static cell is seen through only where the beam crosses its surface point
            miss = np.concatenate([miss[~on], miss[on][self._crossed(pose[:2], d[beam[on]], miss[on])]])
            lo[miss] = np.maximum(lo[miss] - cfg.miss_logodds, cfg.min_logodds)
            gone = hold_removals(self, t, miss[st[miss] & (lo[miss] < 0.0)])  # loaded maps hold their own
            if gone.size:
                st[gone] = False
                self.demoted += int(np.unique(gone).size)
                self._mark_dirty(gone)
            self.dyn_seen.ravel()[miss] = -np.inf  # seen through: nothing there now
        # hits: evidence, sighting streaks, promotion
        hit, _ = self.cell_index(world)
        hit = self._snap(world, hit)
        track_changes(self, t, miss, hit)  # loaded maps only
        before = lo[hit]
        fresh = (t - last[hit]) > cfg.max_gap_s
        streak = self.streak.ravel()
        streak[hit[fresh]] = t
        self.appeared.ravel()[hit[fresh]] = before[fresh] <= cfg.free_logodds
        last[hit] = t
        lo[hit] = np.minimum(before + cfg.hit_logodds, cfg.max_logodds)
        if self.integrations == 0:
            self.started_s = float(time_s)
        new_need = cfg.bootstrap_persist_s if time_s - self.started_s < cfg.bootstrap_s else cfg.new_persist_s
        need = np.where(self.appeared.ravel()[hit], cfg.persist_s, new_need)
        ready = (lo[hit] >= cfg.occupied_logodds) & ((t - streak[hit]) >= need)
        if self.prior_map:  # a change to the loaded map waits for changed_persist_s
            ready &= (t - self.changed_since.ravel()[hit]) >= cfg.changed_persist_s
        new = hit[~st[hit] & (ready | bootstrap)]
        if new.size:
            st[new] = True
            self.promoted += int(np.unique(new).size)
            self._mark_dirty(new)
        self._update_means(world[lab != DYNAMIC], hit[lab != DYNAMIC])
        dyn = hit[lab == DYNAMIC]
        self.dyn_seen.ravel()[dyn] = t
        self.integrations += 1
        self._since_refresh += 1
        if self._dirty is not None and (bootstrap or self._since_refresh >= cfg.field_refresh_every):
            self.refresh_field()

    def _footprint(self, k: NDArray[np.int64], e: Array, across: float = 0.5) -> NDArray[np.bool_]:
        """Do offsets ``e`` (K,2) from static cells ``k``'s mean points lie within half a cell of them along the
        cell's surface and ``across`` cells across it (its normal; the grid axes where it is no line)?"""
        n = np.where(self.line.ravel()[k][:, None], self.normal.reshape(-1, 2)[k], [1.0, 0.0])
        res = self.resolution
        return (np.abs(np.sum(n * e, axis=1)) <= across * res) \
            & (np.abs(n[:, 0] * e[:, 1] - n[:, 1] * e[:, 0]) <= 0.5 * res)

    def _snap(self, world: Array, hit: NDArray[np.int64]) -> NDArray[np.int64]:
        """Hits within a static cell's footprint (:meth:`_footprint`) are that cell's, not their own: a wall on a
        cell boundary is sampled on both sides of it, and without this the cell behind the boundary joins the
        layer when the pose shifts by a centimetre (the static cells of two flights would differ along every
        wall)."""
        k = self.nearest.ravel()[hit].astype(np.int64)
        cand = (k >= 0) & ~self.static.ravel()[hit]
        if not cand.any():
            return hit
        kc = k[cand]
        snap = self._footprint(kc, world[cand] - self.cell_centres(kc) - self.mean.reshape(-1, 2)[kc], across=1.0)
        out = hit.copy()
        out[np.flatnonzero(cand)[snap]] = kc[snap]
        return out

    def _crossed(self, origin: Array, beam: Array, cells: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Do beams from ``origin`` along vectors ``beam`` (K,2) (to their endpoints) pass static ``cells``' (K,)
        surface before their guarded end: a line cell's line within 2.5 cells of its mean point, a point
        cell's mean within its footprint? A beam that runs along a wall, or through the cell behind a wall that
        lies on a cell boundary, meets the surface at its own endpoint: no evidence that the wall has gone."""
        m = self.cell_centres(cells) + self.mean.reshape(-1, 2)[cells]
        line = self.line.ravel()[cells]
        n = np.where(line[:, None], self.normal.reshape(-1, 2)[cells], 0.0)
        nd = np.sum(n * beam, axis=1)
        length = np.maximum(np.hypot(beam[:, 0], beam[:, 1]), 1e-12)
        t_line = np.sum(n * (m - origin), axis=1) / np.where(np.abs(nd) > 1e-12, nd, np.inf)
        t_point = np.sum(beam * (m - origin), axis=1) / length**2
        t = np.where(line, np.where(np.abs(nd) > 1e-12, t_line, np.inf), t_point)
        ok = (t > 0) & (t * length < length - (self.config.endpoint_guard_cells + 0.5) * self.resolution)
        e = origin + np.clip(t, 0, 1)[:, None] * beam - m
        along = np.abs(n[:, 0] * e[:, 1] - n[:, 1] * e[:, 0])
        return ok & np.where(line, along <= 2.5 * self.resolution, self._footprint(cells, e))

    def _update_means(self, world: Array, hit: NDArray[np.int64]) -> None:
        """Running mean of the hit points in each cell (the last ``MEAN_CAP`` hits weigh most)."""
        if not len(hit):
            return
        u, inv = np.unique(hit, return_inverse=True)
        off = world - self.cell_centres(hit)
        cnt = np.bincount(inv, minlength=len(u)).astype(np.float32)
        scan_mean = np.stack([np.bincount(inv, off[:, 0], len(u)), np.bincount(inv, off[:, 1], len(u))], -1) \
            / cnt[:, None]
        mean, count = self.mean.reshape(-1, 2), self.count.ravel()
        total = np.minimum(count[u] + cnt, self.MEAN_CAP)
        mean[u] += (scan_mean - mean[u]) * (cnt / total)[:, None]
        count[u] = total

    def _mark_dirty(self, flat: NDArray[np.int64]) -> None:
        r, c = np.divmod(flat, self.shape[1])
        d = self._dirty or [r.max(), c.max(), r.min(), c.min()]
        self._dirty = [int(min(r.min(), d[0])), int(min(c.min(), d[1])),
                       int(max(r.max(), d[2])), int(max(c.max(), d[3]))]

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
            _, (ir, ic) = distance_transform_edt(~occ, return_indices=True)
            near = ((ir + e0) * nx + ic + f0)[a0 - e0:a1 - e0, b0 - f0:b1 - f0].astype(np.int64)
            rows, cols = np.mgrid[a0:a1, b0:b1]
            centre = self.origin + (np.stack([cols, rows], axis=-1) + 0.5) * self.resolution
            d = np.linalg.norm(self.cell_centres(near.ravel()).reshape(*near.shape, 2)
                               + self.mean.reshape(-1, 2)[near] - centre, axis=-1)
            self.field[a0:a1, b0:b1] = np.where(d <= fm, d, np.inf)
            self.nearest[a0:a1, b0:b1] = np.where(d <= fm, near, -1)
        else:
            self.field[a0:a1, b0:b1] = np.inf
            self.nearest[a0:a1, b0:b1] = -1
        self._fit_normals(e0, f0, e1, f1)

    def _fit_normals(self, r0: int, c0: int, r1: int, c1: int) -> None:
        """Surface normal of every static cell in rows r0:r1, columns c0:c1, from the mean points of the static
        cells within four cells of it (far from the sensor one scan samples a wall a beam width apart): a line when
        the spread across is under a fifth of the spread along (variance ratio 0.04)."""
        r, c = np.nonzero(self.static[r0:r1, c0:c1])
        if not len(r):
            return
        r, c = r + r0, c + c0
        ny, nx = self.shape
        res = self.resolution
        sums = np.zeros((6, len(r)))  # n, x, y, xx, xy, yy (relative to the cell's centre)
        for dr in range(-4, 5):
            for dc in range(-4, 5):
                rr, cc = r + dr, c + dc
                ok = (rr >= 0) & (rr < ny) & (cc >= 0) & (cc < nx)
                rr, cc = np.where(ok, rr, 0), np.where(ok, cc, 0)
                ok &= self.static[rr, cc]
                px = np.where(ok, dc * res + self.mean[rr, cc, 0], 0.0)
                py = np.where(ok, dr * res + self.mean[rr, cc, 1], 0.0)
                sums += np.stack([ok, px, py, px * px, px * py, py * py])
        n = np.maximum(sums[0], 1.0)
        mx, my = sums[1] / n, sums[2] / n
        a, b, d = sums[3] / n - mx * mx, sums[4] / n - mx * my, sums[5] / n - my * my
        phi = 0.5 * np.arctan2(2 * b, a - d)  # direction of the larger spread
        root = np.sqrt(0.25 * (a - d) ** 2 + b * b)
        lam_max, lam_min = 0.5 * (a + d) + root, 0.5 * (a + d) - root
        self.normal[r, c] = np.stack([-np.sin(phi), np.cos(phi)], axis=-1)
        self.line[r, c] = (sums[0] >= 3) & (lam_min < 0.04 * np.maximum(lam_max, 1e-12))

    # ------------------------------------------------------------------ localisation
    def match(self, points: ArrayLike, guess: ArrayLike) -> FieldMatch:
        """Align robot-frame points (N,2) to the static layer from ``guess`` (Gauss-Newton, Cauchy-weighted, with
        the guess as a prior): each point is paired with the mean hit point of the static cell nearest to it
        (a lookup, no search) and pulled along that cell's normal (point to line), or in both axes where the cell
        is not part of a line (an upright). Points farther than ``field_max_m`` from the layer pull nothing."""
        cfg = self.config
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        g = np.asarray(guess, dtype=np.float64)
        x = g.copy()
        prior = np.diag([cfg.prior_sigma_xy_m**-2, cfg.prior_sigma_xy_m**-2, cfg.prior_sigma_theta_rad**-2])
        scale = cfg.range_sigma_m**-2
        near_all, mean_all = self.nearest.ravel(), self.mean.reshape(-1, 2)
        normal_all, line_all = self.normal.reshape(-1, 2), self.line.ravel()
        h = np.zeros((3, 3))
        dist = np.full(len(p), np.inf)
        it = 0
        for it in range(1, cfg.match_iterations + 1):  # noqa: B007 - iteration count is reported
            c, s = np.cos(x[2]), np.sin(x[2])
            q = np.stack([c * p[:, 0] - s * p[:, 1] + x[0], s * p[:, 0] + c * p[:, 1] + x[1]], axis=-1)
            flat, inside = self.cell_index(q) if self.shape[0] else (np.zeros(len(p), np.int64),
                                                                       np.zeros(len(p), bool))
            k = np.where(inside, near_all[flat], -1)
            ok = k >= 0
            k = np.where(ok, k, 0)
            e = q - (self.cell_centres(k) + mean_all[k])  # (N,2) point minus its target
            dist = np.where(ok, np.hypot(e[:, 0], e[:, 1]), np.inf)
            ok &= dist < cfg.field_max_m
            line = line_all[k]
            a1 = np.where(line[:, None], normal_all[k], [1.0, 0.0])  # residual directions
            a2 = np.where(line[:, None], 0.0, np.array([0.0, 1.0]))
            dq = np.stack([-s * p[:, 0] - c * p[:, 1], c * p[:, 0] - s * p[:, 1]], axis=-1)  # d q / d theta
            r1, r2 = np.sum(a1 * e, axis=1), np.sum(a2 * e, axis=1)
            w = np.where(ok, 1.0 / (1.0 + (dist / cfg.match_cauchy_m) ** 2), 0.0)
            j1 = np.concatenate([a1, np.sum(a1 * dq, axis=1, keepdims=True)], axis=1)
            j2 = np.concatenate([a2, np.sum(a2 * dq, axis=1, keepdims=True)], axis=1)
            h = scale * ((j1 * w[:, None]).T @ j1 + (j2 * w[:, None]).T @ j2)
            err = x - g
            err[2] = float(np.arctan2(np.sin(err[2]), np.cos(err[2])))
            b = scale * ((j1 * w[:, None]).T @ r1 + (j2 * w[:, None]).T @ r2) + prior @ err
            try:
                dx = -np.linalg.solve(h + prior, b)
            except np.linalg.LinAlgError:
                break
            x = x + dx
            x[2] = float(np.arctan2(np.sin(x[2]), np.cos(x[2])))
            if np.hypot(dx[0], dx[1]) < 1e-4 and abs(dx[2]) < 1e-5:
                break
        inl = int(np.count_nonzero(dist < cfg.inlier_m))
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
        out = np.where(np.isfinite(self.dyn_seen), out, 0).astype(np.float32)
        return np.where(changed_mask(self), np.float32(1.0), out) if self.prior_map else out

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

    # ------------------------------------------------------------------ saved maps
    #: the named arrays of a saved static layer (``MapSnapshot.layers``)
    SAVED = ("static_frame", "static_logodds", "static_mask", "static_mean")

    def saved(self) -> dict[str, NDArray[Any]]:
        """The static layer as named arrays for a saved map: frame [x0, y0, cell size], log-odds, membership, and
        each cell's mean hit point (the sub-cell map the matcher pulls towards); from a loaded map, the ages of open
        changes. The sighting streaks and the decaying dynamic layer are not kept: they describe one flight."""
        return {"static_frame": np.array([self.origin[0], self.origin[1], self.resolution]),
                "static_logodds": self.logodds.copy(), "static_mask": self.static.copy(),
                "static_mean": self.mean.copy(), **saved_ages(self)}

    @classmethod
    def from_saved(cls, config: LayersConfig | None, arrays: Mapping[str, NDArray[Any]]) -> MapLayers:
        """Layers whose static layer is a saved one (:meth:`saved`), ready to localise against (no bootstrap; changes
        to it are tracked). ValueError when an array is missing or the cell size differs from ``config``'s."""
        lay = cls(config)
        missing = [n for n in cls.SAVED if n not in arrays]
        if missing:
            raise ValueError(f"MapLayers.from_saved: the map has no saved static layer (missing {missing}); it was "
                             "not made by a lifelong session")
        frame = np.asarray(arrays["static_frame"], dtype=np.float64)
        lo, mask = np.asarray(arrays["static_logodds"]), np.asarray(arrays["static_mask"])
        mean = np.asarray(arrays["static_mean"])
        if frame.shape != (3,) or not np.all(np.isfinite(frame)) or lo.ndim != 2 or mask.shape != lo.shape \
                or mean.shape != (*lo.shape, 2) or mask.dtype != np.bool_:
            raise ValueError("MapLayers.from_saved: inconsistent static-layer arrays")
        if not np.isclose(frame[2], lay.resolution, rtol=0, atol=1e-12):
            raise ValueError(f"MapLayers.from_saved: the saved layer has {frame[2]:g} m cells, the config "
                             f"{lay.resolution:g} m (LayersConfig.resolution_m)")
        lay.origin, lay.shape = frame[:2].copy(), (int(lo.shape[0]), int(lo.shape[1]))
        for name, (fill, dtype, trail) in cls._FILL.items():
            setattr(lay, name, np.full((*lay.shape, *trail), fill, dtype=dtype))
        lay.logodds[:] = lo
        lay.static[:] = mask
        lay.mean[:] = mean
        load_changes(lay, arrays)
        lay.count[mask] = 10.0  # settled means: new hits still move them, a few hits do not overwrite them
        lay.integrations, lay.started_s = 1, -np.inf  # not a first scan, and past the bootstrap
        if mask.any():
            lay._dirty = [0, 0, lay.shape[0] - 1, lay.shape[1] - 1]
            lay.refresh_field()
        return lay

    def nbytes(self) -> int:
        """Bytes held by the grids."""
        return sum(getattr(self, n).nbytes for n in self._fill)
