"""FastSLAM's linearised pose covariance (``FastSLAMConfig.pose_cov="linearised"``): maths against a batch solve,
the combination rule on exact small cases, and the filter wiring (estimate unchanged, bad configurations rejected)."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.association import AssociationConfig
from slam2d.filters.fastslam import FastSLAM, FastSLAM2Config
from slam2d.filters.fastslam_marginal import LinearisedMarginal
from slam2d.geometry import se2
from slam2d.lab.registry import make_estimator
from slam2d.log import Observations, Step
from slam2d.models.motion import MotionNoise, odometry_covariance_scalar, odometry_scalar
from slam2d.models.sensors import SensorConfig, range_bearing, range_bearing_scalar
from slam2d.sim.simulator import simulate

R = SensorConfig().covariance
NOISE = MotionNoise()


def _world(rng: np.random.Generator, steps: int = 20) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """True poses (steps+1,3) along a curve, landmarks (8,2) and, per step, the ids seen (within 4 m)."""
    poses = [np.zeros(3)]
    for _ in range(steps):
        poses.append(se2.compose(poses[-1], np.array([0.5, 0.0, rng.uniform(-0.3, 0.3)])))
    path = np.array(poses)
    lms = rng.uniform([-2.0, -4.0], [12.0, 4.0], size=(8, 2))
    seen = [np.flatnonzero(np.hypot(*(lms - p[:2]).T) < 4.0) for p in path[1:]]
    return path, lms, seen


def _batch_marginal(path: np.ndarray, lms: np.ndarray, seen: list[np.ndarray]) -> np.ndarray:
    """The newest pose's marginal from the information matrix of the linearised full-SLAM problem (x_0 known).

    Linearised at the truth, odometry exact (x_k (+) u_k = x_k+1), measurements noise-free: the recursion under test
    then filters the same linear-Gaussian system, so the Kalman recursion must equal the batch marginal exactly."""
    steps, n_lm = len(path) - 1, len(lms)
    order = [int(j) for ids in seen for j in ids]
    first = list(dict.fromkeys(order))
    dim = 3 * steps + 2 * n_lm
    info = np.zeros((dim, dim))

    def add(blocks: list[tuple[int, np.ndarray]], cov: np.ndarray) -> None:
        w = np.linalg.inv(cov)
        for a, ja in blocks:
            for b, jb in blocks:
                info[a:a + ja.shape[1], b:b + jb.shape[1]] += ja.T @ w @ jb

    for k in range(steps):
        u = se2.between(path[k], path[k + 1])
        _, g, v = odometry_scalar(path[k], u)
        q = v @ odometry_covariance_scalar(u, NOISE) @ v.T
        blocks = [(3 * k, np.eye(3))] + ([(3 * (k - 1), -g)] if k else [])
        add(blocks, q)
        for j in seen[k]:
            _, h = range_bearing_scalar(path[k + 1], lms[j])
            add([(3 * k, h[:, :3]), (3 * steps + 2 * first.index(int(j)), h[:, 3:])], R)
    used = np.r_[np.arange(3 * steps), 3 * steps + np.arange(2 * len(first))]
    cov = np.linalg.inv(info[np.ix_(used, used)])
    return cov[3 * steps - 3:3 * steps, 3 * steps - 3:3 * steps]


def test_recursion_equals_the_batch_marginal_of_the_linearised_problem(rng):
    path, lms, seen = _world(rng)
    lin = LinearisedMarginal(path[0], R)
    for k in range(len(path) - 1):
        u = se2.between(path[k], path[k + 1])
        z = range_bearing(path[k + 1], lms[seen[k]])
        lin.step(path[k + 1], u, NOISE, seen[k], lms[seen[k]], z)
    np.testing.assert_allclose(lin.pose_cov(), _batch_marginal(path, lms, seen), rtol=1e-7, atol=1e-12)


def test_landmarks_keep_their_first_linearisation_point(rng):
    # moving a landmark's estimate after its first sighting must not change the covariance (first-estimate Jacobians)
    path, lms, seen = _world(rng)
    covs = []
    for shift in (0.0, 0.3):
        lin = LinearisedMarginal(path[0], R)
        known: set[int] = set()
        for k in range(len(path) - 1):
            ids = seen[k]
            later = np.array([int(j) in known for j in ids], dtype=bool)
            estimates = lms[ids] + shift * k * later[:, None]  # later estimates drift away from the first ones
            lin.step(path[k + 1], se2.between(path[k], path[k + 1]), NOISE, ids, estimates,
                     range_bearing(path[k + 1], lms[ids]))
            known.update(int(j) for j in ids)
        covs.append(lin.pose_cov())
    np.testing.assert_allclose(covs[0], covs[1], rtol=1e-12)


def test_reported_covariance_adds_only_what_the_particles_miss():
    lin = LinearisedMarginal(np.zeros(3), R)
    lin.predict(np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), NOISE)
    L = lin.pose_cov()
    np.testing.assert_allclose(lin.reported_pose_cov(L), L, atol=1e-15)        # cloud spans the posterior
    np.testing.assert_allclose(lin.reported_pose_cov(np.zeros((3, 3))), 2 * L)  # cloud fully collapsed
    np.testing.assert_allclose(lin.reported_pose_cov(5 * L), L, atol=1e-15)    # wider cloud: never below L
    # a cloud wider in one eigen-direction and collapsed in the others: only the collapsed ones are added
    w, v = np.linalg.eigh(L)
    c = (v * (w * np.array([0.0, 0.0, 3.0]))) @ v.T
    np.testing.assert_allclose(lin.reported_pose_cov(c), (v * (w * np.array([2.0, 2.0, 1.0]))) @ v.T, atol=1e-15)


def _run(overrides: dict, steps: int = 40, seed: int = 3) -> list:
    log = simulate("room", seed, steps=steps)
    est = make_estimator("fastslam2", {"particles": 30, **overrides}, log.metadata)
    est.reset(log.initial_pose, rng=np.random.default_rng(7))
    out = []
    for step in log.head(steps):
        est.step(step)
        out.append(est.estimate())
    return out


def test_linearised_option_changes_the_covariance_only():
    a, b = _run({}), _run({"pose_cov": "linearised"})
    for sa, sb in zip(a, b, strict=True):
        np.testing.assert_array_equal(sa.pose, sb.pose)
        np.testing.assert_array_equal(sa.landmarks, sb.landmarks)
        np.testing.assert_array_equal(sa.particles.poses, sb.particles.poses)
        assert np.all(np.linalg.eigvalsh(sb.pose_cov) > 0)
    # the particle spread stops growing while the linearised marginal keeps the map's drift
    assert np.trace(b[-1].pose_cov) > 1.5 * np.trace(a[-1].pose_cov)


def test_linearised_option_rejects_per_particle_association_and_bad_values():
    with pytest.raises(ValueError, match="pose_cov"):
        FastSLAM2Config(pose_cov="ekf")
    est = FastSLAM(FastSLAM2Config(pose_cov="linearised", association=AssociationConfig(method="mahalanobis")))
    est.reset(np.zeros(3), rng=np.random.default_rng(0))
    step = Step(0, 0.0, 1.0, np.array([0.1, 0.0, 0.0]), Observations(np.array([2.0]), np.array([0.1]),
                                                                     np.array([-1])))
    with pytest.raises(ValueError, match="pose_cov='linearised' needs known association"):
        est.step(step)
