"""NEES/NIS and the chi-square band, map error after association, TUM export (cross-checked with evo if present)."""

import itertools
import warnings

import numpy as np
import pytest
from scipy import stats

import slam2d
from slam2d.eval import ate
from slam2d.eval.consistency import Band, chi2_band, monte_carlo_consistency, nees, nis, pose_error, pose_nees
from slam2d.eval.mapping import map_error
from slam2d.geometry import compose
from slam2d.io.tum import poses_to_tum, read_tum, tum_to_poses, write_tum


def random_spd(rng, n, d):
    a = rng.normal(size=(n, d, d))
    return a @ a.transpose(0, 2, 1) + 0.1 * np.eye(d)


def test_nees_matches_the_explicit_quadratic_form(rng):
    covs = random_spd(rng, 20, 3)
    e = rng.normal(size=(20, 3))
    want = np.array([ei @ np.linalg.inv(ci) @ ei for ei, ci in zip(e, covs, strict=True)])
    np.testing.assert_allclose(nees(e, covs), want, rtol=1e-10)
    np.testing.assert_allclose(nis(e[:, :2], covs[:, :2, :2]), [
        ei[:2] @ np.linalg.inv(ci[:2, :2]) @ ei[:2] for ei, ci in zip(e, covs, strict=True)], rtol=1e-10)


def test_pose_error_wraps_the_heading():
    err = pose_error(np.array([[1.0, 2.0, np.pi - 0.1]]), np.array([[0.5, 2.5, -np.pi + 0.1]]))
    np.testing.assert_allclose(err, [[0.5, -0.5, -0.2]], atol=1e-12)


def test_band_holds_its_probability_for_averages_of_chi_square_draws(rng):
    # brute force: the mean of R chi2(d) draws falls in the band with the stated probability
    for dof, runs in [(2, 1), (3, 25), (1, 50)]:
        band = chi2_band(dof, runs, 0.9)
        means = rng.chisquare(dof, size=(20000, runs)).mean(axis=1)
        assert band.fraction_inside(means) == pytest.approx(0.9, abs=0.01), (dof, runs)
    b = chi2_band(3, 50)
    assert b.low < 3 < b.high
    assert (b.low, b.high) == pytest.approx(stats.chi2.ppf([0.025, 0.975], 150) / 50)


def test_nees_of_samples_from_the_stated_covariance_is_inside_the_band_and_of_a_scaled_one_is_not(rng):
    runs, steps = 30, 200
    covs = random_spd(rng, steps, 3)
    chol = np.linalg.cholesky(covs)
    errs = np.einsum("tij,rtj->rti", chol, rng.normal(size=(runs, steps, 3)))
    good = monte_carlo_consistency(nees(errs, covs[None]), dof=3)
    assert good.fraction_inside > 0.9 and good.overall_mean == pytest.approx(3.0, rel=0.05)
    # a filter claiming twice the true covariance is conservative (NEES too small), half of it is overconfident
    for scale in (2.0, 0.5):
        bad = monte_carlo_consistency(nees(errs, scale * covs[None]), dof=3)
        assert bad.fraction_inside < 0.1, (scale, bad.fraction_inside)
        assert bad.overall_mean == pytest.approx(3.0 / scale, rel=0.05)


def test_monte_carlo_consistency_uses_the_band_of_the_runs_present(rng):
    vals = rng.chisquare(3, size=(10, 50))
    vals[:4, 0] = np.nan  # step 0 has only 6 runs
    summ = monte_carlo_consistency(vals, dof=3)
    assert summ.mean[0] == pytest.approx(np.mean(vals[4:, 0]))
    assert summ.band == chi2_band(3, 10)
    with pytest.raises(ValueError, match="runs"):
        chi2_band(3, 0)
    assert isinstance(summ.band, Band)


def test_dead_reckoning_pose_nees_via_the_module(rng):
    log = slam2d.simulate("room", seed=3, steps=40)
    res = slam2d.run(slam2d.make_estimator("dead-reckoning", log_metadata=log.metadata), log,
                     rng=np.random.default_rng(3))
    v = pose_nees(res.poses[1:], res.pose_covs[1:], log.true_poses[1:])
    assert v.shape == (40,) and np.all(v >= 0) and np.isfinite(v).all()


def brute_force_matching(est, ref, gate):
    """Max number of pairs within ``gate``, then the least total distance: by trying every injection."""
    d = np.hypot(*(est[:, None] - ref[None]).transpose(2, 0, 1))
    best = (0, 0.0)
    small, large, flip = (est, ref, False) if len(est) <= len(ref) else (ref, est, True)
    for perm in itertools.permutations(range(len(large)), len(small)):
        pairs = [(i, j) if not flip else (j, i) for i, j in enumerate(perm)]
        ok = [d[a, b] for a, b in pairs if d[a, b] <= gate]
        cand = (len(ok), -sum(ok))
        if cand > (best[0], -best[1]):
            best = (len(ok), sum(ok))
    return best


def test_map_error_is_the_best_gated_one_to_one_matching(rng):
    for _ in range(40):
        ref = rng.uniform(0, 4, size=(rng.integers(1, 6), 2))
        est = rng.uniform(0, 4, size=(rng.integers(1, 6), 2))
        me = map_error(est, ref, max_distance_m=1.2)
        n, total = brute_force_matching(est, ref, 1.2)
        assert me.matched == n
        assert np.sum(me.errors_m) == pytest.approx(total, abs=1e-9)
        assert me.spurious == len(est) - n and me.missed == len(ref) - n
        assert len(set(me.pairs[:, 0])) == n and len(set(me.pairs[:, 1])) == n


def test_map_error_after_the_ate_alignment_forgives_a_common_rigid_motion(rng):
    truth = rng.uniform(0, 30, size=(25, 2))
    motion = np.array([4.0, -2.0, 0.7])
    est = compose(motion, np.column_stack([truth, np.zeros(25)]))[:, :2]
    est = est[rng.permutation(25)][:20]  # own order, 5 never mapped
    est = np.vstack([est, [[200.0, 200.0]]])  # one spurious landmark far away
    raw = map_error(est, truth, max_distance_m=1.0)
    assert raw.matched < 20
    traj = rng.normal(size=(30, 3)).cumsum(axis=0)
    align = ate(compose(motion, traj), traj).alignment
    me = map_error(est, truth, max_distance_m=1.0, alignment=align)
    assert (me.matched, me.spurious, me.missed) == (20, 1, 5)
    assert me.rmse_m < 1e-9
    empty = map_error(np.zeros((0, 2)), truth)
    assert (empty.matched, empty.missed, np.isnan(empty.rmse_m)) == (0, 25, True)


def test_tum_round_trip_and_quaternion(tmp_path, rng):
    poses = np.column_stack([rng.normal(size=(30, 2)), rng.uniform(-np.pi, np.pi, 30)])
    stamps = np.arange(30) * 0.1
    rows = poses_to_tum(stamps, poses)
    assert rows.shape == (30, 8)
    np.testing.assert_allclose(np.linalg.norm(rows[:, 4:], axis=1), 1.0)
    np.testing.assert_array_equal(rows[:, [3, 4, 5]], 0.0)
    path = write_tum(tmp_path / "t.txt", stamps, poses)
    assert path.read_text().splitlines()[1].count(" ") == 7
    t2, p2 = read_tum(path)
    np.testing.assert_array_equal(t2, stamps)
    np.testing.assert_allclose(p2[:, :2], poses[:, :2], atol=0)
    np.testing.assert_allclose(slam2d.geometry.angle_diff(p2[:, 2], poses[:, 2]), 0.0, atol=1e-12)
    bad = rows.copy()
    bad[3, 4] = 0.5
    with pytest.raises(ValueError, match="not planar"):
        tum_to_poses(bad)
    (tmp_path / "b.txt").write_text("0 1 2 3\n")
    with pytest.raises(ValueError, match=r"b.txt:1: expected 8 numbers"):
        read_tum(tmp_path / "b.txt")


def test_our_ate_matches_evo(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        evo_fi = pytest.importorskip("evo.tools.file_interface")
        from evo.core import metrics
    log = slam2d.simulate("loop", seed=1, steps=200)
    res = slam2d.run(slam2d.make_estimator("dead-reckoning", log_metadata=log.metadata), log,
                     rng=np.random.default_rng(1))
    ours = ate(res.trajectory, log.true_poses).rmse_m
    assert ours > 0.1  # dead reckoning drifts: a non-trivial alignment to agree on
    write_tum(tmp_path / "est.txt", log.stamps_s, res.trajectory)
    write_tum(tmp_path / "ref.txt", log.stamps_s, log.true_poses)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = evo_fi.read_tum_trajectory_file(tmp_path / "ref.txt")
        est = evo_fi.read_tum_trajectory_file(tmp_path / "est.txt")
        est.align(ref, correct_scale=False)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref, est))
        theirs = ape.get_statistic(metrics.StatisticsType.rmse)
    assert ours == pytest.approx(theirs, rel=1e-9)
