"""Tracking of the lidar back end (graph/lidar_tracking.py): a poor ICP fit is redone from a correlative search."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.frontend.icp import ICPConfig, ICPTarget, prepare_target
from slam2d.geometry import se2
from slam2d.graph.lidar_config import LidarSLAMConfig
from slam2d.graph.lidar_tracking import good_fit, track_scan
from slam2d.models.lidar import cast_rays

Array = np.ndarray


def _room(rng: np.random.Generator) -> Array:
    """An L-shaped room with a pillar (10 cm spacing, 5 mm noise): every direction is constrained."""
    segs = [((0, 0), (8, 0)), ((8, 0), (8, 3)), ((8, 3), (3, 3)), ((3, 3), (3, 7)), ((3, 7), (0, 7)), ((0, 7), (0, 0)),
            ((5, 1), (5.6, 1)), ((5.6, 1), (5.6, 1.6)), ((5.6, 1.6), (5, 1.6)), ((5, 1.6), (5, 1))]
    pts = []
    for (x0, y0), (x1, y1) in segs:
        n = max(int(np.hypot(x1 - x0, y1 - y0) / 0.1), 2)
        t = np.linspace(0, 1, n, endpoint=False)
        pts.append(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], -1))
    return np.vstack(pts) + rng.normal(0, 0.005, (sum(len(p) for p in pts), 2))


def _cases() -> tuple[LidarSLAMConfig, list[tuple[Array, ICPTarget, Array, Array]]]:
    """The room seen by a 180-degree lidar from a true pose, matched from guesses off by 0.3-0.45 rad (an in-place
    spin's odometry) and 7 cm."""
    rng = np.random.default_rng(5)
    cfg = LidarSLAMConfig()
    world = _room(rng)
    target = prepare_target(world, cfg.icp)
    out = []
    for k in range(12):
        truth = np.array([1.5 + 0.3 * (k % 4), 1.2 + 0.2 * (k % 3), -1.0 + 0.5 * k])
        pts = se2.inverse_transform_points(truth, world)
        pts = pts[np.abs(np.arctan2(pts[:, 1], pts[:, 0])) < np.pi / 2]  # a 180-degree lidar: what leaves the view
        sign = 1.0 if k % 2 else -1.0
        guess = se2.compose(truth, np.array([0.05, -0.05, sign * (0.3 + 0.15 * (k % 2))]))
        out.append((pts, target, guess, truth))
    return cfg, out


def test_a_poor_fit_is_redone_from_a_correlative_search_and_lands_on_the_truth() -> None:
    cfg, cases = _cases()
    plain_wrong = 0
    for pts, target, guess, truth in cases:
        off = track_scan(pts, target, guess, cfg.icp, cfg.min_fitness, cfg.track_rematch_rmse_m,
                         cfg.track_correlative, 0)  # no re-match: ICP from the guess only
        e = se2.local(truth, off.match.transform)
        plain_wrong += bool(np.hypot(e[0], e[1]) > 0.05 or abs(e[2]) > 0.02)
        on = track_scan(pts, target, guess, cfg.icp, cfg.min_fitness, cfg.track_rematch_rmse_m,
                        cfg.track_correlative, cfg.track_rematch_points)
        e = se2.local(truth, on.match.transform)
        assert np.hypot(e[0], e[1]) < 0.02 and abs(e[2]) < 0.005
        assert on.rematched == (not good_fit(off.match, cfg.min_fitness, cfg.track_rematch_rmse_m))
        assert on.match.rmse_m <= cfg.track_rematch_rmse_m
    assert plain_wrong >= 3  # the guesses do put ICP into wrong minima (else this test shows nothing)


def test_a_good_fit_is_kept_without_a_search() -> None:
    cfg, cases = _cases()
    pts, target, _, truth = cases[0]
    res = track_scan(pts, target, se2.compose(truth, np.array([0.02, 0.0, 0.01])), cfg.icp,
                     cfg.min_fitness, cfg.track_rematch_rmse_m, cfg.track_correlative, cfg.track_rematch_points)
    assert not res.rematched and not res.replaced
    assert np.hypot(*se2.local(truth, res.match.transform)[:2]) < 0.01


def _junction() -> Array:
    """A crossing of two corridors 2 m wide, 6 m arms (walls (S,4)): a quarter turn about its centre maps it onto
    itself, so a scan fits as well turned 90 degrees."""
    w, arm, segs = 1.0, 6.0, []
    for k in range(4):
        r = se2.rotation_matrix(k * np.pi / 2)
        for a, b in (((w, w), (arm, w)), ((arm, w), (arm, -w)), ((arm, -w), (w, -w))):
            segs.append([*(r @ np.array(a)), *(r @ np.array(b))])
    return np.asarray(segs)


def test_a_fit_that_slid_a_quarter_turn_is_not_trusted_and_the_steady_guess_finds_the_truth() -> None:
    """Odometry that stalls and then reports the stalled turn at once, on top of the turn tracking already found
    (mit-csail, scans 1579-1583): the guess is 1.0-1.2 rad past the truth, in a junction where a quarter turn fits as
    well. ICP and the +-0.5 rad re-match around that guess end a quarter turn off; ICP from the steady guess (the
    last tracked motion repeated) lands on the truth."""
    rng = np.random.default_rng(0)
    cfg, seg = LidarSLAMConfig(), _junction()
    beams = np.linspace(-np.pi / 2, np.pi / 2, 181)

    def scan(pose: Array) -> Array:
        t = cast_rays(pose, beams, seg, 25.0)
        ok = t < 25.0
        r = t[ok] + rng.normal(0, 0.005, ok.sum())
        return np.stack([r * np.cos(beams[ok]), r * np.sin(beams[ok])], -1)

    before, truth = np.array([0.3, -0.2, 0.1]), np.array([0.35, -0.15, 0.38])
    target = prepare_target(se2.transform_points(before, scan(before)), cfg.icp)
    pts = scan(truth)
    steady = se2.compose(truth, np.array([0.02, -0.02, 0.03]))
    for over in (1.0, 1.2):
        guess = se2.compose(truth, np.array([0.05, 0.03, over]))
        args = (pts, target, guess, cfg.icp, cfg.min_fitness, cfg.track_rematch_rmse_m, cfg.track_correlative,
                cfg.track_rematch_points)
        e = se2.local(truth, track_scan(*args).match.transform)
        assert abs(abs(e[2]) - np.pi / 2) < 0.05  # without the steady guess: a quarter turn off
        on = track_scan(*args, steady)
        e = se2.local(truth, on.match.transform)
        assert on.replaced and np.hypot(e[0], e[1]) < 0.02 and abs(e[2]) < 0.005


def test_the_odometry_prior_is_off_by_default_and_its_settings_are_checked() -> None:
    cfg = LidarSLAMConfig()
    assert cfg.track_prior_xy == 0.0 and cfg.track_prior_theta == 0.0
    with pytest.raises(ValueError, match="track_prior_xy"):
        LidarSLAMConfig(track_prior_xy=-1.0)
    with pytest.raises(ValueError, match="point-to-line"):
        LidarSLAMConfig(track_prior_theta=1.0, icp=ICPConfig(method="point-to-point"))
