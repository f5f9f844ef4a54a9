"""LoopCloser on generic inputs: keyframe points, pose estimates and a joint-covariance callable."""

from __future__ import annotations

import numpy as np

from slam2d.frontend.loop_closure import MAX_QUEUED, LoopCloser
from slam2d.frontend.place_recognition import PlaceRecognitionConfig
from slam2d.geometry import se2


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts_a = rng.uniform(-6, 6, (14, 2))
    pose_b = np.array([1.0, 0.5, 0.3])  # pose b in frame a (a is the origin)
    pts_b = se2.inverse_transform_points(pose_b, pts_a) + 0.01 * rng.normal(size=(14, 2))
    return pts_a, pts_b, pose_b


def test_a_revisit_is_verified_and_accepted_when_the_estimate_agrees():
    rng = np.random.default_rng(0)
    pts_a, pts_b, pose_b = _scene(rng)
    covs = np.broadcast_to(1e-4 * np.eye(2), (14, 2, 2))
    lc = LoopCloser(PlaceRecognitionConfig(), 0.999, rng)
    assert lc.add_keyframe(0, pts_a, covs)
    poses = {0: np.zeros(3), 50: pose_b + [0.05, -0.05, 0.01]}
    asked = []

    def joint(a: int, b: int) -> np.ndarray:
        asked.append((a, b))
        return np.diag([0.0, 0.0, 0.0, 0.01, 0.01, 0.001])

    found = lc.try_close(50, pts_b, covs, poses.__getitem__, joint)
    assert len(found) == 1 and found[0].accepted and (found[0].a, found[0].b) == (0, 50)
    np.testing.assert_allclose(found[0].T_a_b, pose_b, atol=0.02)
    assert asked == [(0, 50)] and 50 in lc.keyframes  # marginal asked once; the new keyframe is stored
    ev = found[0].event
    assert ev.accepted and ev.a == 0 and ev.b == 50


def test_a_look_alike_far_from_the_estimate_is_rejected_by_the_gate():
    rng = np.random.default_rng(1)
    pts_a, pts_b, pose_b = _scene(rng)
    covs = np.broadcast_to(1e-4 * np.eye(2), (14, 2, 2))
    lc = LoopCloser(PlaceRecognitionConfig(), 0.999, rng)
    lc.add_keyframe(0, pts_a, covs)
    poses = {0: np.zeros(3), 50: pose_b + [3.0, 0.0, 0.0]}  # the estimate says: 3 m elsewhere, and is sure of it
    found = lc.try_close(50, pts_b, covs, poses.__getitem__, lambda a, b: 1e-4 * np.eye(6), add_keyframe=False)
    assert len(found) == 1 and not found[0].accepted and found[0].d2 > 100
    assert 50 not in lc.keyframes
    # too recent (min_separation) or too few points: nothing is proposed
    assert lc.try_close(10, pts_b, covs, poses.__getitem__, lambda a, b: np.eye(6)) == []
    assert lc.propose(60, pts_b[:3]) == []


def _keyframes(n: int, rng: np.random.Generator) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """A drive past the same 30 landmarks twice: keyframe k at pose (0.2 k mod 6, 0, 0), its points in its frame."""
    world = rng.uniform(-8, 8, (30, 2))
    out = []
    for k in range(n):
        pose = np.array([0.4 * (k % 15), 0.1 * (k % 15), 0.0])
        pts = se2.inverse_transform_points(pose, world) + 0.01 * rng.normal(size=world.shape)
        out.append((10 * k, pts, pose))
    return out


def test_queued_verification_makes_the_same_decisions_as_try_close_spread_over_calls():
    """queue + verify_queued (one candidate per call) decide exactly what try_close decides for each keyframe, in
    the same order and with the same transforms; each call verifies at most its budget."""
    frames = _keyframes(40, np.random.default_rng(3))
    covs = np.broadcast_to(1e-4 * np.eye(2), (30, 2, 2))
    poses = {key: pose for key, _, pose in frames}

    def joint(a: int, b: int) -> np.ndarray:
        return np.diag([0.0, 0.0, 0.0, 0.01, 0.01, 0.001])

    direct = LoopCloser(PlaceRecognitionConfig(), 0.999, np.random.default_rng(7))
    spread = LoopCloser(PlaceRecognitionConfig(), 0.999, np.random.default_rng(7))
    verified: list[int] = []
    real_verify = spread.verify
    spread.verify = lambda a, p, c: verified.append(a) or real_verify(a, p, c)  # type: ignore[method-assign]
    want, got = [], []
    for key, pts, _ in frames:
        want += [(c.a, c.b, c.accepted, tuple(c.T_a_b)) for c in direct.try_close(key, pts, covs, poses.__getitem__,
                                                                                   joint)]
        spread.queue(key, pts, covs)
        while spread.queued:
            n = len(verified)
            got += [(c.a, c.b, c.accepted, tuple(c.T_a_b)) for c in spread.verify_queued(poses.__getitem__, joint)]
            assert len(verified) - n <= 1
    assert sum(w[2] for w in want) >= 10  # the second pass closes loops
    assert got == want


def test_the_queue_is_bounded_and_drops_the_oldest_candidates():
    frames = _keyframes(40, np.random.default_rng(3))
    covs = np.broadcast_to(1e-4 * np.eye(2), (30, 2, 2))
    lc = LoopCloser(PlaceRecognitionConfig(), 0.999, np.random.default_rng(7))
    for key, pts, _ in frames:
        lc.queue(key, pts, covs)
        assert len(lc.queued) <= MAX_QUEUED
    assert len(lc.queued) == MAX_QUEUED and lc.queued[-1][1] == frames[-1][0]  # the newest keyframe's are kept
