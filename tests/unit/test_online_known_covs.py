"""Online graph SLAM with known association refreshes its landmark covariances at every optimisation (the landmarks
near the newest pose, the rule of the unknown-association path; all of them in finalize), so re-sightings and loop
closures shrink them; before, they stayed at their first-sighting value forever."""

import numpy as np
import pytest

import slam2d
from slam2d.graph.marginals import marginal_covariances
from slam2d.graph.online import GraphSLAM
from slam2d.lab.registry import make_config
from slam2d.sim.simulator import spawn_streams


def _blocks(joint, n):
    idx = 2 * np.arange(n)[:, None] + np.arange(2)
    return joint[idx[:, :, None], idx[:, None, :]]


def _drive(log, **over):
    est = GraphSLAM(make_config("graph", {"association.method": "known", **over}, log.metadata))
    est.reset(log.initial_pose, rng=spawn_streams(0)["estimator"])
    first: dict[int, np.ndarray] = {}  # each landmark's covariance when it first appeared
    for step in log:
        est.step(step)
        e = est.estimate()
        for k, c in zip(e.landmark_ids.tolist(), e.landmark_covs, strict=True):
            first.setdefault(k, c.copy())
    return est, first


def _traces(covs):
    return np.trace(covs, axis1=1, axis2=2)


def _ratio(est, first):
    """Each landmark's covariance trace now over its trace when it first appeared (estimate order)."""
    e = est.estimate()
    return _traces(e.landmark_covs) / _traces(np.array([first[k] for k in e.landmark_ids.tolist()]))


def test_whole_graph_mode_sets_the_near_landmarks_to_their_exact_marginals():
    log = slam2d.simulate("loop", seed=3, steps=480)  # one lap and a bit: the start is seen again
    est, first = _drive(log, optimize_every=10)
    assert est.index % 10 == 0  # the last step optimised
    near = est._near_points(False)
    assert 5 <= near.size < est.values.point_keys.size  # a bounded refresh, not all of them
    exact = _blocks(marginal_covariances(est.graph, est.values, [], near).joint, near.size)
    np.testing.assert_allclose(est.point_covs[est._point_rows(near)], exact, rtol=1e-6, atol=1e-12)
    ratio = _ratio(est, first)
    assert np.all(ratio <= 1 + 1e-9)  # never larger than at creation: information only adds up
    assert np.median(ratio[np.isin(est.estimate().landmark_ids, near)]) < 0.8  # on main: exactly 1
    est.finalize()  # every landmark refreshed
    all_exact = _blocks(marginal_covariances(est.graph, est.values, [], est.values.point_keys).joint,
                        est.values.point_keys.size)
    np.testing.assert_allclose(est.point_covs, all_exact, rtol=1e-6, atol=1e-12)
    assert np.median(_ratio(est, first)) < 0.8


@pytest.mark.slow
def test_window_mode_covariances_shrink_after_loops_and_stay_conservative():
    """The lab's setting (window 20) with loop closure: after two laps the landmarks are far tighter than at
    creation, and never tighter than the whole graph's exact marginals."""
    log = slam2d.simulate("loop", seed=0, steps=940)
    est, first = _drive(log, window=20, loop_closure="true")
    assert est.estimate().diagnostics.loops_accepted > 0
    e = est.estimate()
    ratio = _ratio(est, first)
    assert np.median(ratio) < 0.5, np.median(ratio)
    order = np.argsort(est.values.point_keys)
    exact = _blocks(marginal_covariances(est.graph, est.values, [], est.values.point_keys[order]).joint,
                    order.size)
    assert np.all(_traces(e.landmark_covs) >= 0.99 * _traces(exact))
