"""Floor-marker survey files: exact round trip, every malformed row named by file:line, and the CLI path from
``slam2d simulate --marker-survey`` to ``slam2d run --estimator lidar-lifelong --marker-survey``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slam2d.cli.main import main
from slam2d.config import with_overrides
from slam2d.graph.lidar_config import LifelongLidarConfig
from slam2d.io.survey import SurveyFormatError, read_marker_survey, write_marker_survey
from slam2d.sim.world import marker_survey

WAREHOUSE = ["--scenario", "warehouse-challenge", "--set", "warehouse.floor_markers=true", "--set", "dt_s=0.1",
             "--set", "steps=150"]


def test_round_trip_is_exact(tmp_path):
    rows = marker_survey(np.random.default_rng(1).uniform(-50, 50, (40, 2)), 0.01, np.random.default_rng(2))
    write_marker_survey(tmp_path / "s.csv", rows)
    assert read_marker_survey(tmp_path / "s.csv") == rows


def test_comments_blank_lines_and_spaces_are_allowed(tmp_path):
    (tmp_path / "s.csv").write_text("# surveyed 2026-11-30\n\nid,x,y\n3 1.5 -2\n 7, 0.25 ,4\n")
    assert read_marker_survey(tmp_path / "s.csv") == ((3, 1.5, -2.0), (7, 0.25, 4.0))


@pytest.mark.parametrize(("text", "where", "says"), [
    ("id,x,y\n1,2\n", ":2:", "3 fields"),
    ("1,2,3\nx,2,3\n", ":2:", "not an integer"),
    ("1.5,2,3\n", ":1:", "not an integer"),
    ("-1,2,3\n", ":1:", "negative"),
    ("1,2,abc\n", ":1:", "not a number"),
    ("1,nan,3\n", ":1:", "non-finite"),
    ("1,2,inf\n", ":1:", "non-finite"),
    ("1,2,3\n# c\n1,4,5\n", ":3:", "line 1"),
    ("# nothing\n\n", ":", "no marker rows"),
    ("1,2,3\n\xff\xfe,1,1\n", ":2:", "utf-8"),
])
def test_malformed_rows_are_named_by_file_and_line(tmp_path, text, where, says):
    (tmp_path / "s.csv").write_bytes(text.encode("latin-1"))
    with pytest.raises(SurveyFormatError, match=says) as e:
        read_marker_survey(tmp_path / "s.csv")
    assert f"s.csv{where}" in str(e.value)


def test_survey_rows_are_a_config_override_with_one_type_per_position():
    cfg = with_overrides(LifelongLidarConfig(), {"surveyed_markers": ((0, 1.5, 2.25), (3, 4.0, 5.0))})
    assert cfg.surveyed_markers == ((0, 1.5, 2.25), (3, 4.0, 5.0))
    with pytest.raises(ValueError, match="surveyed_markers must have 3 items"):
        with_overrides(LifelongLidarConfig(), {"surveyed_markers": ((0, 1.5),)})


def test_simulate_writes_a_survey_that_run_uses(tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["simulate", *WAREHOUSE, "--seed", "3", "--out", str(tmp_path / "w.npz"), "--marker-survey", str(out),
                 "--survey-sigma", "0.02"]) == 0
    rows = read_marker_survey(out)
    assert len(rows) > 20 and [r[0] for r in rows] == list(range(len(rows)))
    capsys.readouterr()
    assert main(["run", *WAREHOUSE, "--seed", "3", "--estimator", "lidar-lifelong", "--marker-survey", str(out),
                 "--json", str(tmp_path / "r.json")]) == 0
    rec = json.loads((tmp_path / "r.json").read_text())
    assert [list(r) for r in rec["estimator_config"]["surveyed_markers"]] == [list(r) for r in rows]
