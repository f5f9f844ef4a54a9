"""Association metrics, the scramble scenario, the standalone experiment and `slam2d experiment association`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from slam2d.association import CLUTTER, NEW
from slam2d.cli.main import main
from slam2d.eval.association import AssociationCounts, association_counts
from slam2d.lab.association_experiment import AssociationExperimentConfig, run_association_experiment
from slam2d.sim import simulate
from slam2d.sim.scenarios import SCENARIOS


def test_counts_and_ratios_on_a_hand_made_batch():
    # truth:        5    6    7    8    -1   9 (not offered)   6
    # assignment:   5    7   NEW   8     5   6                 CLUTTER
    true_ids = [5, 6, 7, 8, -1, 9, 6]
    assignment = [5, 7, NEW, 8, 5, 6, CLUTTER]
    c = association_counts(true_ids, assignment, candidate_ids=[5, 6, 7, 8])
    assert c.observations == 7
    assert c.matchable == 5  # 5, 6, 7, 8, 6
    assert c.matches == 5  # 5, 7, 8, 5, 6
    assert c.correct == 2  # obs 0 and 3
    assert c.false_new == 1  # obs 2
    assert c.unmatchable_landmark == 1 and c.wrongly_merged == 1  # landmark 9 folded into 6
    assert c.precision == pytest.approx(2 / 5)
    assert c.recall == pytest.approx(2 / 5)
    assert c.false_new_rate == pytest.approx(1 / 5)
    assert c.missed_new_rate == 1.0
    pooled = c + association_counts([1], [1], [1])
    assert pooled.correct == 3 and pooled.matches == 6 and pooled.precision == pytest.approx(3 / 6)


def test_ratios_are_nan_when_undefined_and_lengths_must_agree():
    c = association_counts([-1, -1], [NEW, CLUTTER], candidate_ids=[])
    assert math.isnan(c.precision) and math.isnan(c.recall) and math.isnan(c.false_new_rate)
    assert AssociationCounts().as_dict()["observations"] == 0
    with pytest.raises(ValueError, match="same length"):
        association_counts([1, 2], [1], [1])


def test_scramble_scenario_packs_landmarks_inside_the_gates():
    assert "scramble" in SCENARIOS
    log = simulate("scramble", 3, steps=40)
    lm = log.true_landmarks
    assert lm is not None and len(lm) == 48
    d = np.hypot(*(lm[:, None] - lm[None]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    nearest = d.min(axis=1)
    # every landmark has a neighbour within 0.2-0.8 m: 2-8 range standard deviations (0.1 m), and at 5 m range
    # 2-8 bearing standard deviations (0.02 rad); the 99 % gate of one sighting is ~3 standard deviations wide
    assert nearest.min() >= 0.2 - 1e-9 and np.median(nearest) < 0.5 and nearest.max() < 1.0
    assert simulate("scramble", 3, steps=40).equals(log)


@pytest.mark.slow
def test_scramble_jcbb_and_ransac_precision_clearly_above_nearest_neighbour():
    cfg = AssociationExperimentConfig(snapshots_per_seed=4, steps=300, methods=("nn", "mahalanobis", "jcbb",
                                                                                  "ransac"))
    res = run_association_experiment(cfg, seeds=range(100, 106)).by_method()
    nn, jcbb, ransac = res["nn"].counts, res["jcbb"].counts, res["ransac"].counts
    assert nn.matchable > 300  # enough sightings for the ratios to mean something
    assert nn.precision < 0.6
    assert jcbb.precision > 0.9 and jcbb.precision > nn.precision + 0.3
    assert ransac.precision > 0.85 and ransac.precision > nn.precision + 0.3
    assert jcbb.recall > nn.recall + 0.3 and ransac.recall > nn.recall + 0.3
    # every seed, not just the pool
    assert min(res["jcbb"].seed_precision) > max(res["nn"].seed_precision)


def test_experiment_command_prints_a_table_and_writes_json(tmp_path, capsys):
    out = tmp_path / "assoc.json"
    argv = ["experiment", "association", "--seeds", "2", "--set", "snapshots_per_seed=2", "--set", "steps=60",
            "--set", "methods=known,nn,jcbb", "--json", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "precision" in text and "jcbb" in text
    rec = json.loads(out.read_text())
    assert rec["experiment"] == "association" and rec["seeds"] == [0, 1]
    rows = {r["method"]: r for r in rec["methods"]}
    assert set(rows) == {"known", "nn", "jcbb"}
    assert rows["known"]["precision"] == 1.0 and rows["known"]["recall"] == 1.0


def test_experiment_command_rejects_bad_settings(capsys):
    assert main(["experiment", "association", "--seeds", "1", "--set", "pose_std_xy_m=-1"]) == 2
    assert "pose_std_xy_m" in capsys.readouterr().err
    assert main(["experiment", "association", "--seeds", "1", "--set", "methods=nn,magic"]) == 2
    assert "methods" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["experiment", "nope"])
