"""Loop verification of the lidar back end (graph/lidar_loops.py): static structure only, on a constructed aisle."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.geometry import se2
from slam2d.graph.lidar_config import LidarSLAMConfig
from slam2d.graph.lidar_loops import confirmed_mask, verify_loop

Array = np.ndarray


def _aisle(rng: np.random.Generator, x0: float, x1: float) -> Array:
    """Two long walls at y = +-2.5 between x0 and x1 (20 cm apart): nothing on them says where along x one is."""
    x = np.arange(x0, x1, 0.2)
    walls = np.vstack([np.stack([x, np.full_like(x, s)], -1) for s in (-2.5, 2.5)])
    return walls + rng.normal(0, 0.005, walls.shape)


def _box(rng: np.random.Generator, x: float) -> Array:
    """The outline of a 0.1 x 0.8 m object (a board carried across the view) whose near end is at ``x``, 1 cm
    apart: the only thing along x. (A long object sliding along its own sides keeps the overlap of its sides: see
    the report of the lidar back end.)"""
    t = np.arange(0.0, 0.1, 0.01)
    u = np.arange(0.0, 0.8, 0.01)
    pts = np.vstack([np.stack([x + t, np.full_like(t, 0.3)], -1), np.stack([x + t, np.full_like(t, 1.1)], -1),
                     np.stack([np.full_like(u, x), 0.3 + u], -1), np.stack([np.full_like(u, x + 0.1), 0.3 + u], -1)])
    return pts + rng.normal(0, 0.005, pts.shape)


def _case(rng: np.random.Generator, box_speed: float) -> tuple[Array, Array, Array, tuple[Array, Array], Array]:
    """Old keyframes at x = -0.3, 0, 0.3 (the middle one is the loop's frame), new keyframes at x = 0.2, 0.5, 0.8 (the
    last is the new scan); the box moves ``box_speed`` m per keyframe. Returns scan, map, guess, static, truth."""
    cfg = LidarSLAMConfig()
    old = [np.vstack([_aisle(rng, -6, 16), _box(rng, 3.0 + box_speed * j)]) for j in range(3)]
    new_poses = [np.array([0.2 + 0.3 * i, 0.0, 0.0]) for i in range(3)]
    truth = new_poses[-1]
    # the new keyframes see the box farther on: the new scan 0.9 m ahead of where the last old one did
    new_world = [np.vstack([_aisle(rng, -4, 14), _box(rng, 3.0 + box_speed * (4 + i))]) for i in range(3)]
    new = [se2.inverse_transform_points(truth, w) for w in new_world]  # in the new scan's frame
    pts = new[-1]
    clouds = [pts, *new[:-1]]
    r, a, s = cfg.loop_static_radius_m, cfg.loop_static_normal_rad, cfg.loop_static_seen_m
    static = (pts[confirmed_mask(clouds, r, a, s)[:len(pts)]], np.vstack(old)[confirmed_mask(old, r, a, s)])
    return pts, np.vstack(old), truth, static, truth


def test_a_loop_on_a_moving_box_in_an_aisle_passes_every_gate_on_all_points_but_not_on_static_ones() -> None:
    rng = np.random.default_rng(3)
    cfg = LidarSLAMConfig()
    pts, target, guess, static, truth = _case(rng, box_speed=0.25)
    plain = verify_loop(pts, target, guess, cfg)  # every point: the box pulls the loop along the aisle
    assert plain.ok
    assert abs(se2.local(truth, plain.transform)[0]) > 0.5  # wrong by more than half a metre along the aisle
    checked = verify_loop(*static, guess, cfg)  # static structure only: nothing says where along the aisle
    assert not checked.ok and checked.reason == "ambiguity"
    # the box is gone from both static sets; the walls stay
    assert not np.any(np.abs(static[1][:, 1]) < 2.0)
    assert len(static[1]) == 3 * 2 * 110  # every wall point of the three old keyframes


@pytest.mark.parametrize("seed", [0, 1])
def test_a_loop_on_a_parked_box_passes_the_static_recheck_and_is_right(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cfg = LidarSLAMConfig()
    pts, target, guess, static, truth = _case(rng, box_speed=0.0)
    start = se2.compose(guess, np.array([0.3, -0.1, 0.02]))  # the estimate is a little off
    checked = verify_loop(*static, start, cfg)
    assert checked.ok, checked.reason
    e = se2.local(truth, checked.transform)
    assert np.hypot(e[0], e[1]) < 0.03 and abs(e[2]) < 0.01


def test_confirmed_mask_keeps_what_two_clouds_saw_on_one_surface() -> None:
    wall = np.stack([np.linspace(0, 2, 21), np.zeros(21)], -1)
    face = np.stack([np.full(11, 1.0), np.linspace(0.2, 1.2, 11)], -1)  # a face across the wall's direction
    a = np.vstack([wall, face])
    b = np.vstack([wall + [0.02, 0.0], face + [0.5, 0.0]])  # the face moved 0.5 m; the wall stayed
    keep = confirmed_mask([a, b], 0.1, 1.0, 0.6)
    assert keep[:21].all() and not keep[21:32].any()  # cloud a: wall confirmed, face not
    assert keep[32:53].all() and not keep[53:].any()  # cloud b likewise
    # a face point next to the wall's end is near the other cloud's wall but faces the other way: not confirmed
    end = np.vstack([wall, np.stack([np.full(5, 2.05), np.linspace(0.0, 0.4, 5)], -1)])
    keep = confirmed_mask([end, wall + [0.3, 0.0]], 0.1, 1.0, 0.6)
    assert not keep[21:26].any()
    # a surface no other cloud looked at is kept
    far = np.stack([np.full(5, 9.0), np.linspace(0, 0.4, 5)], -1)
    assert confirmed_mask([np.vstack([wall, far]), wall], 0.1, 1.0, 0.6)[21:26].all()
