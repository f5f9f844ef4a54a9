"""The correlative matcher's likelihood grids against their definition."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

import slam2d.frontend.correlative as corr
from slam2d.frontend.correlative import CorrelativeConfig, _likelihood, _max_cos, correlative_match
from slam2d.geometry import se2


@pytest.mark.parametrize(("sigma", "cells"), [(0.1, 4), (0.03, 3), (0.4, 1)])
def test_likelihood_grids_are_the_gaussian_of_the_distance_and_its_block_maxima(sigma: float, cells: int) -> None:
    rng = np.random.default_rng(cells)
    cfg = CorrelativeConfig(sigma_m=sigma, coarse_cells=cells)
    pts = rng.uniform(0.0, 4.0, size=(60, 2))
    shape, pad = (70, 90), 2 * cells + 1
    g = _likelihood(pts, np.zeros(2), shape, cfg, pad)
    occ = np.ones(shape, dtype=bool)
    ij = np.floor(pts / cfg.resolution_m).astype(np.int64)
    inside = (ij[:, 0] < shape[1]) & (ij[:, 1] < shape[0])
    occ[ij[inside, 1], ij[inside, 0]] = False
    d = ndimage.distance_transform_edt(occ) * cfg.resolution_m
    want = np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)
    fine = g.fine.reshape(shape[0] + 2 * g.pad, shape[1] + 2 * g.pad)
    coarse = g.coarse.reshape(fine.shape)
    inner = (slice(g.pad, g.pad + shape[0]), slice(g.pad, g.pad + shape[1]))
    assert np.array_equal(fine[inner], want)
    for grid in (fine, coarse):  # the border is zero
        border = grid.copy()
        border[inner] = 0
        assert not border.any()
    grown = np.zeros((shape[0] + cells, shape[1] + cells), dtype=np.float32)
    grown[: shape[0], : shape[1]] = want
    blocks = np.max([grown[i:i + shape[0], j:j + shape[1]] for i in range(cells) for j in range(cells)], axis=0)
    assert np.array_equal(coarse[inner], blocks)  # the max over [i, i+c) x [j, j+c), 0 outside the grid


def test_the_largest_cosine_over_an_interval_matches_dense_sampling() -> None:
    rng = np.random.default_rng(1)
    a0 = rng.uniform(-12.0, 12.0, 500)
    a1 = a0 + rng.uniform(0.0, 3.0, 500)
    dense = np.cos(a0[:, None] + (a1 - a0)[:, None] * np.linspace(0.0, 1.0, 20001)[None, :]).max(axis=1)
    got = _max_cos(a0, a1)
    assert np.all(got >= dense - 1e-12)  # never below a value the arc reaches ...
    assert np.allclose(got, dense, atol=1e-7)  # ... and no more than it (sampling 1.5e-4 rad apart)


@pytest.mark.parametrize("theta_window", [0.3, 0.5, 1.2])
def test_a_wide_scan_turned_over_the_window_reads_only_cells_of_its_crop(
        monkeypatch: pytest.MonkeyPatch, theta_window: float) -> None:
    """A 360-degree scan of 20 m in a map of 40 m, turned by the whole window: every cell the search reads lies in
    the crop, whose matches are bit-identical to the whole grid's, and the crop is smaller than the scan's box grown
    by the arc of its farthest point on every side (the reach before it was exact)."""
    rng = np.random.default_rng(int(theta_window * 10))
    cfg = CorrelativeConfig(window_xy_m=0.5, window_theta_rad=theta_window)
    ang = rng.uniform(-np.pi, np.pi, 600)
    rad = rng.uniform(1.0, 40.0, 600)  # the map reaches twice as far as the scan
    tgt = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)]) + np.array([30.0, 10.0])
    lo = tgt.min(axis=0) - 0.5
    whole = (int((tgt[:, 1].max() - lo[1]) / 0.05) + 11, int((tgt[:, 0].max() - lo[0]) / 0.05) + 11)
    reachable = corr._reachable
    for _ in range(3):
        pose = np.array([30.0, 10.0, 0.0]) + rng.uniform(-0.3, 0.3, 3)
        src = se2.inverse_transform_points(pose, tgt[rad < 20.0])
        guess = pose + rng.uniform(-0.2, 0.2, 3)
        cells, first = reachable(src, guess, lo, whole, cfg)
        # every pose the search can try: coarse angles to the step past the window, fine ones half a step beyond
        far = np.ceil(theta_window / 0.02) * 0.02 + 0.01
        turn = np.linspace(-far, far, 400)
        moved = np.concatenate([se2.transform_points(np.array([0.0, 0.0, guess[2] + t]), src) for t in turn])
        reach = 0.5 + 2 * 0.2 + 0.1
        need_lo = np.floor((moved.min(axis=0) + guess[:2] - reach - lo) / 0.05)
        need_hi = np.ceil((moved.max(axis=0) + guess[:2] + reach - lo) / 0.05)
        need_lo, need_hi = np.maximum(need_lo, 0), np.minimum(need_hi, np.array(whole[::-1]) - 1)  # off the grid
        assert np.all(need_lo >= first)
        assert np.all(need_hi <= np.array(first) + cells[::-1] - 1)
        at_guess = se2.transform_points(np.array([0.0, 0.0, guess[2]]), src)
        grow = 1.05 + np.hypot(src[:, 0], src[:, 1]).max() * (theta_window + 0.02) + 1.5  # shift + sweep + border
        old = at_guess.max(axis=0) - at_guess.min(axis=0) + 2 * grow
        assert cells[0] * cells[1] < 0.8 * (old[0] / 0.05) * (old[1] / 0.05)
        _crop_matches_whole_grid(monkeypatch, src, tgt, guess, cfg)


def _crop_matches_whole_grid(monkeypatch: pytest.MonkeyPatch, src: np.ndarray, tgt: np.ndarray, guess: np.ndarray,
                             cfg: CorrelativeConfig) -> None:
    """The match on the cropped grid is bit-identical to the match on the whole grid."""
    reachable = corr._reachable
    cropped = correlative_match(src, tgt, guess, cfg)
    monkeypatch.setattr(corr, "_reachable", lambda s, g, lo, shape, c: (shape, (0, 0)))
    full = correlative_match(src, tgt, guess, cfg)
    monkeypatch.setattr(corr, "_reachable", reachable)
    assert np.array_equal(cropped.transform, full.transform)
    assert cropped.score == full.score and cropped.ambiguity == full.ambiguity


def test_correlative_grid_cropped_to_the_scans_reach_gives_the_whole_grids_results(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The likelihood grid covers only the cells a moved scan point can reach (plus a zero border): on a long
    corridor map with clutter the crop is less than half the grid, and every match is bit-identical to the whole
    grid's (same lattice, and outside the border the likelihood is exactly zero in float32)."""
    rng = np.random.default_rng(0)
    x = np.arange(-40, 40, 0.05)
    walls = np.vstack([np.stack([x, np.full_like(x, s)], -1) for s in (-1.5, 1.5)])
    clutter = np.column_stack([rng.uniform(-40, 40, 300), rng.uniform(-4, 4, 300)])
    tgt = np.vstack([walls, clutter]) + rng.normal(0, 0.01, (len(walls) + 300, 2))
    cfg = CorrelativeConfig()
    reachable = corr._reachable
    for _ in range(10):
        pose = np.array([rng.uniform(-20, 20), rng.uniform(-0.5, 0.5), rng.uniform(-0.2, 0.2)])
        src = se2.inverse_transform_points(pose, tgt[np.abs(tgt[:, 0] - pose[0]) < 8])
        guess = pose + np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2)])
        lo = tgt.min(axis=0) - 0.5
        whole = (int((tgt[:, 1].max() - lo[1]) / 0.05) + 11, int((tgt[:, 0].max() - lo[0]) / 0.05) + 11)
        cells, _ = reachable(src, guess, lo, whole, cfg)
        assert cells[0] * cells[1] < 0.5 * whole[0] * whole[1]
        _crop_matches_whole_grid(monkeypatch, src, tgt, guess, cfg)
