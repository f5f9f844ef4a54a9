"""QA pass on the CLI commands other than run/lidar: wrong types in config files, seeds that name their option, outputs
refused before the work, a learner's sys.exit(), empty graph files and g2o ids at the edge of int64."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam2d.cli.experiment import ScalingExperimentConfig
from slam2d.cli.main import main
from slam2d.config import with_overrides
from slam2d.graph.graph import FactorGraph, Values
from slam2d.io import GraphFormatError, read_graph
from slam2d.io.g2o import read_g2o, write_g2o
from slam2d.sim.scenarios import ScenarioConfig


def _one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


# ------------------------------------------------------------------------------------------- config values (TOML/JSON)
@pytest.mark.parametrize(("overrides", "field"), [
    ({"steps": True}, "ScenarioConfig.steps"),  # TOML `steps = true` is a mistake, not 1
    ({"dt_s": True}, "ScenarioConfig.dt_s"),
    ({"lidar.enabled": 2}, "ScenarioConfig.lidar.enabled"),  # not silently True
    ({"lidar.enabled": 0.5}, "ScenarioConfig.lidar.enabled"),
])
def test_config_refuses_values_of_the_wrong_type(overrides, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        with_overrides(ScenarioConfig(), overrides)


def test_config_scalar_for_a_list_field_names_the_field():
    with pytest.raises(ValueError, match=r"ScalingExperimentConfig\.landmarks must be a list"):
        with_overrides(ScalingExperimentConfig(), {"landmarks": 5})
    with pytest.raises(ValueError, match=r"ScalingExperimentConfig\.estimators must be a list"):
        with_overrides(ScalingExperimentConfig(), {"estimators": {"a": 1}})


def test_config_still_takes_the_usual_spellings():
    cfg = with_overrides(ScenarioConfig(), {"lidar.enabled": 0, "steps": 7.0, "dt_s": 1})
    assert cfg.lidar.enabled is False and cfg.steps == 7 and cfg.dt_s == 1.0
    assert with_overrides(ScenarioConfig(), {"lidar.enabled": "yes"}).lidar.enabled is True
    assert with_overrides(ScalingExperimentConfig(), {"landmarks": "10,20"}).landmarks == (10, 20)
    assert with_overrides(ScalingExperimentConfig(), {"landmarks": np.array([3, 4])}).landmarks == (3, 4)


def test_sweep_file_with_a_wrong_type_is_refused(tmp_path, capsys):
    toml = tmp_path / "s.toml"
    toml.write_text('estimators = ["dead-reckoning"]\nscenarios = ["room"]\nseeds = 1\n[set]\nsteps = true\n')
    assert main(["sweep", str(toml), "--out", str(tmp_path / "sw"), "--dry-run"]) == 2
    assert "steps must be of type int" in _one_error_line(capsys)


# ------------------------------------------------------------------------------------------------- seeds name options
@pytest.mark.parametrize(("argv", "option"), [
    (["demo", "--seed", "-1", "--out", "{d}/demo"], "--seed"),
    (["experiment", "loop-closure", "--seeds", "1", "--first-seed", "-1"], "--first-seed"),
    (["experiment", "loop-closure", "--seeds", "2", "--first-seed", str(2**63 - 1)], "--first-seed"),
    (["map", "save", "--scenario", "room", "--seed", "-1", "--out", "{d}/m.db"], "--seed"),
    (["map", "save", "--scenario", "room", "--keyframe-every-deg", "nan", "--out", "{d}/m.db"],
     "--keyframe-every-deg"),
])
def test_bad_seeds_and_spacings_name_their_option(argv, option, tmp_path, capsys):
    assert main([a.replace("{d}", str(tmp_path)) for a in argv]) == 2
    assert option in _one_error_line(capsys)
    assert not any(tmp_path.iterdir())


def test_drone_seed_names_its_option(capsys):
    pytest.importorskip("zmq")
    pytest.importorskip("msgpack")
    assert main(["drone", "--server", "127.0.0.1:1", "--drone", "0", "--seed", "-1"]) == 2
    assert "--seed" in _one_error_line(capsys)


# ------------------------------------------------------------------------------------- outputs refused before the work
def test_map_save_refuses_a_file_that_is_not_a_map_before_simulating(tmp_path, capsys, monkeypatch):
    import slam2d.cli.map as map_cli

    def no_simulation(*_a, **_k):
        raise AssertionError("simulated before checking --out")

    monkeypatch.setattr(map_cli, "simulate", no_simulation)
    target = tmp_path / "notes.txt"
    target.write_text("mine\n")
    assert main(["map", "save", "--scenario", "room", "--out", str(target)]) == 2
    line = _one_error_line(capsys)
    assert "not a slam2d map" in line and "refusing to overwrite" in line
    assert target.read_text() == "mine\n"
    # --replace-other-world allows replacing another world's map, never a file that is not a map: refused up front
    # too (it was found only when the map was written, after the run)
    assert main(["map", "save", "--scenario", "room", "--out", str(target), "--replace-other-world"]) == 2
    assert "not a slam2d map" in _one_error_line(capsys) and target.read_text() == "mine\n"
    assert main(["map", "save", "--scenario", "room", "--out", str(tmp_path / "sub" / "m.db")]) == 2
    assert "does not exist" in _one_error_line(capsys)


def test_breakit_figure_path_is_checked_before_the_runs(tmp_path, capsys, monkeypatch):
    import slam2d.lab.breakit as breakit

    def no_runs(*_a, **_k):
        raise AssertionError("ran before checking the figure path")

    monkeypatch.setattr(breakit, "breakit_experiment", no_runs)
    (tmp_path / "afile").write_text("x")
    assert main(["experiment", "breakit", "--seeds", "1", "--set", f"figure={tmp_path}/afile/b.png"]) == 2
    assert "figure" in _one_error_line(capsys)


# --------------------------------------------------------------------------------------------------------- exercise
@pytest.mark.parametrize(("source", "code"), [
    ("import sys\nsys.exit(0)\n", 2),
    ("import sys\ndef augment_state(mu, P, z_range, z_bearing, R_obs):\n    sys.exit(0)\n", 1),
])
def test_exercise_sys_exit_in_the_learners_file_is_not_a_pass(source, code, tmp_path, capsys):
    f = tmp_path / "mine.py"
    f.write_text(source)
    assert main(["exercise", "check", str(f), "--random", "1"]) == code
    out = capsys.readouterr()
    assert "SystemExit" in out.out + out.err


# ------------------------------------------------------------------------------------------------------ graph files
@pytest.mark.parametrize("fmt", ["g2o", "toro", "isam"])
@pytest.mark.parametrize("text", ["", "# a comment\n\n   \n"])
def test_an_empty_graph_file_is_a_format_error(fmt, text, tmp_path):
    p = tmp_path / "g.txt"
    p.write_text(text)
    name = {"g2o": "g2o", "toro": "TORO", "isam": "iSAM"}[fmt]
    with pytest.raises(GraphFormatError, match=rf"g\.txt: no {name} lines \(the file is empty"):
        read_graph(p, fmt)


def test_optimize_an_empty_file_says_so(tmp_path, capsys):
    p = tmp_path / "e.g2o"
    p.write_text("")
    assert main(["optimize", str(p), "--out", str(tmp_path / "o.g2o")]) == 2
    assert "e.g2o: no g2o lines" in _one_error_line(capsys)


def test_g2o_point_ids_near_int64_max_stay_readable(tmp_path):
    top = 2**63 - 1
    g = FactorGraph()
    g.add_between(np.array([top - 1]), np.array([top]), np.array([[1.0, 0, 0]]), np.eye(3)[None])
    g.add_point(np.array([top]), np.array([top]), np.array([[2.0, 0]]), np.eye(2)[None])
    values = Values(np.array([top - 1, top]), np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([top]),
                    np.array([[3.0, 0]]))
    shift = write_g2o(tmp_path / "o.g2o", g, values)
    assert shift == -2
    back = read_g2o(tmp_path / "o.g2o")
    np.testing.assert_array_equal(back.values.point_keys, [top - 2])
    np.testing.assert_array_equal(back.values.pose_keys, [top - 1, top])


def test_optimize_reports_the_point_id_offset(tmp_path, capsys):
    p = tmp_path / "g.isam"
    p.write_text(f"ODOMETRY {2**63 - 2} {2**63 - 1} 1 0 0 1 0 0 1 0 1\nLANDMARK {2**63 - 1} {2**63 - 1} 2 0 1 0 1\n")
    assert main(["optimize", str(p), "--out", str(tmp_path / "o.g2o"), "--json", str(tmp_path / "o.json")]) == 0
    assert "VERTEX_XY id -2" in capsys.readouterr().err
    assert json.loads(Path(tmp_path / "o.json").read_text())["point_id_offset"] == -2
    assert read_graph(tmp_path / "o.g2o").values.point_keys.tolist() == [2**63 - 3]
    p.write_text(f"ODOMETRY {2**63 - 2} {2**63 - 1} 1 0 0 1 0 0 1 0 1\nODOMETRY {-(2**63 - 1)} {2**63 - 1} 1 0 0 1 0 0 "
                 f"1 0 1\nLANDMARK {2**63 - 1} {2**63 - 1} 2 0 1 0 1\nLANDMARK {2**63 - 1} {-(2**63 - 1)} 2 0 1 0 1\n")
    assert main(["optimize", str(p), "--out", str(tmp_path / "o2.g2o")]) == 2
    assert "g.isam: write_g2o: the point ids cannot be moved" in _one_error_line(capsys)
    assert not (tmp_path / "o2.g2o").exists()
