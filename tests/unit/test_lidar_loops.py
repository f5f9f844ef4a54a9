"""Loop verification of the lidar back end (graph/lidar_loops.py): static structure only, on a constructed aisle."""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import replace
from typing import TypeVar

import numpy as np
import pytest

from slam2d.frontend import icp as icp_module
from slam2d.frontend.correlative import correlative_match, correlative_stages, run_stages
from slam2d.geometry import se2
from slam2d.graph import lidar_loops
from slam2d.graph.factors import between_error
from slam2d.graph.lidar_config import LidarSLAMConfig
from slam2d.graph.lidar_loops import at_window_edge, confirmed_mask, verify_loop, verify_loop_stages, wide_correlative
from slam2d.models.lidar import cast_rays

Array = np.ndarray
T = TypeVar("T")


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


def test_confirmed_mask_of_three_clouds_is_each_point_against_each_other_cloud(rng: np.random.Generator) -> None:
    """The mask of three clouds equals, point by point, the rule applied to each other cloud on its own (an empty
    cloud looks nowhere)."""
    wall = np.stack([np.linspace(0, 3, 31), np.zeros(31)], -1)
    clouds = [wall + rng.normal(0, 0.01, wall.shape), np.vstack([wall[::2], [[1.5, 0.5], [1.6, 0.5]]]),
              np.zeros((0, 2)), wall[10:] + [0.0, 0.3]]
    got = confirmed_mask(clouds, 0.1, 0.5, 0.6)
    want = []
    for i, c in enumerate(clouds):
        n_i = icp_module.estimate_normals(c) if len(c) >= 2 else np.zeros((len(c), 2))
        seen, confirmed = np.zeros(len(c), bool), np.zeros(len(c), bool)
        for j, o in enumerate(clouds):
            if j == i or not len(o):
                continue
            n_j = icp_module.estimate_normals(o)
            for p in range(len(c)):
                d = np.hypot(*(o - c[p]).T)
                seen[p] |= bool(d.min() <= 0.6)
                close = np.argsort(d)[:4]
                confirmed[p] |= bool(np.any((d[close] < 0.1) & (np.abs(n_j[close] @ n_i[p]) >= np.cos(0.5))))
        want.append(confirmed | ~seen)
    assert np.array_equal(got, np.concatenate(want))
    assert got.any() and not got.all()


def test_agreeing_equals_loops_agree_pair_by_pair(rng: np.random.Generator) -> None:
    """The pool's agreement with a new loop, all at once, is loops_agree of each pair on the later loop's poses."""
    cfg = LidarSLAMConfig()
    poses = np.cumsum(rng.normal(0, [0.5, 0.5, 0.1], (40, 3)), axis=0)
    snap = poses + rng.normal(0, 0.01, poses.shape)  # the new loop's poses
    c, k = 5, 30
    t_ck = se2.between(snap[c], snap[k])
    pool = []
    for c1, k1 in ((4, 28), (6, 30), (5, 30), (3, 33), (7, 25), (2, 31)):  # (5, 30) is the new loop itself
        t = se2.between(snap[c1], snap[k1]) + rng.normal(0, [0.02, 0.02, 0.01]) * rng.integers(0, 2)
        pool.append((c1, k1, t, np.eye(3), False, snap if k1 <= k else snap + rng.normal(0, 0.01, snap.shape)))
    got = lidar_loops.agreeing(pool, (c, k, t_ck), snap, cfg)
    want = [lidar_loops.loops_agree(q[:3], (c, k, t_ck), snap, cfg) if q[1] <= k else
            lidar_loops.loops_agree((c, k, t_ck), q[:3], q[5], cfg) for q in pool]
    assert got == want
    assert any(got) and not all(got) and not got[2]  # both outcomes occur; a loop never agrees with itself


def _segments(posts: bool) -> Array:
    """Walls (S,4) [x0, y0, x1, y1] of a corridor 2.4 m wide along x. ``posts=False``: closed by an end wall at
    x = -3, with door recesses here and there (what pins where along the corridor one is); ``posts=True``:
    open, a 0.3 m post on each wall every 1.5 m (a repeating rack: every 1.5 m looks the same)."""
    if posts:
        seg = [[-20, -1.2, 20, -1.2], [-20, 1.2, 20, 1.2]]
        seg += [[px, s * 1.2, px, s * 0.9] for px in np.arange(-15.0, 15.0, 1.5) for s in (-1.0, 1.0)]
    else:  # door recesses (0.4 m deep) at irregular places on both walls
        seg, doors = [[-3, -1.2, -3, 1.2]], {1.2: [-2.2, -0.6, 1.9, 6.0], -1.2: [-1.5, 0.3, 3.1]}
        for y, xs in doors.items():
            d = 0.4 * np.sign(y)
            edges = [-3.0] + [e for x in xs for e in (x, x + 0.8)] + [20.0]
            seg += [[a, y, b, y] for a, b in zip(edges[::2], edges[1::2], strict=True)]
            seg += [q for x in xs for q in ([x, y, x, y + d], [x, y + d, x + 0.8, y + d], [x + 0.8, y + d, x + 0.8, y])]
    return np.asarray(seg, dtype=np.float64)


def _scan(rng: np.random.Generator, seg: Array, pose: Array, max_range: float = 8.0) -> Array:
    """A 361-beam, 180-degree scan at ``pose`` (points in its frame, 5 mm range noise), beams that hit only."""
    a = np.linspace(-np.pi / 2, np.pi / 2, 361)
    t = cast_rays(pose, a, seg, max_range)
    ok = t < max_range
    r = t[ok] + rng.normal(0, 0.005, ok.sum())
    return np.stack([r * np.cos(a[ok]), r * np.sin(a[ok])], -1)


def _return(rng: np.random.Generator, posts: bool) -> tuple[Array, Array, Array, Array]:
    """A loop candidate on coming back after a drift of 1.7 m along the corridor: the old keyframe at the origin
    facing -x (its map: every wall within 12 m, as many views would have drawn it), the new scan 1 m ahead, the guess
    1.7 m off along the axis. Returns scan, map (in the old keyframe's frame), guess, truth (T_old_new)."""
    seg = _segments(posts)
    truth = np.array([-1.0, 0.1, np.pi + 0.05])  # facing the end wall, 2 m away
    old = np.array([0.0, 0.0, np.pi])
    walls = np.vstack([a + np.linspace(0.0, 1.0, int(np.hypot(*(b - a)) / 0.02) + 1)[:, None] * (b - a)
                       for a, b in zip(seg[:, :2], seg[:, 2:], strict=True)])  # every wall, 2 cm apart
    walls = walls[np.hypot(walls[:, 0], walls[:, 1]) < 12.0]
    target = se2.inverse_transform_points(old, walls + rng.normal(0, 0.005, walls.shape))
    truth = se2.between(old, truth)
    scan = _scan(rng, seg, se2.compose(old, truth))
    return scan, target, se2.compose(truth, np.array([1.7, 0.0, 0.0])), truth


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_return_beyond_the_window_is_found_by_the_wide_search_in_a_corridor_pinned_by_its_end(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cfg = LidarSLAMConfig(loop_retry_window_m=2.5)
    pts, target, guess, truth = _return(rng, posts=False)
    first = verify_loop(pts, target, guess, cfg)  # +-1 m: the right alignment is outside, nothing matches
    assert not first.ok and first.reason == "score"  # what makes the back end search wider ...
    assert 0 < first.score and at_window_edge(first.transform, guess, cfg.correlative)  # ... with the best at the edge
    wide = verify_loop(pts, target, guess, cfg, wide=True)
    assert wide.ok, wide.reason
    assert wide.ambiguity < cfg.loop_max_ambiguity
    e = se2.local(truth, wide.transform)
    assert np.hypot(e[0], e[1]) < 0.03 and abs(e[2]) < 0.01
    # every far alignment counted (the old rule) leaves it ambiguous: the axis keeps the scores high
    plain = correlative_match(pts[::3], target, guess, replace(wide_correlative(cfg), ambiguity_peaks=False))
    assert plain.ambiguity > cfg.loop_max_ambiguity


@pytest.mark.parametrize("seed", [0, 1])
def test_the_wide_search_rejects_a_corridor_of_repeating_posts(seed: int) -> None:
    """Posts every 1.5 m: the alignments 1.5 m either side are peaks of their own and score as well."""
    rng = np.random.default_rng(seed)
    cfg = LidarSLAMConfig(loop_retry_window_m=2.5)
    pts, target, guess, _ = _return(rng, posts=True)
    wide = verify_loop(pts, target, guess, cfg, wide=True)
    assert not wide.ok and wide.reason in ("ambiguity", "edge")
    assert wide.reason != "ambiguity" or wide.ambiguity > cfg.loop_max_ambiguity


def _stages_run(gen: Generator[object, None, T]) -> tuple[int, T]:
    """Drive a staged computation: (how many times it paused, its value)."""
    pauses = 0
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return pauses, stop.value  # type: ignore[no-any-return]
        pauses += 1


@pytest.mark.parametrize("stages", [1, 2, 3, 7])
def test_a_staged_correlative_search_pauses_after_its_grid_and_between_stages_and_equals_the_search_at_once(
        stages: int) -> None:
    rng = np.random.default_rng(stages)
    cfg = LidarSLAMConfig(loop_retry_window_m=2.5)
    pts, target, guess, _ = _return(rng, posts=False)
    cc = wide_correlative(cfg)
    pauses, staged = _stages_run(correlative_stages(pts, target, guess, cc, stages=stages))
    once = correlative_match(pts, target, guess, cc)
    assert pauses == stages  # the grid, then the coarse scores in ``stages`` parts
    assert np.array_equal(staged.transform, once.transform)
    assert (staged.score, staged.ambiguity, staged.evaluated) == (once.score, once.ambiguity, once.evaluated)
    assert run_stages(correlative_stages(pts, target, guess, cc, stages=stages)).score == once.score


def test_a_staged_loop_check_pauses_in_its_search_and_before_icp_and_equals_the_check_at_once() -> None:
    rng = np.random.default_rng(0)
    cfg = LidarSLAMConfig(loop_retry_window_m=2.5, loop_retry_stages=3, loop_search_stages=2)
    pts, target, guess, truth = _return(rng, posts=False)
    pauses, first = _stages_run(verify_loop_stages(pts, target, guess, cfg))
    assert pauses == cfg.loop_search_stages and first.reason == "score"  # rejected before ICP: no ICP stages
    pauses, wide = _stages_run(verify_loop_stages(pts, target, guess, cfg, wide=True))
    assert pauses == cfg.loop_retry_stages + 2 and wide.ok  # the search's stages, then the normals', then ICP's
    at_once = verify_loop(pts, target, guess, cfg, wide=True)
    assert np.array_equal(at_once.transform, wide.transform) and at_once.chi2 == wide.chi2


@pytest.mark.parametrize("turn", [0.0, np.pi / 2, 2.0])
def test_a_loops_information_weighs_a_displacement_in_the_old_frame_as_its_icp_covariance_whatever_the_new_heading(
        turn: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """The loop enters the graph as a between factor, whose error is in the new keyframe's frame; its ICP
    covariance is over x, y in the old keyframe's. The same loop seen from a new frame turned by ``turn`` must
    weigh a displacement along the corridor (old x) as the covariance does: loosely (it was entered unturned, which
    after a 90-degree turn weighed it as the sure direction across)."""
    cov = np.diag([0.04**2, 0.002**2, 0.001**2])  # ICP's covariance, made long along the corridor

    def long_icp(*args: object, **kw: object) -> icp_module.ICPResult:
        return replace(icp_module.icp(*args, **kw), covariance=cov)  # type: ignore[arg-type]

    monkeypatch.setattr(lidar_loops, "icp", long_icp)
    cfg = LidarSLAMConfig()
    pts, target, _, truth = _return(np.random.default_rng(0), posts=False)
    turned = np.array([0.0, 0.0, turn])  # the new keyframe's frame turned: its points turn back
    chk = verify_loop(se2.inverse_transform_points(turned, pts), target, se2.compose(truth, turned), cfg)
    assert chk.ok, chk.reason
    floor = np.diag([cfg.min_sigma_xy_m**2, cfg.min_sigma_xy_m**2, cfg.min_sigma_theta_rad**2])
    want = np.linalg.inv(cov + floor)
    for d in ([0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0, 0.01]):
        e = between_error(np.zeros(3), chk.transform + d, chk.transform)
        assert e @ chk.information @ e == pytest.approx(np.asarray(d) @ want @ np.asarray(d), rel=1e-9)
