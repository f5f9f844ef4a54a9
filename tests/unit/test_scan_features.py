"""Scan features: split-and-merge lines match the true walls; corners are true corners; bad beams are ignored."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.frontend.scan import LineExtractionConfig, corner_observations, extract_lines, line_corners
from slam2d.geometry import se2
from slam2d.models.lidar import cast_rays
from slam2d.models.sensors import range_bearing_inverse
from slam2d.sim.world import box_walls

WALLS = np.vstack([box_walls(0, 0, 20, 14), box_walls(9, 6, 11, 8)])
CORNERS = np.array([[0, 0], [20, 0], [20, 14], [0, 14], [9, 6], [11, 6], [11, 8], [9, 8]], dtype=float)
ANGLES = np.linspace(-np.pi, np.pi, 720, endpoint=False)


def true_line_params(pose: np.ndarray) -> np.ndarray:
    """(alpha, d) of every wall in the frame of ``pose``."""
    a = se2.inverse_transform_points(pose, WALLS[:, :2])
    b = se2.inverse_transform_points(pose, WALLS[:, 2:])
    t = (b - a) / np.hypot(*(b - a).T)[:, None]
    n = np.stack([-t[:, 1], t[:, 0]], axis=-1)
    d = np.einsum("ki,ki->k", n, a)
    n = np.where(d[:, None] < 0, -n, n)
    return np.stack([np.arctan2(n[:, 1], n[:, 0]), np.abs(d)], axis=-1)


def test_lines_and_corners_match_the_room(rng: np.random.Generator) -> None:
    found_room_corners = []
    for _ in range(20):
        pose = np.array([rng.uniform(1.5, 18.5), rng.uniform(1.5, 12.5), rng.uniform(-3, 3)])
        if 8.5 < pose[0] < 11.5 and 5.5 < pose[1] < 8.5:
            continue
        r = cast_rays(pose, ANGLES, WALLS, 30.0) + rng.normal(0, 0.01, ANGLES.shape)
        lines = extract_lines(r, ANGLES, 30.0)
        assert len(lines) >= 4
        truth = true_line_params(pose)
        for k in range(len(lines)):
            # both segment ends lie on one true wall line (within 5 cm), and the direction agrees
            ends = np.stack([lines.start[k], lines.end[k]])
            off = np.abs(ends @ np.stack([np.cos(truth[:, 0]), np.sin(truth[:, 0])]) - truth[:, 1])  # (2, W)
            da = np.abs(np.angle(np.exp(2j * (truth[:, 0] - lines.normal_angle[k])))) / 2
            best = np.argmin(off.max(axis=0) + da)
            assert off[:, best].max() < 0.05 and da[best] < 0.02, (k, off[:, best], da[best])
            assert lines.length[k] > 0.3
        corners = se2.transform_points(pose, line_corners(lines))
        dist = np.min(np.hypot(*(corners[:, None] - CORNERS[None]).transpose(2, 0, 1)), axis=1)
        assert np.all(dist < 0.05), dist  # every detected corner is a true corner (precision 1)
        dc = np.min(np.hypot(*(CORNERS[:4, None] - corners[None]).transpose(2, 0, 1)), axis=1) if len(corners) else \
            np.full(4, np.inf)
        found_room_corners.append(int(np.sum(dc < 0.05)))
    # recall is limited by physics, not by the extractor: the pillar hides corners, and walls seen at grazing angles
    # break into gaps wider than max_gap_m near far corners (measured: 2.06 of 4 room corners per pose on average)
    assert np.mean(found_room_corners) >= 1.8 and min(found_room_corners) >= 1, found_room_corners


def test_corner_observations_roundtrip() -> None:
    pose = np.array([4.0, 3.0, 0.3])
    r = cast_rays(pose, ANGLES, WALLS, 30.0)
    c = line_corners(extract_lines(r, ANGLES, 30.0))
    z = corner_observations(c)
    assert np.allclose(range_bearing_inverse(np.broadcast_to(pose, (len(z), 3)), z), se2.transform_points(pose, c))


def test_bad_beams_and_empty_scans() -> None:
    pose = np.array([4.0, 3.0, 0.0])
    r = cast_rays(pose, ANGLES, WALLS, 30.0)
    clean = extract_lines(r, ANGLES, 30.0)
    bad = r.copy()
    bad[::7] = np.nan
    bad[3::11] = np.inf
    bad[5::13] = 30.0  # max range = no return
    bad[2::17] = -1.0
    dirty = extract_lines(bad, ANGLES, 30.0)
    assert len(dirty) >= len(clean) - 2 and np.all(np.isfinite(dirty.start))
    assert len(extract_lines(np.zeros(0), np.zeros(0), 30.0)) == 0
    assert len(extract_lines(np.full(720, np.nan), ANGLES, 30.0)) == 0
    assert line_corners(extract_lines(np.zeros(0), np.zeros(0), 30.0)).shape == (0, 2)
    with pytest.raises(ValueError, match="shape"):
        extract_lines(r[:10], ANGLES, 30.0)
    with pytest.raises(ValueError, match="min_points"):
        LineExtractionConfig(min_points=1)
