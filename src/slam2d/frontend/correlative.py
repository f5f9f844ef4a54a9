"""Correlative scan matching (Olson 2009): exhaustive search of a pose window against a likelihood grid, with a
coarse-to-fine branch and bound.

The target points are rasterised into a grid whose cells hold ``exp(-d^2 / 2 sigma^2)``, ``d`` the distance to the
nearest target point (one Euclidean distance transform). A candidate pose scores the mean of that likelihood at the
moved source points. The search is exhaustive over a window of translations and rotations, so it cannot get stuck in
a local minimum the way ICP can, and it sees every competing alignment, which is what tells a unique match from
one of several identical corridors or aisles (:attr:`CorrelativeMatch.ambiguity`).

Coarse-to-fine: a second grid holds, in every cell, the maximum of the likelihood over the ``coarse_cells`` x
``coarse_cells`` block of fine cells starting there, so a coarse candidate's score bounds the score of every fine
translation inside its block (Olson's multi-resolution bound; the bound is exact in translation, approximate in
rotation). Coarse candidates are refined best-first and the search stops when the next coarse bound falls below the
best fine score. Every level is one array operation over all candidate poses: shape (angles, points, ny, nx).
"""

from __future__ import annotations

import functools
from collections.abc import Generator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from slam2d.config import check_positive

Array = NDArray[np.float64]
T = TypeVar("T")


@dataclass(frozen=True, slots=True, kw_only=True)
class CorrelativeConfig:
    """Search window, grid and likelihood settings."""

    resolution_m: float = 0.05
    """fine grid cell (m)."""
    sigma_m: float = 0.1
    """spread of the likelihood around target points (m); two cells, so that the cell a point falls in matters
    less than the distance to the target (at one cell, noise straddling a cell border outweighed a 5 cm offset)."""
    coarse_cells: int = 4
    """a coarse translation step is this many fine cells."""
    window_xy_m: float = 1.0
    """translations searched: +- this around the initial guess, in x and in y (m)."""
    window_theta_rad: float = 0.3
    """rotations searched: +- this around the initial guess (rad)."""
    coarse_theta_step_rad: float = 0.02
    """rotation step of the coarse search (rad)."""
    fine_theta_step_rad: float = 0.005
    """rotation step of the fine search (rad)."""
    max_refined: int = 8
    """at most this many coarse candidates are refined (best first)."""
    ambiguity_radius_m: float = 0.4
    """a competing alignment must differ from the best by more than this in translation ..."""
    ambiguity_angle_rad: float = 0.15
    """... or by more than this in rotation (rad)."""
    ambiguity_peaks: bool = False
    """count only competing alignments that are peaks of their own (a coarse score no lower than its neighbours'
    in angle, x and y): in a corridor whose end or doors pin the match, the scores fall off along the axis from
    the winner without another peak, and the coarse ratio is still near 1 at 0.4 m (False: every far alignment)."""

    def __post_init__(self) -> None:
        check_positive(self, "resolution_m", "sigma_m", "window_xy_m", "window_theta_rad", "coarse_theta_step_rad",
                       "fine_theta_step_rad", "ambiguity_radius_m", "ambiguity_angle_rad")
        if self.coarse_cells < 1 or self.max_refined < 1:
            raise ValueError("CorrelativeConfig.coarse_cells and max_refined must be >= 1")


@dataclass(frozen=True)
class CorrelativeMatch:
    """Best pose ``T_target_source`` (3,), its fine score in [0, 1], and the best coarse score of an alignment
    farther than the ambiguity radius / angle from it, divided by the best coarse score (``ambiguity``: near 1 when
    another alignment fits as well, e.g. a parallel aisle or a corridor's axis)."""

    transform: Array
    score: float
    ambiguity: float
    evaluated: int


@dataclass(frozen=True)
class _Grids:
    """The fine and coarse likelihood grids, flattened with a zero border of ``pad`` cells on every side, so that a
    point moved by any offset of the search window indexes a zero cell instead of needing a bounds check."""

    fine: NDArray[np.float32]
    coarse: NDArray[np.float32]
    lo: Array
    shape: tuple[int, int]
    pad: int
    first: tuple[int, int] = (0, 0)
    """(x, y) index, on the lattice of ``lo``, of the grid's first cell (a crop of a larger grid)."""


def _likelihood(points: Array, lo: Array, shape: tuple[int, int], cfg: CorrelativeConfig, pad: int,
                first: tuple[int, int] = (0, 0)) -> _Grids:
    res = cfg.resolution_m
    occ = np.ones(shape, dtype=bool)
    ij = np.floor((points - lo) / res).astype(np.int64) - np.asarray(first, dtype=np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[0])
    occ[ij[inside, 1], ij[inside, 0]] = False
    # squared distance in cells (an integer) to the nearest target point, then the likelihood from a table of its
    # values: the same numbers as exp(-d^2 / 2 sigma^2) of the distance transform, without an exp per cell
    near = ndimage.distance_transform_edt(occ, return_distances=False, return_indices=True)
    dy = near[0] - np.arange(shape[0], dtype=near.dtype)[:, None]
    dx = near[1] - np.arange(shape[1], dtype=near.dtype)[None, :]
    d2 = dy * dy + dx * dx
    table = _likelihood_table(res, cfg.sigma_m)
    ny, nx = shape
    c = cfg.coarse_cells
    pad = max(pad, c)  # the coarse maxima below read c - 1 cells past the grid
    fine = np.zeros((ny + 2 * pad, nx + 2 * pad), dtype=np.float32)
    fine[pad:pad + ny, pad:pad + nx] = table[np.minimum(d2, len(table) - 1)]
    # coarse: the max over the block [i, i+c) x [j, j+c) of fine cells, as c shifted maxima along each axis (the
    # zero border is the 0 outside the grid)
    rows = fine[pad:pad + ny, pad:pad + nx + c - 1].copy()
    for k in range(1, c):
        np.maximum(rows, fine[pad + k:pad + k + ny, pad:pad + nx + c - 1], out=rows)
    coarse = np.zeros_like(fine)
    block = coarse[pad:pad + ny, pad:pad + nx]
    block[...] = rows[:, :nx]
    for k in range(1, c):
        np.maximum(block, rows[:, k:k + nx], out=block)
    return _Grids(fine.ravel(), coarse.ravel(), lo, shape, pad, first)


@functools.lru_cache(maxsize=8)
def _likelihood_table(res: float, sigma: float) -> NDArray[np.float32]:
    """exp(-d^2 / 2 sigma^2) as float32 for d = sqrt(k) cells, k = 0, 1, ... up to the first k where it is 0 (at
    ``_ZERO_SIGMAS`` sigma at the latest): every squared distance beyond reads that last 0."""
    k = np.arange(int(np.ceil((_ZERO_SIGMAS * sigma / res) ** 2)) + 1)
    d = np.sqrt(k.astype(np.float64)) * res
    table = np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)
    table = table[: np.flatnonzero(table == 0)[0] + 1]  # 0 in float32 at _ZERO_SIGMAS sigma: exp(-112.5) < 1e-45
    table.flags.writeable = False
    return table


def _scores(grid: NDArray[np.float32], g: _Grids, pts: Array, thetas: Array, origin: Array, off_x: NDArray[np.int64],
            off_y: NDArray[np.int64], res: float) -> Array:
    """Mean grid value of ``pts`` rotated by each theta and moved by ``origin`` (m) plus each (off_y, off_x) cells,
    for B blocks of angles and offsets at once.

    Shapes: pts (N,2), thetas (B,A), origin (2,), offsets (B,X), (B,Y) -> (B, A, Y, X). Offsets are whole cells, so
    a point's cell is found once per angle and every offset is an index shift (one gather of B*A*N*Y*X values).
    """
    ny, nx = g.shape
    p = g.pad
    width = nx + 2 * p
    nb, na = thetas.shape
    th = thetas.ravel()
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    x = c * pts[None, :, 0] - s * pts[None, :, 1] + (origin[0] - g.lo[0])  # (B*A,N)
    y = s * pts[None, :, 0] + c * pts[None, :, 1] + (origin[1] - g.lo[1])
    bx = np.floor(x / res).astype(np.int64) - g.first[0]
    by = np.floor(y / res).astype(np.int64) - g.first[1]
    reach = max(int(np.abs(off_x).max()), int(np.abs(off_y).max()))
    # a point whose every offset lands outside the grid reads the zero corner of the border (one that some offset
    # brings back reads the zero border itself: the same 0)
    far = (bx < -reach) | (bx >= nx + reach) | (by < -reach) | (by >= ny + reach)
    bx[far] = reach - p
    by[far] = reach - p
    base = ((by + p) * width + (bx + p)).astype(np.int32).reshape(nb, na, 1, -1)  # (B,A,1,N)
    off = (off_y[:, :, None] * width + off_x[:, None, :]).astype(np.int32).reshape(nb, 1, -1, 1)  # (B,1,Y*X,1)
    vals = np.take(grid, base + off)  # (B, A, Y*X, N)
    out = vals.sum(axis=-1, dtype=np.float64) / len(pts)
    return np.asarray(out.reshape(nb, na, off_y.shape[1], off_x.shape[1]), dtype=np.float64)


#: beyond this many sigma from every target point the likelihood is exactly 0 in float32 (exp(-112) < 1e-45)
_ZERO_SIGMAS = 15.0


def _max_cos(a0: Array, a1: Array) -> Array:
    """The largest cosine over each angle interval [a0, a1] (a0 <= a1): 1 where it holds a multiple of 2 pi, else
    the larger end."""
    full = np.floor(a1 / (2 * np.pi)) >= np.ceil(a0 / (2 * np.pi))
    return np.where(full, 1.0, np.maximum(np.cos(a0), np.cos(a1)))


def _reachable(src: Array, g: Array, lo: Array, shape: tuple[int, int],
               cfg: CorrelativeConfig) -> tuple[tuple[int, int], tuple[int, int]]:
    """The cells (shape, first cell) of the target's grid that matter: those a source point can reach at any pose
    of the window, plus a border where the likelihood is already zero. The grid's cost (distance transform, maximum
    filter) follows its area, and a local map of long corridors spans far more than one scan can reach; values in
    the reachable cells are the same as on the whole grid (same lattice, same nearby points). The reach is each
    point's exact extent over the window's rotations (the arc's ends, or the axis it crosses), not a sweep added on
    every side: for a 25 m scan turned by +- 0.5 rad that sweep alone was 12.5 m on each side."""
    res = cfg.resolution_m
    step = cfg.coarse_cells * res  # the search's farthest offset and angle (a coarse step past the window)
    shift = (np.ceil(cfg.window_xy_m / step) + 1) * step + 2 * res
    turn = (np.ceil(cfg.window_theta_rad / cfg.coarse_theta_step_rad) + 1) * cfg.coarse_theta_step_rad
    r = np.hypot(src[:, 0], src[:, 1])
    a0 = np.arctan2(src[:, 1], src[:, 0]) + (g[2] - turn)
    a1 = a0 + 2 * turn

    def farthest(direction: float) -> float:  # the farthest any point gets along the unit vector at ``direction``
        return float(np.max(r * _max_cos(a0 - direction, a1 - direction)))

    lo_xy = -np.array([farthest(np.pi), farthest(-np.pi / 2)])  # x = r cos(a), y = r cos(a - pi/2)
    hi_xy = np.array([farthest(0.0), farthest(np.pi / 2)])
    # the coarse maxima read coarse_cells - 1 cells past a reached one: the border covers those too
    grow = shift + _ZERO_SIGMAS * cfg.sigma_m + cfg.coarse_cells * res
    i0 = np.maximum(np.floor((g[:2] + lo_xy - grow - lo) / res).astype(np.int64), 0)
    i1 = np.minimum(np.ceil((g[:2] + hi_xy + grow - lo) / res).astype(np.int64), [shape[1] - 1, shape[0] - 1])
    if np.any(i1 < i0):  # the scan cannot reach the target at all: keep a small grid
        i0 = i1 = np.zeros(2, dtype=np.int64)
    return (int(i1[1] - i0[1]) + 1, int(i1[0] - i0[0]) + 1), (int(i0[0]), int(i0[1]))


def correlative_match(source: ArrayLike, target: ArrayLike, initial: ArrayLike,
                      config: CorrelativeConfig | None = None) -> CorrelativeMatch:
    """Best ``T_target_source`` within the window around ``initial`` (3,). Shapes: source (N,2), target (M,2)."""
    return run_stages(correlative_stages(source, target, initial, config))


def correlative_stages(source: ArrayLike, target: ArrayLike, initial: ArrayLike,
                       config: CorrelativeConfig | None = None, *,
                       stages: int = 1) -> Generator[str, None, CorrelativeMatch]:
    """:func:`correlative_match` in steps that pause in between, the same result as at once: the likelihood grid,
    then the coarse scores (the bulk of the work) split by rotation into ``stages`` steps, the last of which also
    refines. ``stages`` + 1 steps: a caller with a per-cycle budget runs one at a time. Each pause yields the kind
    of the step that follows ("scores"), so that such a caller can tell short steps from long ones."""
    cfg = config or CorrelativeConfig()
    src = np.asarray(source, dtype=np.float64).reshape(-1, 2)
    tgt = np.asarray(target, dtype=np.float64).reshape(-1, 2)
    g = np.asarray(initial, dtype=np.float64)
    if len(src) == 0 or len(tgt) == 0:
        return CorrelativeMatch(g.copy(), 0.0, 1.0, 0)
    yield from ()  # a generator even when it returns before its first pause
    res, c = cfg.resolution_m, cfg.coarse_cells
    margin = 3 * cfg.sigma_m + c * res
    lo = tgt.min(axis=0) - margin
    hi = tgt.max(axis=0) + margin
    shape = (int(np.ceil((hi[1] - lo[1]) / res)) + 1, int(np.ceil((hi[0] - lo[0]) / res)) + 1)
    # coarse: angles around the guess, translations on a grid of coarse steps (multiples of c fine cells)
    na = int(np.ceil(cfg.window_theta_rad / cfg.coarse_theta_step_rad))
    th = g[2] + np.arange(-na, na + 1) * cfg.coarse_theta_step_rad
    step = c * res
    nk = int(np.ceil(cfg.window_xy_m / step))
    cells, first = _reachable(src, g, lo, shape, cfg)
    grids = _likelihood(tgt, lo, cells, cfg, 2 * (nk * c + c) + 1, first)
    koff = np.arange(-nk, nk + 1) * c  # coarse offsets from the guess, in fine cells
    kx = g[0] + koff * res
    ky = g[1] + koff * res
    parts = []
    for a in np.array_split(np.arange(len(th)), max(min(stages, len(th)), 1)):
        yield "scores"
        parts.append(_scores(grids.coarse, grids, src, th[a][None], g[:2], koff[None], koff[None], res)[0])
    sc = np.concatenate(parts, axis=0)  # (A,Y,X)
    order = np.argsort(sc, axis=None, kind="stable")[::-1]
    best_t, best_s = g.copy(), -1.0
    fa = int(np.ceil(0.5 * cfg.coarse_theta_step_rad / cfg.fine_theta_step_rad))
    dth = np.arange(-fa, fa + 1) * cfg.fine_theta_step_rad
    fine_cells = np.arange(c)
    fine_off = fine_cells * res
    evaluated = sc.size
    # the best max_refined coarse blocks' fine scores in one gather (a call per block costs more than the few
    # blocks the bound below skips)
    top_a, top_y, top_x = np.unravel_index(order[: cfg.max_refined], sc.shape)
    fine = _scores(grids.fine, grids, src, th[top_a][:, None] + dth, g[:2], koff[top_x][:, None] + fine_cells,
                   koff[top_y][:, None] + fine_cells, res)  # (B, fine angles, c, c)
    for f, a, iy, ix in zip(fine, top_a.tolist(), top_y.tolist(), top_x.tolist(), strict=True):
        if sc[a, iy, ix] <= best_s:  # the bound: nothing in this block can beat the best fine score
            break
        evaluated += f.size
        b = np.unravel_index(int(np.argmax(f)), f.shape)
        if f[b] > best_s:
            best_s = float(f[b])
            best_t = np.array([kx[ix] + fine_off[b[2]], ky[iy] + fine_off[b[1]], th[a] + dth[b[0]]])
    # ambiguity: the best coarse alignment far from the winner, relative to the best coarse score
    ty, tx = np.meshgrid(ky, kx, indexing="ij")
    far = ((np.hypot(tx - best_t[0], ty - best_t[1])[None] > cfg.ambiguity_radius_m)
           | (np.abs(th - best_t[2])[:, None, None] > cfg.ambiguity_angle_rad))
    if cfg.ambiguity_peaks:
        far &= sc >= ndimage.maximum_filter(sc, size=3, mode="nearest")
    top = float(sc.max())
    amb = float(sc[far].max()) / top if far.any() and top > 0 else 0.0
    best_t[2] = float(np.arctan2(np.sin(best_t[2]), np.cos(best_t[2])))
    return CorrelativeMatch(best_t, max(best_s, 0.0), amb, int(evaluated))


def run_stages(stages: Generator[object, None, T]) -> T:
    """Run staged work (a generator that pauses between stages, yielding anything) to its end and return its
    value."""
    while True:
        try:
            next(stages)
        except StopIteration as stop:
            return stop.value  # type: ignore[no-any-return]
