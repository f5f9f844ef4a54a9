"""Lab experiments: slopes, claims, and the shape of their results (run on whatever estimators are registered)."""

import numpy as np
import pytest

from slam2d.lab.experiments import claim_for, consistency, fit_loglog_slope, scaling
from slam2d.lab.registry import estimator_names, get_spec


def test_loglog_slope_recovers_a_power_law():
    x = np.array([10.0, 40, 160, 640])
    assert fit_loglog_slope(x, 3.0 * x**2) == pytest.approx(2.0)
    assert fit_loglog_slope(x, 0.5 * x**1) == pytest.approx(1.0)
    assert np.isnan(fit_loglog_slope([5.0, 5.0], [1.0, 2.0]))  # one distinct x: no slope


def test_claims_cover_the_lesson_back_ends():
    assert claim_for("ekf")[1] == 2.0
    assert claim_for("fastslam2")[1] == 1.0
    assert claim_for("dead-reckoning")[1] == 0.0
    assert claim_for("something-new") == ("no claim recorded", None)


def test_scaling_runs_every_registered_estimator_and_fits_slopes():
    res = scaling(landmarks=(9, 16), steps=20)
    # the lidar back ends would only dead-reckon on the grid (no walls): listed as skipped, not timed
    scans = {n for n in estimator_names() if get_spec(n).needs == "scans"}
    assert scans == {"lidar", "lidar-lifelong"} and set(res["skipped"]) == scans
    assert set(res["fits"]) == set(estimator_names()) - scans
    for name in res["fits"]:
        rows = [r for r in res["rows"] if r["estimator"] == name]
        assert [r["landmarks"] for r in rows] == [9, 16]
        assert all(r["step_ms_median"] > 0 and r["obs_per_step"] > 0 for r in rows)
    dr = [r for r in res["rows"] if r["estimator"] == "dead-reckoning"]
    assert all(r["mapped"] == 0 for r in dr)  # dead reckoning keeps no map


def test_consistency_reports_band_and_fraction_for_each_estimator():
    res = consistency(["dead-reckoning"], scenario="room", seeds=6, steps=30)
    r = res["results"]["dead-reckoning"]
    assert len(r["mean_nees"]) == 30
    lo, hi = r["band"]
    assert lo < 3 < hi and 0 <= r["fraction_inside"] <= 1
    with pytest.raises(ValueError, match="unknown key 'bogus'"):
        consistency(["dead-reckoning"], seeds=2, overrides={"bogus": 1})
