import numpy as np
import pytest

from slam2d.models import (
    LidarConfig,
    MotionNoise,
    SensorConfig,
    cast_rays,
    odometry_covariance,
    odometry_to_rtr,
    range_bearing,
    range_bearing_inverse,
    rtr_to_odometry,
    sample_odometry,
    sense_clutter,
    sense_landmarks,
)
from slam2d.sim.world import box_walls


def test_rtr_round_trip():
    u = np.array([[0.5, 0.2, 0.3], [1.0, -0.3, -2.0], [0.0, 0.0, 0.4]])
    np.testing.assert_allclose(rtr_to_odometry(odometry_to_rtr(u)), u, atol=1e-12)


def test_odometry_covariance_matches_monte_carlo():
    u = np.array([1.0, 0.3, 0.4])
    noise = MotionNoise(alpha_rot_rot=0.01, alpha_rot_trans=0.002, alpha_trans_trans=0.01, alpha_trans_rot=0.001)
    samples = sample_odometry(np.broadcast_to(u, (40000, 3)), noise, np.random.default_rng(1))
    emp = np.cov(samples.T)
    np.testing.assert_allclose(emp, odometry_covariance(u, noise), rtol=0.08, atol=2e-5)


def test_motion_noise_validation_names_the_field():
    with pytest.raises(ValueError, match="alpha_trans_trans"):
        MotionNoise(alpha_trans_trans=-1.0)
    with pytest.raises(ValueError, match="range_std_m"):
        SensorConfig(range_std_m=-0.1)
    with pytest.raises(ValueError, match="max_range_m"):
        SensorConfig(max_range_m=0.0)
    with pytest.raises(ValueError, match="beams"):
        LidarConfig(beams=0)


def test_inverse_sensor_model_inverts_the_sensor():
    pose = np.array([5.0, 3.0, np.pi / 4])
    lm = range_bearing_inverse(pose, np.array([2.0, 0.0]))
    np.testing.assert_allclose(lm, [5 + np.sqrt(2), 3 + np.sqrt(2)], atol=1e-12)
    np.testing.assert_allclose(range_bearing(pose, lm), [2.0, 0.0], atol=1e-12)


def test_sensor_respects_range_fov_and_detection():
    pose = np.array([0.0, 0.0, 0.0])
    lms = np.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.0], [20.0, 0.0]])
    cfg = SensorConfig(max_range_m=5.0, fov_rad=np.pi)
    z, ids, _ = sense_landmarks(pose, lms, np.arange(4), cfg, np.random.default_rng(0))
    assert sorted(ids.tolist()) == [0, 1]  # behind and too far are not seen
    cfg0 = SensorConfig(detection_prob=0.0)
    z, ids, _ = sense_landmarks(pose, lms, np.arange(4), cfg0, np.random.default_rng(0))
    assert len(ids) == 0
    zc, _ = sense_clutter(SensorConfig(clutter_rate=50.0), np.random.default_rng(0))
    assert 25 < len(zc) < 80 and np.all(zc[:, 0] <= 8.0)


def test_sensor_noise_statistics():
    pose = np.array([1.0, 2.0, 0.3])
    lm = np.array([[4.0, 5.0]])
    cfg = SensorConfig(range_std_m=0.2, bearing_std_rad=0.05)
    rng = np.random.default_rng(3)
    zs = np.vstack([sense_landmarks(pose, lm, [0], cfg, rng)[0] for _ in range(4000)])
    err = zs - range_bearing(pose, lm)
    np.testing.assert_allclose(err.std(axis=0), [0.2, 0.05], rtol=0.05)
    np.testing.assert_allclose(err.mean(axis=0), [0, 0], atol=0.01)


def test_cast_rays_against_a_box():
    walls = box_walls(-2, -3, 4, 5)
    r = cast_rays(np.array([0.0, 0.0, 0.0]), np.array([0.0, np.pi / 2, np.pi, -np.pi / 2]), walls, 100.0)
    np.testing.assert_allclose(r, [4.0, 5.0, 2.0, 3.0])
    r = cast_rays(np.array([0.0, 0.0, np.pi / 2]), np.array([0.0]), walls, 4.0)
    np.testing.assert_allclose(r, [4.0])  # beyond max range -> max range
    assert np.all(cast_rays(np.zeros(3), np.linspace(-1, 1, 5), np.zeros((0, 4)), 7.0) == 7.0)
    # diagonal ray hits the corner region at the right distance
    r = cast_rays(np.array([0.0, 0.0, 0.0]), np.array([np.arctan2(5, 4)]), walls, 100.0)
    assert r[0] == pytest.approx(np.hypot(4, 5))
