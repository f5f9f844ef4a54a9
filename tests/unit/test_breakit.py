import dataclasses

import numpy as np
import pytest

import slam2d
from slam2d.lab.breakit import corrupt_association, forget_revisits, thin_landmarks


def _tiny_log():
    log = slam2d.simulate("room", seed=0, steps=5)
    steps = np.array([1, 2, 3, 50, 51, 200, 2, 3], dtype=np.int64)
    ids = np.array([0, 0, 0, 0, 0, 0, 1, 1], dtype=np.int64)
    order = np.argsort(steps, kind="stable")
    t = 200
    return dataclasses.replace(
        log, stamps_s=np.arange(t + 1) * 0.1, odometry=np.zeros((t, 3)), true_poses=np.zeros((t + 1, 3)),
        obs_step=steps[order], obs_range_m=np.ones(8), obs_bearing_rad=np.zeros(8), obs_id=ids[order],
        scan_step=None, scan_ranges_m=None, scan_angles_rad=None, dynamic_xy=None)


def test_forget_revisits_rekeys_exactly_after_gaps():
    log = _tiny_log()
    out = forget_revisits(log, gap_steps=10)
    keys = zip(log.obs_step.tolist(), log.obs_id.tolist(), strict=True)
    by_step = dict(zip(keys, out.obs_id.tolist(), strict=True))
    assert by_step[(1, 0)] == by_step[(2, 0)] == by_step[(3, 0)] == 0
    assert by_step[(50, 0)] == by_step[(51, 0)] == 2  # second visit of landmark 0: 0 + span(2) * 1
    assert by_step[(200, 0)] == 4  # third visit
    assert by_step[(2, 1)] == by_step[(3, 1)] == 1  # landmark 1 never left
    with pytest.raises(ValueError):
        forget_revisits(log, 0)


def test_corrupt_association_changes_the_requested_fraction_to_wrong_ids():
    log = slam2d.simulate("room", seed=3)
    out = corrupt_association(log, 0.5, np.random.default_rng(0))
    real = log.obs_id >= 0
    changed = out.obs_id[real] != log.obs_id[real]
    assert 0.45 < changed.mean() < 0.55
    assert np.all(np.isin(out.obs_id[real], log.obs_id[real]))  # wrong but valid ids
    np.testing.assert_array_equal(out.obs_id[~real], log.obs_id[~real])


def test_thin_landmarks_keeps_one_in_five():
    log = slam2d.simulate("loop", seed=1)
    out = thin_landmarks(log, 0.2, np.random.default_rng(0))
    kept = np.unique(out.obs_id[out.obs_id >= 0])
    assert len(kept) == 20
    assert sum(len(s.observations) for s in out) == len(out.obs_step)


def test_breakit_experiment_damages_every_back_end():
    from slam2d.lab.breakit import CONDITIONS, breakit_experiment

    rows = breakit_experiment(("ekf", "graph"), (0,), "room", steps=80)
    assert len(rows) == 2 * len(CONDITIONS)
    for est in ("ekf", "graph"):
        by = {r["condition"]: r for r in rows if r["estimator"] == est}
        # half the associations wrong is far worse than the baseline for every back end
        assert by["wrong-association"]["ate_mean_m"] > 5 * by["baseline"]["ate_mean_m"]
        assert by["baseline"]["ate_mean_m"] < 0.2
