"""The correlative matcher's likelihood grids against their definition."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from slam2d.frontend.correlative import CorrelativeConfig, _likelihood


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
