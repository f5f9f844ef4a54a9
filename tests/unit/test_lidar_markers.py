"""Floor markers in the lidar back end (slam2d.graph.lidar_markers): the factor, an exact small case, identity."""

import numpy as np
import pytest

from slam2d import _jacobians
from slam2d.geometry import se2
from slam2d.graph.factors import KINDS
from slam2d.graph.incremental import IncrementalConfig, IncrementalPoseGraph
from slam2d.graph.lidar_markers import KeyframeMarkers, MarkerPoseGraph, MarkerSettings
from slam2d.log import MarkerReadings
from slam2d.models.floor_markers import FloorCameraConfig, marker_in_robot
from slam2d.testing import assert_jacobian_matches

CFG = IncrementalConfig(window=10, loop_neighbourhood=2, iterations=3, full_every=1000)


def test_marker_factor_is_the_registered_point_factor_and_its_jacobian_passes_finite_differences():
    g = MarkerPoseGraph(np.zeros(3), CFG)
    g.add_step(1, np.array([0]), np.array([1]), np.array([[1.0, 0.0, 0.3]]), np.eye(3)[None] * 100)
    z = np.array([0.4, -0.2])
    g.add_marker_observations(1, np.array([7]), z[None], (np.eye(2) / 0.01**2)[None])
    graph, _, _ = g._with_markers(g.graph(), np.arange(1))
    block = graph.block("point")
    assert np.allclose(block.information[0], np.eye(2) / 0.01**2)
    # the factor's error is the marker model minus the reading, at any estimate
    pose, m = np.array([0.3, -0.5, 2.9]), np.array([1.2, 0.7])
    e, _ = KINDS["point"].evaluate(pose[:, None], m[:, None], z[:, None])
    assert np.allclose(e[:, 0], marker_in_robot(pose, m) - z)
    pair = next(p for p in _jacobians.registry() if p.name == "slam2d.graph.factors.point_error")
    rng = np.random.default_rng(3)
    for edge in ("random", "pi", "-pi"):
        args = [_jacobians.sample_arg(k, rng, edge) for k in pair.arg_kinds]
        analytic = pair.jacobians(*args, z=z)
        for i, kind in enumerate(pair.arg_kinds):
            def f(xi, i=i, args=args):
                a = list(args)
                a[i] = xi
                return pair.function(*a, z=z)
            assert_jacobian_matches(f, args[i], analytic[i], input_angles=_jacobians.ARG_KINDS[kind][1],
                                    output_angles=(), rtol=1e-5, atol=1e-6)


def _square(n_side=12, step=0.5):
    """True poses of a square drive (4 sides of n_side steps, turning left at each corner), back at the start."""
    poses = [np.zeros(3)]
    for side in range(4):
        for k in range(n_side):
            turn = np.pi / 2 if k == n_side - 1 else 0.0
            poses.append(se2.compose(poses[-1], np.array([step, 0.0, turn])))
        del side
    return np.array(poses)


def _drive(markers_on: bool):
    """Odometry with a scale and heading bias (drift), markers 0 and 1 near the start read at the start and at the
    end. Returns (graph, true poses, KeyframeMarkers)."""
    truth = _square()
    marks = np.array([[0.3, 0.4], [0.6, -0.3]])
    cam = FloorCameraConfig(std_m=0.01)
    km = KeyframeMarkers(MarkerSettings(camera=cam, resight_keyframes=20, full_iterations=10))
    g = MarkerPoseGraph(truth[0], CFG)
    info = np.diag([0.02**-2, 0.02**-2, 0.01**-2])[None]
    resolved = []
    for t in range(len(truth)):
        if t:
            z = se2.between(truth[t - 1], truth[t]) * np.array([1.05, 1.0, 1.0]) + np.array([0.0, 0.0, 0.01])
            g.add_step(t, np.array([t - 1]), np.array([t]), z[None], info)
        xy = marker_in_robot(truth[t], marks)
        seen = np.hypot(*xy.T) <= 1.0
        if markers_on and seen.any():
            resolved.append(km.observe(g, t, np.zeros(3), MarkerReadings(xy[seen], np.flatnonzero(seen))))
    return g, truth, km, resolved


def _end_error(g, truth, k=-1):
    """Error of keyframe ``k`` relative to keyframe 0 (a local solve may move the whole graph: gauge freedom)."""
    e = se2.between(g.poses[0], g.poses[k]) - se2.between(truth[0], truth[k])
    return float(np.hypot(e[0], e[1]))


def test_square_drive_with_drift_end_error_drops_to_marker_noise_only_with_markers():
    g_off, truth, _, _ = _drive(False)
    g_on, _, km, resolved = _drive(True)
    online = _end_error(g_on, truth, -2)  # at the last re-sighting's solve, before finalize
    g_off.finalize()
    g_on.finalize()
    end_off, end_on = _end_error(g_off, truth), _end_error(g_on, truth)
    assert end_off > 0.5  # the drift: heading bias (0.5 rad in all) and 5 % scale over 24 m
    assert end_on < 0.03 and online < 0.05  # readings of 1 cm noise pin the end pose to within 3 sigma
    assert km.resightings >= 1 and resolved[-1] is False and any(resolved)  # solved once, at the first re-sighting
    in_first = se2.inverse_transform_points(g_on.poses[0], g_on.markers[np.argsort(g_on.marker_ids)])
    assert np.allclose(in_first, [[0.3, 0.4], [0.6, -0.3]], atol=0.02)


def test_without_marker_readings_the_graph_is_the_incremental_pose_graph_exactly():
    rng = np.random.default_rng(0)
    a, b = IncrementalPoseGraph(np.zeros(3), CFG), MarkerPoseGraph(np.zeros(3), CFG)
    info = np.diag([400.0, 400.0, 1e4])
    for t in range(1, 60):
        z = np.array([0.5, 0.0, 0.1]) + rng.normal(0, 0.01, 3)
        ei, ej, ez = [t - 1], [t], [z]
        if t % 17 == 0:  # a loop to an old pose
            ei.append(t - 15)
            ej.append(t)
            ez.append(se2.between(a.poses[t - 15], se2.compose(a.poses[t - 1], z)))
        for g in (a, b):
            g.add_step(t, np.array(ei), np.array(ej), np.array(ez), np.repeat(info[None], len(ei), axis=0))
    a.finalize()
    b.finalize()
    assert np.array_equal(a.poses, b.poses) and (a.local_solves, a.full_solves) == (b.local_solves, b.full_solves)


def test_readings_between_keyframes_attach_through_the_tracked_offset():
    g = MarkerPoseGraph(np.array([1.0, 2.0, 0.5]), CFG)
    km = KeyframeMarkers(MarkerSettings(camera=FloorCameraConfig(std_m=0.01), attach_sigma_per_m=0.02))
    rel = np.array([0.3, 0.0, 0.1])
    km.observe(g, 0, rel, MarkerReadings(np.array([[0.5, 0.2]]), np.array([4])))
    km.observe(g, 0, np.zeros(3), MarkerReadings(np.array([[0.5, 0.2]]), np.array([4])))  # same pair: kept once
    assert g.num_observations == 1 and km.readings == 2
    expect = se2.transform_points(se2.compose(g.poses[0], rel), np.array([[0.5, 0.2]]))
    assert np.allclose(g.markers, expect)
    assert g._o_info[0][0, 0] == pytest.approx(1 / (0.01**2 + (0.02 * 0.3) ** 2))


def test_lidar_estimator_uses_readings_and_is_unchanged_without_them():
    """On one simulated warehouse log with floor markers: ignoring the readings (``markers.enabled=False``) and
    a log without them give the same trajectory bit for bit; using them adds marker factors and moves it."""
    from dataclasses import replace

    from slam2d.graph.lidar import LidarSLAM, LidarSLAMConfig
    from slam2d.sim.scenarios import ScenarioConfig
    from slam2d.sim.simulator import simulate
    from slam2d.sim.warehouse import WarehouseConfig

    log = simulate(ScenarioConfig(name="warehouse", steps=150, warehouse=WarehouseConfig(floor_markers=True)), seed=3)

    def run(cfg, strip):
        est = LidarSLAM(cfg)
        est.reset(log.initial_pose, rng=np.random.default_rng(0))
        for s in log:
            est.step(replace(s, markers=None) if strip else s)
        est.finalize()
        return est

    off = run(LidarSLAMConfig(markers=MarkerSettings(enabled=False)), False)
    none = run(LidarSLAMConfig(), True)
    on = run(LidarSLAMConfig(), False)
    assert np.array_equal(off.trajectory(), none.trajectory()) and off.markers.factors == 0
    assert on.markers.factors > 0 and on.graph.num_observations == on.markers.factors
    assert not np.array_equal(on.trajectory(), none.trajectory())
    truth = log.true_markers[np.asarray(on.graph.marker_ids)]
    assert np.abs(on.graph.markers - truth).max() < 0.5  # placed where they are, up to the drift so far
