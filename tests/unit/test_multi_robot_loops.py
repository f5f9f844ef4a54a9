"""Each robot's loop closures in the joint graph (slam2d.graph.multi_robot_loops): keyframes, verification when the
keyframe is taken, the gate deferred to the next solve."""

from __future__ import annotations

import numpy as np

from slam2d.frontend.place_recognition import PlaceRecognitionConfig
from slam2d.geometry import se2
from slam2d.graph.multi_robot_loops import RobotLoops
from slam2d.models.sensors import range_bearing

R = np.diag([0.05**2, 0.01**2])
LANDMARKS = np.array([[3.0, -1.0], [4.0, 0.5], [5.0, 1.5], [3.5, 2.0], [6.0, -0.5], [4.5, -2.0], [5.5, 0.0]])


def _seen(pose: np.ndarray) -> np.ndarray:
    return range_bearing(pose, LANDMARKS)


def _loops() -> RobotLoops:
    return RobotLoops(2, PlaceRecognitionConfig(), 0.999, keyframe_every=5, rng=np.random.default_rng(0))


def test_a_revisit_is_verified_then_gated_against_the_estimate():
    a, b = np.array([0.0, 0.0, 0.0]), np.array([0.3, -0.2, 0.1])  # robot 1 (index 1) back at its place
    loops = _loops()
    loops.observe(1, 10, 10_000_010, _seen(a), R)
    loops.observe(1, 12, 10_000_012, _seen(b), R)  # too soon after the last keyframe: ignored
    assert not loops.pending
    loops.observe(1, 100, 10_000_100, _seen(b), R)
    assert [(p.robot, p.a, p.b) for p in loops.pending] == [(1, 10_000_010, 10_000_100)]
    np.testing.assert_allclose(loops.pending[0].hypothesis.T_a_b, se2.between(a, b), atol=1e-6)
    assert loops.keys().tolist() == [10_000_010, 10_000_100]
    poses = {10_000_010: a, 10_000_100: b}
    cov = np.eye(6) * 1e-3
    found = loops.gate(poses.__getitem__, lambda i, j: cov)
    assert [(c.a, c.b) for c in found] == [(10_000_010, 10_000_100)] and loops.accepted == 1
    assert not loops.pending


def test_the_gate_rejects_a_loop_the_estimate_contradicts_and_robots_keep_their_own_keyframes():
    a, b = np.array([0.0, 0.0, 0.0]), np.array([0.3, -0.2, 0.1])
    loops = _loops()
    loops.observe(0, 10, 10, _seen(a), R)
    loops.observe(1, 100, 10_000_100, _seen(b), R)  # another robot: never a candidate of robot 0's keyframes
    assert not loops.pending
    loops.observe(0, 100, 100, _seen(b), R)
    assert len(loops.pending) == 1
    far = {10: a, 100: se2.compose(b, np.array([2.0, 0.0, 0.0]))}  # the estimate puts b 2 m elsewhere
    assert loops.gate(far.__getitem__, lambda i, j: np.eye(6) * 1e-3) == []
    assert loops.rejected == 1 and loops.accepted == 0
