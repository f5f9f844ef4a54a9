"""association="auto": known ids when the log has them, else AUTO_WITHOUT_IDS; resolved by the runner from the whole
log (and recorded as ``association_method``) or by a back end at its first step with observations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import slam2d
from slam2d.association import AssociationConfig, associate, resolve_method
from slam2d.association.base import AUTO_WITHOUT_IDS, Candidates
from slam2d.lab.registry import make_config, make_estimator
from slam2d.log import Observations

BACK_ENDS = ["ekf", "fastslam", "fastslam2", "graph"]


def _without_ids(log: slam2d.Log) -> slam2d.Log:
    return dataclasses.replace(log, obs_id=np.full_like(log.obs_id, -1))


def test_resolve_method() -> None:
    auto = AssociationConfig(method="auto", gate_probability=0.95)
    assert resolve_method(auto, True).method == "known"
    out = resolve_method(auto, False)
    assert out.method == AUTO_WITHOUT_IDS and out.gate_probability == 0.95
    jcbb = AssociationConfig(method="jcbb")
    assert resolve_method(jcbb, True) is jcbb
    obs = Observations(np.array([1.0]), np.array([0.0]), np.array([-1]))
    with pytest.raises(ValueError, match="auto"):
        associate(obs, Candidates.empty(), auto, rng=np.random.default_rng(0))


@pytest.mark.parametrize("name", BACK_ENDS)
def test_every_back_end_defaults_to_auto(name: str) -> None:
    assert make_config(name).association.method == "auto"
    assert make_config(name, has_ids=True).association.method == "known"
    assert make_config(name, has_ids=False).association.method == AUTO_WITHOUT_IDS
    assert make_config(name, {"association.method": "jcbb"}, has_ids=True).association.method == "jcbb"


@pytest.mark.parametrize("name", BACK_ENDS)
def test_runner_records_the_method_used(name: str) -> None:
    log = slam2d.simulate("room", 0, steps=12)
    over = {"particles": 5} if name.startswith("fastslam") else {}
    _, rec = slam2d.run_named(name, log=log, overrides=over)
    assert rec["association_method"] == "known" and rec["estimator_config"]["association"]["method"] == "known"
    _, rec = slam2d.run_named(name, log=_without_ids(log), overrides=over)
    assert rec["association_method"] == AUTO_WITHOUT_IDS
    _, rec = slam2d.run_named(name, log=log, overrides={**over, "association.method": "nn"})
    assert rec["association_method"] == "nn"
    _, rec = slam2d.run_named("dead-reckoning", log=log)
    assert rec["association_method"] is None


@pytest.mark.parametrize("name", BACK_ENDS)
def test_a_back_end_built_without_a_log_resolves_auto_at_its_first_observations(name: str) -> None:
    log = slam2d.simulate("room", 1, steps=8)
    over = {"particles": 5} if name.startswith("fastslam") else None
    for data, expect in ((log, "known"), (_without_ids(log), AUTO_WITHOUT_IDS)):
        est = make_estimator(name, over, data.metadata)
        est.reset(data.initial_pose, rng=np.random.default_rng(0))
        assert est.association_method == "auto"  # type: ignore[attr-defined]
        for step in data:
            est.step(step)
        assert est.association_method == expect  # type: ignore[attr-defined]
        snap = est.estimate()
        assert len(snap.landmarks) + len(snap.tentative_landmarks) > 0
