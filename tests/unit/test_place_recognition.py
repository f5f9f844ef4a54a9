import numpy as np
import pytest
from scipy import stats

from slam2d.frontend.place_recognition import (
    KeyframeDatabase,
    PlaceRecognitionConfig,
    constellation_descriptor,
    loop_gate,
    observation_points,
    verify_loop,
)
from slam2d.geometry import between, compose, local
from slam2d.models import range_bearing

R = np.diag([0.05**2, 0.01**2])
CFG = PlaceRecognitionConfig()


def _scan(pose, landmarks, rng, max_range=8.0):
    z = range_bearing(pose, landmarks)
    z = z[z[:, 0] < max_range]
    z = z + rng.standard_normal(z.shape) * np.sqrt(np.diag(R))
    rng.shuffle(z)
    return observation_points(z, R)


def test_verified_transform_is_accurate_and_its_covariance_honest():
    rng = np.random.default_rng(0)
    errs = []
    for _ in range(150):
        lms = rng.uniform(-10, 10, size=(40, 2))
        pa = np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
        pb = compose(pa, np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-np.pi, np.pi)]))
        a, ca = _scan(pa, lms, rng)
        b, cb = _scan(pb, lms, rng)
        hyp = verify_loop(a, ca, b, cb, CFG, rng)
        assert hyp is not None
        e = local(between(pa, pb), hyp.T_a_b)
        errs.append(e @ np.linalg.solve(hyp.cov, e))
        assert np.hypot(*e[:2]) < 0.1
    # NEES of the loop constraint: mean ~3 (chi-square, 3 dof) -> the covariance is honest
    lo, hi = stats.chi2.ppf([0.005, 0.995], 3 * len(errs)) / len(errs)
    assert lo < np.mean(errs) < hi, np.mean(errs)


def test_degenerate_geometry_is_rejected():
    rng = np.random.default_rng(1)
    line = np.stack([np.linspace(-6, 6, 12), np.full(12, 2.0)], axis=-1)  # collinear landmarks
    a, ca = _scan(np.zeros(3), line, rng)
    b, cb = _scan(np.array([0.5, 0.0, 0.1]), line, rng)
    assert verify_loop(a, ca, b, cb, CFG, rng) is None
    few = rng.uniform(-5, 5, size=(3, 2))
    a, ca = _scan(np.zeros(3), few, rng)
    assert verify_loop(a, ca, a, ca, CFG, rng) is None
    assert verify_loop(np.zeros((0, 2)), np.zeros((0, 2, 2)), a, ca, CFG, rng) is None


def test_unrelated_places_do_not_verify():
    rng = np.random.default_rng(2)
    a, ca = _scan(np.zeros(3), rng.uniform(-8, 8, size=(15, 2)), rng)
    b, cb = _scan(np.zeros(3), rng.uniform(-8, 8, size=(15, 2)), rng)
    assert verify_loop(a, ca, b, cb, CFG, rng) is None


def test_descriptor_is_pose_invariant_and_database_finds_the_place():
    rng = np.random.default_rng(3)
    world = rng.uniform(0, 60, size=(300, 2))
    db = KeyframeDatabase(CFG)
    poses = [np.array([x, 30.0, 0.0]) for x in np.arange(5.0, 56.0, 2.0)]
    for k, p in enumerate(poses):
        assert db.add(k, _scan(p, world, rng)[0])
    revisit = np.array([25.3, 30.2, 2.0])  # near keyframe 10, facing another way
    hits = db.query(_scan(revisit, world, rng)[0], current_key=100)
    assert hits and abs(hits[0][0] - 10) <= 1
    d1 = constellation_descriptor(_scan(poses[10], world, rng)[0], CFG)
    d2 = constellation_descriptor(_scan(revisit, world, rng)[0], CFG)
    d3 = constellation_descriptor(_scan(np.array([50.0, 10.0, 0.0]), world, rng)[0], CFG)
    assert np.abs(d1 - d2).sum() < np.abs(d1 - d3).sum()
    assert db.query(_scan(revisit, world, rng)[0], current_key=5) == []  # too recent to be a loop
    db.remove(10)
    db.remove(999)  # unknown keyframe: ignored
    assert 10 not in db.keys


def test_loop_gate_rejects_a_loop_that_contradicts_the_estimate():
    cov_pred = np.diag([0.5, 0.5, 0.02])
    cov_meas = np.diag([0.01, 0.01, 0.001])
    ok, d2 = loop_gate(np.array([0.2, -0.1, 0.05]), cov_meas, np.zeros(3), cov_pred)
    assert ok and d2 < 5
    bad, d2 = loop_gate(np.array([6.0, 0.0, 0.0]), cov_meas, np.zeros(3), cov_pred)  # the aisle next door
    assert not bad and d2 > 50


def test_config_validation():
    with pytest.raises(ValueError, match="min_inliers"):
        PlaceRecognitionConfig(min_inliers=2)
