"""SLAM on the whole Victoria Park log without ids, GPS used only to score (skipped cleanly when ../shared/datasets
is absent). Apart from ``test_datasets_real.py`` so that the two long files run on both test workers at once.
EKF-SLAM runs in every `make test`; FastSLAM 2.0 and online graph SLAM (about 210 s more on the CI machine) run with
SLAM2D_LONG_TESTS=1."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.eval.gps import gps_ate
from slam2d.io.datasets.victoria import load_victoria
from testkit import LONG, chain, dataset_path


@pytest.mark.slow
@pytest.mark.parametrize(("estimator", "gps_bound_m"), [
    ("ekf", 4.5),
    pytest.param("fastslam2", 4.5, marks=LONG),
])
def test_victoria_unknown_association_matches_gps_and_the_processed_optimum(estimator: str, gps_bound_m: float):
    """The must-show of the real-data issue: no ids, GPS used only to score. Measured (seed 0): ekf 3.28 m,
    fastslam2 2.80 m against 44.2 m for dead reckoning; both lead the processed graph to chi2 6183.93. FastSLAM 2.0
    needs its landmark tracks' evidence rule here (FastSLAM's default): with consecutive misses and confirmed
    landmarks never pruned it keeps 655 landmarks (the processed graph has 151 trees) and ends at 19.2 m (seed 1:
    704 landmarks, 17.3 m)."""
    import slam2d
    from slam2d.lab.victoria_reference import compare_with_processed_graph

    log = load_victoria(dataset_path("victoria-park"))
    dataset_path("victoria-park", "victoriaPark.txt")
    res, _ = slam2d.run_named(estimator, log=log, seed=0,
                              overrides={"association.method": "mahalanobis",
                                         **({"use_gps": "false"} if estimator == "ekf" else {})})
    dr = gps_ate(chain(log.odometry, log.initial_pose), log).rmse_m
    got = gps_ate(res.trajectory, log).rmse_m
    assert got < gps_bound_m and got < 0.15 * dr, (got, dr)
    ref = compare_with_processed_graph(log, res.trajectory, res.final.landmarks)
    # from the odometry chain the solvers stop at 503276 (LM) / 250028 (dog leg); from either estimate, at one far
    # lower minimum (the same to 1e-6: two different raw-data estimates lead to it)
    assert ref.chi2_final == pytest.approx(6183.9328, rel=1e-6) and ref.chi2_initial > 100 * ref.chi2_final
    assert np.median(ref.trajectory_vs_optimum_m) < 2.0
    assert ref.map_vs_optimum.matched >= 75 and np.median(ref.map_vs_optimum.errors_m) < 2.0


@pytest.mark.slow
@LONG
def test_victoria_online_graph_with_unknown_association_beats_dead_reckoning():
    """Online graph SLAM, no ids, GPS only to score, on the first 2500 steps (about 25 s CPU on the VM of 2026-12-01,
    76 s on the 2.0 GHz EPYC VM of 2026-12-05; the whole log is in ``benchmarks/real_data.py``). Measured (seed 0):
    1.31 m against 14.3 m for dead reckoning and 1.4 m for EKF-SLAM; before the association used the joint [pose,
    candidates] covariance and held tentative landmarks aside it was 8.2 m."""
    import slam2d

    log = load_victoria(dataset_path("victoria-park"), max_steps=2500)
    res, rec = slam2d.run_named("graph", log=log, seed=0, overrides={"association.method": "mahalanobis"})
    dr = gps_ate(chain(log.odometry, log.initial_pose), log).rmse_m
    got = gps_ate(res.trajectory, log).rmse_m
    assert got < 2.5 and got < 0.2 * dr, (got, dr)
    assert res.final.diagnostics.loops_accepted >= 1 and rec["landmarks_estimated"] < 250
