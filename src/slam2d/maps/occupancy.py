"""Log-odds occupancy grid with an inverse sensor model, vectorised ray casting, clamping and decay.

Cell ``(i, j)`` covers ``x in [x0 + j*res, x0 + (j+1)*res)``, ``y in [y0 + i*res, y0 + (i+1)*res)``: row index is y,
column index is x, so ``grid.logodds`` displays upright with ``origin="lower"``.

Inverse sensor model (the classic one from Probabilistic Robotics ch. 9, in log-odds form): every cell a beam passes
through before its endpoint gets ``logodds_free``; the cell holding the endpoint of a beam that hit something gets
``logodds_occupied``; a no-return beam (NaN, inf, <= 0 or >= max range) clears cells up to ``free_range_cap_m`` and
marks nothing. Each cell is updated at most once per scan, and a hit wins over a pass-through in the same scan (a
wall cell is often crossed by grazing neighbour beams). Values are clamped to ``[logodds_min, logodds_max]`` so the
map can still change when the world does.

Ray casting is done for all beams at once: points are sampled along every beam at half-cell spacing (one
``np.repeat``/``arange`` construction, no loop over beams), turned into flat cell indices, and de-duplicated.

Decay: after each update, cells that the scan did NOT observe move toward "unknown" (log-odds 0) by the factor
``1 - decay_per_update``; a forklift that drove away fades from the map even where no beam sees the floor it left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_nonnegative, check_positive
from slam2d.geometry import se2

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class OccupancyConfig:
    """Grid geometry and inverse sensor model."""

    resolution_m: float = 0.1
    """cell side (m)."""
    logodds_occupied: float = 0.85
    """log-odds added to the endpoint cell of a beam that hit (p=0.7)."""
    logodds_free: float = -0.4
    """log-odds added to cells a beam passed through (p=0.4)."""
    logodds_min: float = -2.0
    """lower clamp (p=0.12): keeps free cells able to become occupied again."""
    logodds_max: float = 3.5
    """upper clamp (p=0.97)."""
    decay_per_update: float = 0.0
    """fraction of their log-odds that cells not observed in an update lose (0: no decay; 1: forget at once)."""
    sample_step_cells: float = 0.5
    """spacing of the free-space samples along a beam, in cells (0.5 visits every crossed cell but corner clips; 1.0
    is twice as fast and skips some diagonal cells)."""
    free_range_cap_m: float = 10.0
    """no-return beams clear free space only up to this range (m); 0: they clear nothing."""
    occupied_threshold: float = 0.65
    """probability above which a cell counts as occupied (and below 1 - this as free) when classifying."""

    def __post_init__(self) -> None:
        check_positive(self, "resolution_m", "logodds_occupied", "logodds_max", "sample_step_cells")
        check_nonnegative(self, "free_range_cap_m")
        check_nonnegative(self, "decay_per_update")
        if not self.logodds_free < 0:
            raise ValueError(f"OccupancyConfig.logodds_free must be < 0 (got {self.logodds_free})")
        if not self.logodds_min < 0:
            raise ValueError(f"OccupancyConfig.logodds_min must be < 0 (got {self.logodds_min})")
        if self.decay_per_update > 1:
            raise ValueError(f"OccupancyConfig.decay_per_update must be in [0, 1] (got {self.decay_per_update})")
        if not 0.5 <= self.occupied_threshold < 1:
            raise ValueError(f"OccupancyConfig.occupied_threshold must be in [0.5, 1) (got {self.occupied_threshold})")


def beam_samples(pose: ArrayLike, ranges: ArrayLike, angles: ArrayLike, max_range: float, step_m: float,
                 free_cap_m: float) -> tuple[Array, Array]:
    """World points sampled along every beam (free space) and the endpoints of beams that hit.

    Shapes: pose (3,), ranges (B,), angles (B,) -> free points (F,2), hit points (H,2). Free samples stop half a
    step before the endpoint so the endpoint cell is not cleared by its own beam.
    """
    pose = np.asarray(pose, dtype=np.float64)
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64) + pose[2]
    hit = np.isfinite(r) & (r > 0) & (r < max_range)
    free_len = np.where(hit, r - 0.5 * step_m, np.minimum(max_range, free_cap_m))
    free_len = np.clip(np.nan_to_num(free_len, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
    n = np.floor(free_len / step_m).astype(np.int64) + 1  # samples per beam, including the origin
    n = np.where(free_len > 0, n, 0)
    beam = np.repeat(np.arange(len(r)), n)
    # position of each sample inside its beam: 0, 1, ..., n_b - 1 without a loop over beams
    starts = np.cumsum(n) - n
    k = np.arange(int(n.sum())) - np.repeat(starts, n)
    d = k * step_m
    c, s = np.cos(a), np.sin(a)
    free = np.stack([pose[0] + d * c[beam], pose[1] + d * s[beam]], axis=-1)
    hits = np.stack([pose[0] + r[hit] * c[hit], pose[1] + r[hit] * s[hit]], axis=-1)
    return free, hits


class OccupancyGrid:
    """A log-odds grid over a fixed rectangle. ``logodds`` has shape (rows, cols) = (ny, nx)."""

    def __init__(self, bounds: tuple[float, float, float, float], config: OccupancyConfig | None = None) -> None:
        self.config = config or OccupancyConfig()
        x0, y0, x1, y1 = (float(v) for v in bounds)
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"OccupancyGrid bounds must have xmax > xmin and ymax > ymin (got {bounds})")
        res = self.config.resolution_m
        self.origin = np.array([x0, y0])
        rows, cols = (y1 - y0) / res, (x1 - x0) / res
        # the cell count in floats first, so that bounds of 1e300 m give a short message, not a 300-digit shape
        if not (math.isfinite(rows * cols) and math.ceil(rows) * math.ceil(cols) <= 50_000_000):
            raise ValueError(f"OccupancyGrid of {rows:.3g} x {cols:.3g} cells (bounds {x1 - x0:.3g} x {y1 - y0:.3g} "
                             f"m at {res} m) is too large (50 million at most); raise resolution_m")
        self.shape = (math.ceil(rows), math.ceil(cols))
        self.logodds = np.zeros(self.shape, dtype=np.float64)
        self.observed = np.zeros(self.shape, dtype=bool)
        self.updates = 0

    @classmethod
    def around(cls, points: ArrayLike, margin_m: float, config: OccupancyConfig | None = None) -> OccupancyGrid:
        """A grid covering ``points`` (K,2) plus a margin on every side."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        lo, hi = p.min(axis=0) - margin_m, p.max(axis=0) + margin_m
        return cls((lo[0], lo[1], hi[0], hi[1]), config)

    @property
    def resolution(self) -> float:
        return self.config.resolution_m

    def cell_index(self, xy: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Flat cell indices of points and whether each lies inside the grid. Shapes: (K,2) -> (K,), (K,)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        ij = np.floor((p - self.origin) / self.resolution).astype(np.int64)  # columns: x index, y index
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < self.shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < self.shape[0])
        flat = np.where(inside, ij[:, 1] * self.shape[1] + ij[:, 0], 0)
        return flat, inside

    def cell_centres(self) -> tuple[Array, Array]:
        """x (cols,) and y (rows,) of the cell centres."""
        r = self.resolution
        return (self.origin[0] + (np.arange(self.shape[1]) + 0.5) * r,
                self.origin[1] + (np.arange(self.shape[0]) + 0.5) * r)

    def update(self, pose: ArrayLike, ranges: ArrayLike, angles: ArrayLike, max_range: float) -> None:
        """Integrate one scan taken at ``pose``. Shapes: pose (3,), ranges (B,), angles (B,)."""
        cfg = self.config
        free_pts, hit_pts = beam_samples(pose, ranges, angles, max_range, cfg.sample_step_cells * self.resolution,
                                         cfg.free_range_cap_m)
        hf, hin = self.cell_index(hit_pts)
        ff, fin = self.cell_index(free_pts)
        hit_idx, free_idx = hf[hin], ff[fin]
        flat = self.logodds.reshape(-1)
        seen = self.observed.reshape(-1)
        if cfg.decay_per_update > 0:
            keep = np.zeros(flat.shape, dtype=bool)
            keep[hit_idx] = True
            keep[free_idx] = True
            flat[~keep] *= 1.0 - cfg.decay_per_update
        before_hit = flat[hit_idx]
        # ``a[i] = a[i] + v`` reads every element before writing, so a cell listed many times is updated ONCE per
        # scan, without sorting the (long) sample list; the hit cells are then set from their pre-scan values
        # so that a hit wins over pass-throughs in the same scan
        flat[free_idx] = np.maximum(flat[free_idx] + cfg.logodds_free, cfg.logodds_min)
        flat[hit_idx] = np.minimum(before_hit + cfg.logodds_occupied, cfg.logodds_max)
        seen[hit_idx] = True
        seen[free_idx] = True
        self.updates += 1

    def integrate(self, poses: ArrayLike, ranges: ArrayLike, angles: ArrayLike, max_range: float) -> None:
        """Integrate scans in order. Shapes: poses (S,3), ranges (S,B), angles (B,)."""
        poses = np.asarray(poses, dtype=np.float64)
        ranges = np.asarray(ranges, dtype=np.float64)
        for p, r in zip(poses, ranges, strict=True):
            self.update(p, r, angles, max_range)

    def probability(self) -> Array:
        """Occupancy probability per cell (0.5 = unknown)."""
        return 1.0 / (1.0 + np.exp(-self.logodds))

    def occupied(self) -> NDArray[np.bool_]:
        """Cells whose probability exceeds ``occupied_threshold``."""
        t = self.config.occupied_threshold
        return self.logodds > np.log(t / (1 - t)) if t > 0.5 else self.logodds > 0

    def free(self) -> NDArray[np.bool_]:
        """Cells whose probability is below ``1 - occupied_threshold``."""
        t = self.config.occupied_threshold
        return self.logodds < -np.log(t / (1 - t)) if t > 0.5 else self.logodds < 0

    def occupied_points(self) -> Array:
        """Centres of occupied cells, (K,2)."""
        i, j = np.nonzero(self.occupied())
        return self.origin + (np.stack([j, i], axis=-1) + 0.5) * self.resolution

    def image(self) -> NDArray[np.uint8]:
        """8-bit grey image, row 0 = lowest y: 0 occupied ... 255 free, 128 unknown (flip rows to display)."""
        return np.round(255.0 * (1.0 - self.probability())).astype(np.uint8)


def rasterize_segments(grid: OccupancyGrid, segments: ArrayLike) -> NDArray[np.bool_]:
    """Cells of ``grid`` that the segments (W,4) [x0,y0,x1,y1] pass through (sampled at a quarter cell)."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    out = np.zeros(grid.shape, dtype=bool)
    if len(seg) == 0:
        return out
    lengths = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    n = np.ceil(lengths / (0.25 * grid.resolution)).astype(np.int64) + 1
    idx = np.repeat(np.arange(len(seg)), n)
    t = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(np.maximum(n - 1, 1), n)
    pts = seg[idx, :2] + t[:, None] * (seg[idx, 2:] - seg[idx, :2])
    flat, inside = grid.cell_index(pts)
    out.reshape(-1)[flat[inside]] = True
    return out


@dataclass(frozen=True)
class GridAccuracy:
    """Comparison of a grid with a ground-truth wall map over the cells the grid observed."""

    cell_accuracy: float
    """fraction of observed cells whose class (occupied / not) equals the truth."""
    occupied_precision: float
    """occupied cells within ``tolerance_cells`` of a true wall cell / occupied cells."""
    occupied_recall: float
    """observed true wall cells with an occupied cell within ``tolerance_cells`` / observed true wall cells."""
    observed_cells: int
    tolerance_cells: int


def compare_with_walls(grid: OccupancyGrid, segments: ArrayLike, tolerance_cells: int = 1) -> GridAccuracy:
    """Score ``grid`` against the true walls: cell accuracy plus occupied precision/recall with a cell tolerance."""
    from scipy.ndimage import binary_dilation

    truth = rasterize_segments(grid, segments)
    occ = grid.occupied()
    obs = grid.observed
    acc = float(np.mean(occ[obs] == truth[obs])) if obs.any() else 0.0
    st = np.ones((2 * tolerance_cells + 1,) * 2, dtype=bool)
    truth_d = binary_dilation(truth, st) if tolerance_cells else truth
    occ_d = binary_dilation(occ, st) if tolerance_cells else occ
    prec = float(np.mean(truth_d[occ])) if occ.any() else 0.0
    seen_truth = truth & binary_dilation(obs, st)
    rec = float(np.mean(occ_d[seen_truth])) if seen_truth.any() else 0.0
    return GridAccuracy(acc, prec, rec, int(obs.sum()), tolerance_cells)


def transform_scan_points(pose: ArrayLike, ranges: ArrayLike, angles: ArrayLike, max_range: float) -> Array:
    """World coordinates of the endpoints of beams that hit. Shapes: (3,),(B,),(B,) -> (K,2)."""
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    ok = np.isfinite(r) & (r > 0) & (r < max_range)
    return se2.transform_points(pose, np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=-1))


def wall_thickness_cells(grid: OccupancyGrid, min_component_cells: int = 20) -> Array:
    """Local thickness of the occupied structures, in cells, sampled along their skeleton.

    For every skeleton cell of each occupied component with at least ``min_component_cells`` cells (walls, not
    specks): ``2 * d - 1`` with ``d`` the Euclidean distance (in cells) to the nearest non-occupied cell. One- and
    two-cell walls give 1, three/four-cell walls 3, and so on; walls built from misaligned scans are thick.
    Shape: (K,) one value per skeleton cell.
    """
    from scipy import ndimage
    from skimage.morphology import skeletonize

    occ = grid.occupied()
    lab, n = ndimage.label(occ, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return np.zeros(0)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    keep = (sizes >= min_component_cells)[lab] & occ
    dist = ndimage.distance_transform_edt(occ)
    skel = np.asarray(skeletonize(keep), dtype=bool)
    return np.asarray(2.0 * dist[skel] - 1.0, dtype=np.float64)


def grid_from_scans(poses: ArrayLike, ranges: ArrayLike, angles: ArrayLike, max_range: float, *,
                    resolution_m: float = 0.05, min_motion_m: float = 0.3, min_turn_rad: float = 0.25) -> OccupancyGrid:
    """The occupancy map of any trajectory over a scan log: the scans taken after the pose moved ``min_motion_m``
    or turned ``min_turn_rad`` since the last one used (the scans in between add little and cost time), at their
    poses; no-return beams clear nothing (through windows and doors they would paint fans of free space outside).

    Shapes: poses (S,3) one per scan, ranges (S,B), angles (B,).
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(ranges, dtype=np.float64)
    if len(p) == 0 or len(p) != len(r):
        raise ValueError(f"grid_from_scans: need one pose per scan (got {len(p)} poses, {len(r)} scans)")
    keep = [0]
    for k in range(1, len(p)):  # a scalar test per scan, like keyframe selection
        d = se2.between(p[keep[-1]], p[k])
        if np.hypot(d[0], d[1]) >= min_motion_m or abs(d[2]) >= min_turn_rad:
            keep.append(k)
    sel = np.asarray(keep)
    pts = np.vstack([transform_scan_points(p[k], r[k], angles, max_range) for k in sel.tolist()] + [p[:, :2]])
    grid = OccupancyGrid.around(pts, 1.0, OccupancyConfig(resolution_m=resolution_m, free_range_cap_m=0.0))
    grid.integrate(p[sel], r[sel], angles, max_range)
    return grid
