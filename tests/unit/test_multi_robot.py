"""Multi-robot graph SLAM: map merging maths, the composed-odometry covariance, and the joint graph on a simulated
fleet (known/unknown starts, known/unknown association), plus the CLI on a synthetic MRCLAM folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam2d.cli.main import main
from slam2d.estimator import EstimatorStateError
from slam2d.eval.trajectory import ate
from slam2d.geometry import se2
from slam2d.graph.factors import pose_range_bearing_error
from slam2d.graph.map_merge import find_merge, rigid_align
from slam2d.graph.multi_robot import MultiGraphSLAM, compose_with_covariance, config_from_log
from slam2d.lab.multi_robot import run_multi
from slam2d.log import Log
from slam2d.models.motion import MotionNoise, odometry_covariance, sample_odometry
from slam2d.models.sensors import SensorConfig, range_bearing
from slam2d.multi_log import MultiRobotLog, RobotSightings

MOTION = MotionNoise(alpha_rot_rot=0.02, alpha_rot_trans=0.005, alpha_trans_trans=0.02, alpha_trans_rot=0.005,
                     min_trans_std_m=1e-3, min_rot_std_rad=2e-3)
SENSOR = SensorConfig(max_range_m=6.0, fov_rad=2.0, range_std_m=0.05, bearing_std_rad=0.01)


def fleet(rng: np.random.Generator, n_robots: int = 3, steps: int = 900) -> MultiRobotLog:
    """Robots circling different centres in a 10 m room with 14 landmarks; noisy odometry, landmark and
    robot-robot sightings (range-bearing, in range and field of view), on one 0.1 s clock."""
    lm = rng.uniform(-5, 5, size=(14, 2))
    t = 0.1 * np.arange(steps + 1)
    logs, rows = [], []
    truth = []
    for r in range(n_robots):
        c = np.array([np.cos(2.1 * r), np.sin(2.1 * r)]) * 1.5
        rad, w = 2.0 + 0.4 * r, (0.25 + 0.05 * r) * (-1) ** r
        ph = w * t + r
        xy = c + rad * np.column_stack([np.cos(ph), np.sin(ph)])
        th = ph + np.sign(w) * np.pi / 2
        truth.append(np.column_stack([xy, np.angle(np.exp(1j * th))]))
    truth = np.array(truth)  # (R, T+1, 3)
    for r in range(n_robots):
        u_true = se2.between(truth[r, :-1], truth[r, 1:])
        u = np.array([sample_odometry(ut, MOTION, rng) for ut in u_true])
        z = range_bearing(truth[r, 1:, None, :], lm[None])  # (T, L, 2)
        vis = (z[..., 0] < SENSOR.max_range_m) & (np.abs(z[..., 1]) < SENSOR.fov_rad / 2) & \
            (rng.random(z.shape[:2]) < 0.3)
        st, li = np.nonzero(vis)
        zz = z[st, li] + rng.normal(size=(st.size, 2)) * [SENSOR.range_std_m, SENSOR.bearing_std_rad]
        meta = {"motion": {k: getattr(MOTION, k) for k in MOTION.__dataclass_fields__},
                "sensor": {k: getattr(SENSOR, k) for k in SENSOR.__dataclass_fields__}}
        logs.append(Log(t.copy(), u, (st + 1).astype(np.int64), zz[:, 0], zz[:, 1], li.astype(np.int64),
                        initial_pose=truth[r, 0].copy(), true_poses=truth[r], true_landmarks=lm,
                        true_landmark_ids=np.arange(len(lm)), metadata=meta))
        for b in range(n_robots):
            if b == r:
                continue
            zb = range_bearing(truth[r, 1:], truth[b, 1:, :2])
            ok = (zb[:, 0] < SENSOR.max_range_m) & (np.abs(zb[:, 1]) < SENSOR.fov_rad / 2) & \
                (rng.random(steps) < 0.1)
            k = np.flatnonzero(ok)
            noisy = zb[k] + rng.normal(size=(k.size, 2)) * [0.05, 0.01]
            rows += [(int(kk) + 1, r + 1, b + 1, float(n[0]), float(n[1])) for kk, n in zip(k, noisy, strict=True)]
    rows.sort()
    arr = np.array(rows)
    s = RobotSightings(arr[:, 0].astype(np.int64), arr[:, 1].astype(np.int64), arr[:, 2].astype(np.int64),
                       arr[:, 3], arr[:, 4])
    return MultiRobotLog(tuple(range(1, n_robots + 1)), tuple(logs), s,
                         {"sighting_noise": {"range_std_m": 0.05, "bearing_std_rad": 0.01}})


@pytest.fixture(scope="module")
def world() -> MultiRobotLog:
    return fleet(np.random.default_rng(4))


def test_composed_odometry_covariance_matches_step_by_step_propagation():
    rng = np.random.default_rng(0)
    u = np.column_stack([rng.uniform(0, 0.1, 30), rng.normal(0, 0.01, 30), rng.normal(0, 0.1, 30)])
    q = odometry_covariance(u, MOTION) + 1e-8 * np.eye(3)
    big_u, cov = compose_with_covariance(u, q)
    p, c = np.zeros(3), np.zeros((3, 3))
    for ui, qi in zip(u, q, strict=True):
        ja, jb = se2.compose_jacobians(p, ui)
        c = ja @ c @ ja.T + jb @ qi @ jb.T
        p = se2.compose(p, ui)
    np.testing.assert_allclose(big_u, p, atol=1e-12)
    np.testing.assert_allclose(cov, c, rtol=1e-10, atol=1e-15)
    z0, c0 = compose_with_covariance(np.zeros((0, 3)), np.zeros((0, 3, 3)))
    assert np.all(z0 == 0) and np.all(c0 == 0)


def test_pose_range_bearing_factor_is_zero_at_the_truth():
    xi, xj = np.array([1.0, 2.0, 0.5]), np.array([3.0, -1.0, 2.0])
    z = range_bearing(xi, xj[:2])
    np.testing.assert_allclose(pose_range_bearing_error(xi, xj, z), 0.0, atol=1e-12)
    # j's heading is not observed
    np.testing.assert_allclose(pose_range_bearing_error(xi, xj + [0, 0, 1.0], z), 0.0, atol=1e-12)


def test_rigid_align_recovers_an_exact_transform():
    rng = np.random.default_rng(1)
    T = np.array([1.5, -2.0, 2.8])
    pb = rng.uniform(-5, 5, size=(6, 2))
    np.testing.assert_allclose(rigid_align(pb, se2.transform_points(T, pb)), T, atol=1e-12)


def test_find_merge_verifies_and_rejects():
    rng = np.random.default_rng(2)
    T = np.array([0.7, 3.0, -1.2])
    pb = rng.uniform(-5, 5, size=(10, 2))
    cov = np.broadcast_to(0.01 * np.eye(2), (10, 2, 2))
    pa = se2.transform_points(T, pb) + rng.normal(size=(10, 2)) * 0.07
    pa[[2, 7]] += [3.0, -2.0]  # two wrong correspondences
    h = find_merge(pa, cov, pb, cov, rng=rng)
    assert h.accepted and set(h.inliers.tolist()) == set(range(10)) - {2, 7}
    assert np.hypot(*(h.T_a_b[:2] - T[:2])) < 0.1 and abs(h.T_a_b[2] - T[2]) < 0.03
    # too little evidence, too little spread, or an inconsistent set: rejected with a reason
    assert not find_merge(pa[:2], cov[:2], pb[:2], cov[:2], rng=rng).accepted
    close = pb[:4] * 0.05
    h2 = find_merge(se2.transform_points(T, close), cov[:4], close, cov[:4], rng=rng)
    assert not h2.accepted and "spread" in h2.reason
    tight = np.broadcast_to(1e-6 * np.eye(2), (10, 2, 2))  # claimed far more precise than the 7 cm noise
    assert not find_merge(pa, tight, pb, tight, rng=rng).accepted
    # unknown association: every pair is a candidate, the consensus is one-to-one and correct
    ia, ib = np.meshgrid(np.arange(10), np.arange(10), indexing="ij")
    ia, ib = ia.ravel(), ib.ravel()
    pa_ok = se2.transform_points(T, pb) + rng.normal(size=(10, 2)) * 0.03
    h3 = find_merge(pa_ok[ia], cov[ia], pb[ib], cov[ib], rng=rng, ambiguous=np.ones(100, bool), ids_a=ia, ids_b=ib,
                    iterations=500)
    # (a landmark with a second candidate inside the gate is left out rather than risked)
    assert h3.accepted and np.all(ia[h3.inliers] == ib[h3.inliers]) and h3.inliers.size >= 8


def test_lifecycle_and_config_errors(world):
    est = MultiGraphSLAM(config_from_log(world))
    with pytest.raises(EstimatorStateError):
        est.step(world.step(1))
    with pytest.raises(ValueError, match="known starts need initial_poses"):
        est.reset(None, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="node_every must be >= 1"):
        config_from_log(world, node_every=0)


def _dead_reckoning_ate(world: MultiRobotLog) -> list[float]:
    return [ate(se2.compose_chain(lg.initial_pose, lg.odometry), lg.true_poses).rmse_m for lg in world.logs]


def test_joint_graph_known_starts_uses_sightings_and_beats_dead_reckoning(world):
    res = run_multi(world)
    m = res.metrics
    dr = _dead_reckoning_ate(world)
    for i, r in enumerate(world.robots):
        assert m["ate_rmse_m"][str(r)] < 0.5 * dr[i], (r, m["ate_rmse_m"], dr)
    assert m["counters"]["sightings_used"] > 0.95 * len(world.sightings)
    assert m["map_matched"] == 14 and m["map_rmse_m"] < 0.1 and m["joint_ate_rmse_m"] < 0.15
    assert all(g == 0 for g in m["groups"])


def test_unknown_starts_merge_and_recover_the_start_transforms(world):
    m = run_multi(world, unknown_starts=True).metrics
    assert m["groups"] == [0, 0, 0] and m["counters"]["merges"] == 2
    for r in ("2", "3"):
        assert m["start_errors"][r]["translation_error_m"] < 0.1
        assert m["start_errors"][r]["rotation_error_rad"] < 0.03
    acc = [e for e in m["merges"] if e["accepted"]]
    assert all(e["chi2"] <= 2.5 * e["dof"] for e in acc)  # verified, not forced
    assert m["map_matched"] == 14 and m["map_rmse_m"] < 0.15


def test_unknown_association_and_unknown_starts(world):
    known_starts = run_multi(world, association="mahalanobis").metrics
    assert known_starts["map_matched"] == 14 and known_starts["map_rmse_m"] < 0.03
    assert known_starts["landmarks_estimated"] <= 15
    m = run_multi(world, unknown_starts=True, association="mahalanobis").metrics
    assert m["groups"] == [0, 0, 0]
    for r in ("2", "3"):
        assert m["start_errors"][r]["translation_error_m"] < 0.15
        assert m["start_errors"][r]["rotation_error_rad"] < 0.05
    # every true landmark is mapped once: the duplicates made before the frames were merged are fused
    assert m["map_matched"] == 14 and m["map_rmse_m"] < 0.03 and m["landmarks_estimated"] <= 15
    assert m["counters"]["landmarks_fused"] > 0
    dr = _dead_reckoning_ate(world)
    for i, r in enumerate(world.robots):
        assert m["ate_rmse_m"][str(r)] < 0.5 * dr[i]


def test_robust_landmark_kernel_without_ids_beats_plain_factors(world):
    """A sighting given to the wrong landmark pulls less through the kernel: a better map, fewer duplicates."""
    robust = run_multi(world, unknown_starts=True, association="mahalanobis").metrics
    plain = run_multi(world, unknown_starts=True, association="mahalanobis", landmark_robust_kernel="none").metrics
    assert robust["map_rmse_m"] < plain["map_rmse_m"]
    assert robust["landmarks_estimated"] < plain["landmarks_estimated"]
    with pytest.raises(ValueError, match="landmark_robust_kernel must be"):
        config_from_log(world, landmark_robust_kernel="tukey")


def test_cli_multi_graph_on_a_synthetic_mrclam_folder(tmp_path: Path, capsys):
    from test_multi_log import write_multi

    write_multi(tmp_path / "F", robots=(1, 2, 3, 4, 5), duration=8.0)
    out = tmp_path / "o.json"
    assert main(["run", "--dataset", "mrclam", "--dataset-path", str(tmp_path / "F"), "--robot", "all",
                 "--estimator", "multi-graph", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert set(rec["ate_rmse_m"]) == {"1", "2", "3", "4", "5"} and rec["map_matched"] == 3
    assert max(rec["ate_rmse_m"].values()) < 0.05  # exact measurements
    assert "joint" in capsys.readouterr().out
    assert main(["run", "--dataset", "mrclam", "--dataset-path", str(tmp_path / "F"), "--robot", "2",
                 "--estimator", "multi-graph"]) == 2
    assert "multi-robot runs need" in capsys.readouterr().err
