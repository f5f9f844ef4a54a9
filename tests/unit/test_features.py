"""Image/grid features: Harris corners on the simulated room's grid, blobs, edges, BRIEF matching."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.frontend.features import (
    BlobConfig,
    HarrisConfig,
    blobs,
    brief_descriptors,
    edges,
    grid_image,
    harris_corners,
    match_binary,
    match_points,
    pixels_to_world,
    world_to_pixels,
)
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid
from slam2d.sim import simulate

ROOM_CORNERS = np.array([[0, 0], [20, 0], [20, 14], [0, 14], [9, 6], [11, 6], [11, 8], [9, 8]], dtype=float)


@pytest.fixture(scope="module")
def room_grid() -> OccupancyGrid:
    log = simulate("room", seed=0)
    assert log.true_poses is not None and log.scan_step is not None
    g = OccupancyGrid((-1.05, -1.05, 21.0, 15.0), OccupancyConfig(resolution_m=0.1))
    g.integrate(log.true_poses[log.scan_step], log.scan_ranges_m, log.scan_angles_rad, log.scan_max_range_m)
    return g


def test_harris_finds_the_room_corners(room_grid: OccupancyGrid) -> None:
    img = grid_image(room_grid)
    truth_px = world_to_pixels(room_grid, ROOM_CORNERS)
    c = harris_corners(img, HarrisConfig(threshold_rel=0.1))
    s = match_points(c, truth_px, tolerance=3.0)  # 3 cells = 0.3 m
    # measured: 8 detections, all 8 corners (precision 1, recall 1)
    assert s.recall == 1.0 and s.precision >= 0.8, s
    # world coordinates of the matched detections are within 0.3 m of the true corners
    w = pixels_to_world(room_grid, c)
    d = np.min(np.hypot(*(w[:, None] - ROOM_CORNERS[None]).transpose(2, 0, 1)), axis=0)
    assert np.all(d < 0.3)


@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_harris_count_is_monotone_in_threshold(room_grid: OccupancyGrid, noise: float) -> None:
    rng = np.random.default_rng(0)
    img = np.clip(grid_image(room_grid) + rng.normal(0, noise, room_grid.shape), 0, 1)
    truth_px = world_to_pixels(room_grid, ROOM_CORNERS)
    ths = [0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.8, 0.95]
    scores = [match_points(harris_corners(img, HarrisConfig(threshold_rel=t)), truth_px, 3.0) for t in ths]
    counts = [s.detections for s in scores]
    assert np.all(np.diff(counts) <= 0), counts
    assert counts[0] > 3 * counts[-1]  # the threshold really controls the count
    # low threshold: everything found but many false corners; high threshold: few, all right, some missed
    assert scores[0].recall == 1.0 and scores[0].precision < 0.5
    assert scores[-1].precision == 1.0 and scores[-1].recall < 1.0
    assert max(s.precision + s.recall for s in scores) == 2.0  # some threshold in between is perfect


def test_blobs_find_gaussian_spots(rng: np.random.Generator) -> None:
    img = np.zeros((120, 160))
    centres = np.array([[20, 30], [60, 80], [100, 40], [30, 130], [90, 120]], dtype=float)
    rr, cc = np.mgrid[:120, :160]
    for r, c in centres:
        img += np.exp(-((rr - r) ** 2 + (cc - c) ** 2) / (2 * 3.0**2))
    img += rng.normal(0, 0.01, img.shape)
    for method in ("dog", "log"):
        b = blobs(img, BlobConfig(method=method, min_sigma_px=1, max_sigma_px=8, threshold=0.05))  # type: ignore[arg-type]
        s = match_points(b[:, :2], centres, tolerance=2.0)
        assert s.recall == 1.0 and s.precision == 1.0, (method, s)
        assert np.all((b[:, 2] > 1.5) & (b[:, 2] < 6))  # the scale of a sigma-3 spot


def test_canny_edges_on_a_rectangle() -> None:
    img = np.zeros((60, 80))
    img[15:45, 20:60] = 1.0
    e = edges(img, sigma_px=1.0)
    r, c = np.nonzero(e)
    # every edge pixel lies on the rectangle border (within a pixel) and all four sides are found
    on_border = (np.minimum(np.abs(r - 14.5), np.abs(r - 44.5)) <= 1.0) | (
        np.minimum(np.abs(c - 19.5), np.abs(c - 59.5)) <= 1.0)
    assert on_border.all()
    assert e[14:16, 30].any() and e[44:46, 30].any() and e[30, 19:21].any() and e[30, 59:61].any()


def test_brief_descriptors_match_under_translation(room_grid: OccupancyGrid) -> None:
    img = grid_image(room_grid)
    shift = (7, -5)
    moved = np.roll(img, shift, axis=(0, 1))
    k1 = harris_corners(img, HarrisConfig(threshold_rel=0.01))
    k2 = harris_corners(moved, HarrisConfig(threshold_rel=0.01))
    d1, m1 = brief_descriptors(img, k1, patch_px=15)
    d2, m2 = brief_descriptors(moved, k2, patch_px=15)
    assert d1.dtype == bool and d1.shape[1] == 256 and len(d1) == m1.sum() >= 6
    pairs = match_binary(d1, d2)
    disp = k2[m2][pairs[:, 1]] - k1[m1][pairs[:, 0]]
    good = np.all(disp == shift, axis=1)
    assert len(pairs) >= 6 and good.mean() >= 0.9, (len(pairs), good.mean())
    assert match_binary(d1[:0], d2).shape == (0, 2)


def test_bad_images_and_configs() -> None:
    with pytest.raises(ValueError, match="2-D"):
        harris_corners(np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        harris_corners(np.full((5, 5), np.nan))
    assert harris_corners(np.zeros((20, 20))).shape == (0, 2)
    with pytest.raises(ValueError, match="threshold_rel"):
        HarrisConfig(threshold_rel=1.5)
    with pytest.raises(ValueError, match="method"):
        BlobConfig(method="hog")  # type: ignore[arg-type]
