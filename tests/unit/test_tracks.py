"""LandmarkTracks: exact small cases of the confirm / miss / prune rules, the in-view rule, the persistence rule, and
the batch axis (M maps at once equal M independent runs)."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.association.tracks import LandmarkTracks, TrackConfig, in_view


def test_confirmed_after_k_sightings_exactly() -> None:
    tr = LandmarkTracks(TrackConfig(confirm_after=3))
    tr.append(2, step=0)
    assert tr.tentative[0].tolist() == [True, True] and not tr.confirmed.any()
    tr.sight([0], step=1)
    assert tr.hits[0].tolist() == [2, 1] and not tr.confirmed.any()
    tr.sight([0], step=2)
    assert tr.confirmed[0].tolist() == [True, False]
    # a slot listed twice in one call counts twice (two observations of one landmark in a scan)
    tr.sight([1, 1], step=3)
    assert tr.hits[0].tolist() == [3, 3] and tr.confirmed[0].tolist() == [True, True]


@pytest.mark.parametrize("confirmed", [False, True])
def test_pruned_after_n_misses_in_view_not_before(confirmed: bool) -> None:
    cfg = TrackConfig(confirm_after=2, tentative_max_misses=3, confirmed_max_misses=5)
    tr = LandmarkTracks(cfg)
    tr.append(1, step=0)
    t = 0
    if confirmed:
        t = 1
        tr.sight([0], step=t)
    limit = 5 if confirmed else 3
    for k in range(1, limit + 1):
        tr.miss(np.ones((1, 1), dtype=bool), step=t + k)
        assert tr.misses[0, 0] == k
        assert tr.prune_mask()[0, 0] == (k >= limit), k


def test_not_pruned_out_of_view_and_a_sighting_resets_the_misses() -> None:
    tr = LandmarkTracks(TrackConfig(tentative_max_misses=2))
    tr.append(2, step=0)
    for t in range(1, 20):  # landmark 1 is never in view: never a miss
        tr.miss(np.array([[t % 3 != 0, False]]), step=t)
        if t % 3 == 2:
            tr.sight([0], step=t)  # sighted after each miss: consecutive misses never reach 2
        assert not tr.prune_mask().any(), t
    assert tr.misses[0].tolist() == [1, 0]
    # a slot sighted (or started) at the step itself is never missed at that step
    tr.sight([0], step=30)
    tr.miss(np.ones((1, 2), dtype=bool), step=30)
    assert tr.misses[0].tolist() == [0, 1]


def test_zero_limits_never_prune_and_detection_probability_scales_the_limits() -> None:
    never = LandmarkTracks(TrackConfig(tentative_max_misses=0, confirmed_max_misses=0))
    never.append(1, step=0)
    for t in range(1, 50):
        never.miss(np.ones((1, 1), dtype=bool), step=t)
    assert not never.prune_mask().any()
    # p_d = 0.4: 1/p_d = 2.5 sightings' worth of misses per miss allowed -> ceil(3 * 2.5) = 8
    cfg = TrackConfig(tentative_max_misses=3, misses_per_sighting=2.5)
    assert cfg.tentative_limit == 8
    tr = LandmarkTracks(cfg)
    tr.append(1, step=0)
    for t in range(1, 9):
        tr.miss(np.ones((1, 1), dtype=bool), step=t)
        assert tr.prune_mask()[0, 0] == (t >= 8)


@pytest.mark.parametrize("p_d", [1.0, 0.5, 0.25, 0.3])
def test_evidence_rule_is_the_existence_counter(p_d: float, rng: np.random.Generator) -> None:
    """miss_rule="evidence" against a scalar reference of the existence counter FastSLAM had before the tracker
    (start 2g, +g per sighting, -1 per miss, pruned at 0; g = round(1/p_d)), over random sighting/miss sequences.
    When 1/p_d is not an integer the start is the tracker's limit ceil(2/p_d) (7 for p_d = 0.3, not 2g = 6)."""
    g = max(1, round(1 / p_d))
    cfg = TrackConfig(confirm_after=2, tentative_max_misses=2, confirmed_max_misses=2, misses_per_sighting=1 / p_d,
                      miss_rule="evidence")
    assert cfg.misses_cancelled_by_sighting == g
    for _ in range(20):
        tr = LandmarkTracks(cfg)
        tr.append(1, step=0)
        evidence = cfg.tentative_limit
        assert evidence == 2 * g or p_d == 0.3
        for t in range(1, 60):
            if rng.random() < 0.4:
                tr.sight([0], step=t)
                evidence += g
            else:
                tr.miss(np.ones((1, 1), dtype=bool), step=t)
                evidence -= 1
            assert tr.prune_mask()[0, 0] == (evidence <= 0), (t, evidence, tr.misses)
            if evidence <= 0:
                break
    # unlike "consecutive", a long-sighted landmark survives a run of misses longer than the limit
    tr = LandmarkTracks(cfg)
    tr.append(1, step=0)
    for t in range(1, 10):
        tr.sight([0], step=t)
    for t in range(10, 10 + cfg.tentative_limit + 9 * g - 1):
        tr.miss(np.ones((1, 1), dtype=bool), step=t)
    assert not tr.prune_mask().any()
    with pytest.raises(ValueError, match="miss_rule"):
        TrackConfig(miss_rule="sometimes")


def test_in_view_rule() -> None:
    z = np.array([[7.4, 0.0], [7.6, 0.0], [5.0, 0.5], [5.0, 0.45], [0.0, 0.0]])
    # range <= 8 - 0.5; |bearing| <= fov/2 - 0.5 / range (fov 1.2 rad: 0.6 - 0.1 = 0.5 at 5 m)
    assert in_view(z, 8.0, 1.2, 0.5).tolist() == [True, False, True, True, False]
    assert in_view(z[:2], 8.0, 2 * np.pi, 0.0).tolist() == [True, True]


def test_free_select_grow_keep() -> None:
    tr = LandmarkTracks(TrackConfig(), batch=2, capacity=1)
    tr.start([0], step=0, rows=[1])
    assert tr.occupied.tolist() == [[False], [True]]
    tr.grow(3)
    assert tr.capacity == 3 and tr.hits.tolist() == [[0, 0, 0], [1, 0, 0]]
    tr.start([2, 2], step=1, rows=[0, 1])
    copy = tr.select([1, 1])
    copy.hits[0, 0] = 9
    assert tr.hits[1, 0] == 1 and copy.hits[1, 0] == 1  # fancy indexing copies: rows share no memory
    tr.free(np.array([[False, False, True], [True, False, False]]))
    assert tr.occupied.tolist() == [[False, False, False], [False, False, True]]
    one = LandmarkTracks(TrackConfig())
    one.append(3, step=0)
    one.sight([2], step=1)
    one.keep(np.array([True, False, True]))
    assert one.hits[0].tolist() == [1, 2]
    with pytest.raises(ValueError, match="rows are required"):
        tr.sight([0], step=2)
    with pytest.raises(ValueError, match="confirm_after"):
        TrackConfig(confirm_after=0)


def _walk(rng: np.random.Generator, velocity: float, steps: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    z = np.array([3.0, 4.0]) + np.outer(np.arange(steps), [velocity, 0.0]) + rng.normal(0, sigma, (steps, 2))
    return z, np.repeat(np.eye(2)[None] * sigma**2, steps, axis=0)


def test_a_moving_object_is_never_confirmed_a_static_one_is(rng: np.random.Generator) -> None:
    cfg = TrackConfig(confirm_after=10, dynamic_test=True, tentative_max_misses=0)
    sigma = 0.15
    counts = {"static": 0, "moving": 0}
    for _ in range(40):
        for kind, v in (("static", 0.0), ("moving", 0.16)):  # the forklift: one sigma of drift per step
            z, c = _walk(rng, v, 30, sigma)
            tr = LandmarkTracks(cfg)
            tr.append(1, 0, z[:1], c[:1])
            ever = False
            for t in range(1, 30):
                tr.sight([0], t, z[t:t + 1], c[t:t + 1])
                ever |= bool(tr.confirmed[0, 0])
            counts[kind] += int(ever)
            if kind == "moving" and tr.dynamic[0, 0]:
                assert tr.prune_mask()[0, 0]  # a dynamic track is pruned at once
    assert counts["moving"] <= 1 and counts["static"] >= 37, counts


def test_persistence_sums_equal_the_direct_fits(rng: np.random.Generator) -> None:
    tr = LandmarkTracks(TrackConfig(confirm_after=50, dynamic_test=True))
    steps = np.array([4, 5, 7, 8, 11])
    z = rng.normal(0, 1, (5, 2))
    covs = np.array([np.diag(rng.uniform(0.1, 0.5, 2)) for _ in range(5)])
    tr.append(1, int(steps[0]), z[:1], covs[:1])
    for i in range(1, 5):
        tr.sight([0], int(steps[i]), z[i:i + 1], covs[i:i + 1])
    w = np.linalg.inv(covs)
    mean = np.linalg.solve(w.sum(0), np.einsum("kij,kj->i", w, z))
    d = z - mean
    assert tr.consistency_chi2()[0] == pytest.approx(np.einsum("ki,kij,kj->", d, w, d), rel=1e-10)
    # constant-velocity weighted least squares, solved directly: z_i = a + b t_i
    t = steps - steps[0]
    a_rows = np.concatenate([np.eye(2)[None].repeat(5, 0), t[:, None, None] * np.eye(2)], axis=2)  # (5,2,4)
    h = np.einsum("kai,kab,kbj->ij", a_rows, w, a_rows)
    sol = np.linalg.solve(h, np.einsum("kai,kab,kb->i", a_rows, w, z))
    b, cov_b = sol[2:], np.linalg.inv(h)[2:, 2:]
    assert tr.velocity_chi2()[0] == pytest.approx(b @ np.linalg.solve(cov_b, b), rel=1e-8)


def test_batch_axis_equals_m_independent_runs(rng: np.random.Generator) -> None:
    m, k, steps = 4, 6, 25
    cfg = TrackConfig(confirm_after=3, tentative_max_misses=2, confirmed_max_misses=4, dynamic_test=True)
    batch = LandmarkTracks(cfg, batch=m, capacity=k)
    singles = [LandmarkTracks(cfg, batch=1, capacity=k) for _ in range(m)]
    for t in range(steps):
        start = rng.random((m, k)) < 0.1
        sight = (rng.random((m, k)) < 0.5) & batch.occupied & ~start
        view = rng.random((m, k)) < 0.7
        pts = rng.normal(0, 0.2, (m, k, 2)) + np.arange(k)[None, :, None]
        covs = np.broadcast_to(np.eye(2) * 0.04, (m, k, 2, 2))
        r, c = np.nonzero(start)
        batch.start(c, t, pts[r, c], covs[r, c], rows=r)
        r, c = np.nonzero(sight)
        batch.sight(c, t, pts[r, c], covs[r, c], rows=r)
        batch.miss(view, t)
        drop = batch.prune_mask()
        batch.free(drop)
        for i, one in enumerate(singles):
            cs = np.flatnonzero(start[i])
            one.start(cs, t, pts[i, cs], covs[i, cs])
            cs = np.flatnonzero(sight[i])
            one.sight(cs, t, pts[i, cs], covs[i, cs])
            one.miss(view[i][None], t)
            d = one.prune_mask()
            np.testing.assert_array_equal(d[0], drop[i])
            one.free(d)
    assert batch.hits.sum() > 0 and batch.confirmed.any()
    for i, one in enumerate(singles):
        for name in ("hits", "misses", "first_step", "last_step", "dynamic", "w", "wz", "zwz", "wt", "wtt", "wtz"):
            np.testing.assert_array_equal(getattr(batch, name)[i], getattr(one, name)[0], err_msg=name)


@pytest.mark.parametrize("name", ["ekf", "fastslam", "graph"])
def test_back_ends_keep_a_slowly_moving_object_out_with_the_persistence_rule(name: str) -> None:
    from slam2d.lab.registry import make_estimator
    from slam2d.log import Observations, Step

    confirmed = {}
    for dyn in (False, True):
        rng = np.random.default_rng(4)
        # the filter assumes 5 cm / 25 mrad noise (the data have 1 cm / 5 mrad): the object creeping 2 cm per step
        # stays inside the association gate, so only the persistence rule can tell it from a post
        over = {"association.method": "mahalanobis", "dynamic_test": dyn, "confirm_after": 12,
                "sensor.range_std_m": 0.05, "sensor.bearing_std_rad": 0.025}
        if name == "fastslam":
            over["particles"] = 5
        est = make_estimator(name, over)
        est.reset(np.zeros(3), rng=np.random.default_rng(0))
        for t in range(1, 40):
            pts = np.array([[3.0, 0.0], [0.0, 2.0 + 0.02 * t]])  # a post, and the creeping object
            r = np.hypot(*pts.T) + rng.normal(0, 0.01, 2)
            b = np.arctan2(pts[:, 1], pts[:, 0]) + rng.normal(0, 0.005, 2)
            est.step(Step(index=t, time_s=0.1 * t, dt_s=0.1, odometry=np.zeros(3),
                          observations=Observations(r, b, np.array([-1, -1]))))
        confirmed[dyn] = est.estimate().landmarks
    assert len(confirmed[False]) >= 2, confirmed  # without the rule the creeping object becomes landmark(s)
    assert len(confirmed[True]) == 1 and np.hypot(*(confirmed[True][0] - [3.0, 0.0])) < 0.1, confirmed
