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

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from slam2d.config import check_positive

Array = NDArray[np.float64]


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


def _likelihood(points: Array, lo: Array, shape: tuple[int, int], cfg: CorrelativeConfig) -> tuple[Array, Array]:
    res = cfg.resolution_m
    occ = np.ones(shape, dtype=bool)
    ij = np.floor((points - lo) / res).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[0])
    occ[ij[inside, 1], ij[inside, 0]] = False
    d = np.asarray(ndimage.distance_transform_edt(occ), dtype=np.float64) * res
    fine = np.exp(-0.5 * (d / cfg.sigma_m) ** 2)
    c = cfg.coarse_cells
    # max over the block [i, i+c) x [j, j+c): a maximum filter shifted so that the block starts at the cell
    coarse = ndimage.maximum_filter(fine, size=c, origin=-(c // 2), mode="constant", cval=0.0)
    return fine, coarse


def _scores(grid: Array, pts: Array, thetas: Array, shifts_x: Array, shifts_y: Array, lo: Array,
            res: float) -> Array:
    """Mean grid value of ``pts`` rotated by each theta and moved by each (shift_y, shift_x) (metres).

    Shapes: pts (N,2), thetas (A,), shifts (X,), (Y,) -> (A, Y, X).
    """
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    x = c * pts[None, :, 0] - s * pts[None, :, 1]  # (A,N)
    y = s * pts[None, :, 0] + c * pts[None, :, 1]
    ix = np.floor((x[:, :, None] + shifts_x[None, None, :] - lo[0]) / res).astype(np.int64)  # (A,N,X)
    iy = np.floor((y[:, :, None] + shifts_y[None, None, :] - lo[1]) / res).astype(np.int64)  # (A,N,Y)
    ny, nx = grid.shape
    okx, oky = (ix >= 0) & (ix < nx), (iy >= 0) & (iy < ny)
    ix, iy = np.clip(ix, 0, nx - 1), np.clip(iy, 0, ny - 1)
    vals = grid[iy[:, :, :, None], ix[:, :, None, :]] * (oky[:, :, :, None] & okx[:, :, None, :])  # (A,N,Y,X)
    return np.asarray(vals.mean(axis=1), dtype=np.float64)


def correlative_match(source: ArrayLike, target: ArrayLike, initial: ArrayLike,
                      config: CorrelativeConfig | None = None) -> CorrelativeMatch:
    """Best ``T_target_source`` within the window around ``initial`` (3,). Shapes: source (N,2), target (M,2)."""
    cfg = config or CorrelativeConfig()
    src = np.asarray(source, dtype=np.float64).reshape(-1, 2)
    tgt = np.asarray(target, dtype=np.float64).reshape(-1, 2)
    g = np.asarray(initial, dtype=np.float64)
    if len(src) == 0 or len(tgt) == 0:
        return CorrelativeMatch(g.copy(), 0.0, 1.0, 0)
    res, c = cfg.resolution_m, cfg.coarse_cells
    margin = 3 * cfg.sigma_m + c * res
    lo = tgt.min(axis=0) - margin
    hi = tgt.max(axis=0) + margin
    shape = (int(np.ceil((hi[1] - lo[1]) / res)) + 1, int(np.ceil((hi[0] - lo[0]) / res)) + 1)
    fine, coarse = _likelihood(tgt, lo, shape, cfg)

    # coarse: angles around the guess, translations on a grid of coarse steps (multiples of c fine cells)
    na = int(np.ceil(cfg.window_theta_rad / cfg.coarse_theta_step_rad))
    th = g[2] + np.arange(-na, na + 1) * cfg.coarse_theta_step_rad
    step = c * res
    nk = int(np.ceil(cfg.window_xy_m / step))
    kx = g[0] + np.arange(-nk, nk + 1) * step
    ky = g[1] + np.arange(-nk, nk + 1) * step
    sc = _scores(coarse, src, th, kx, ky, lo, res)  # (A,Y,X)
    order = np.argsort(sc, axis=None, kind="stable")[::-1]
    best_t, best_s = g.copy(), -1.0
    fa = int(np.ceil(0.5 * cfg.coarse_theta_step_rad / cfg.fine_theta_step_rad))
    dth = np.arange(-fa, fa + 1) * cfg.fine_theta_step_rad
    fine_off = np.arange(c) * res
    evaluated = sc.size
    for flat in order[: cfg.max_refined].tolist():
        a, iy, ix = np.unravel_index(flat, sc.shape)
        if sc[a, iy, ix] <= best_s:  # the bound: nothing in this block can beat the best fine score
            break
        f = _scores(fine, src, th[a] + dth, kx[ix] + fine_off, ky[iy] + fine_off, lo, res)
        evaluated += f.size
        b = np.unravel_index(int(np.argmax(f)), f.shape)
        if f[b] > best_s:
            best_s = float(f[b])
            best_t = np.array([kx[ix] + fine_off[b[2]], ky[iy] + fine_off[b[1]], th[a] + dth[b[0]]])
    # ambiguity: the best coarse alignment far from the winner, relative to the best coarse score
    ty, tx = np.meshgrid(ky, kx, indexing="ij")
    far = ((np.hypot(tx - best_t[0], ty - best_t[1])[None] > cfg.ambiguity_radius_m)
           | (np.abs(th - best_t[2])[:, None, None] > cfg.ambiguity_angle_rad))
    top = float(sc.max())
    amb = float(sc[far].max()) / top if far.any() and top > 0 else 0.0
    best_t[2] = float(np.arctan2(np.sin(best_t[2]), np.cos(best_t[2])))
    return CorrelativeMatch(best_t, max(best_s, 0.0), amb, int(evaluated))
