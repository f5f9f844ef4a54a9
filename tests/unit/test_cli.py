import json
import subprocess
import sys

import pytest

from slam2d.cli.main import build_parser, main


def test_every_command_has_help(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert {"simulate", "run", "demo"} <= set(sub.choices)
    for name in sub.choices:
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0
        assert "usage: slam2d " + name in capsys.readouterr().out


def test_simulate_then_run_from_log_writes_json(tmp_path, capsys):
    log = tmp_path / "room.npz"
    assert main(["simulate", "--scenario", "room", "--seed", "4", "--out", str(log), "--set", "steps=40"]) == 0
    out = tmp_path / "r.json"
    assert main(["run", "--log", str(log), "--estimator", "dead-reckoning", "--seed", "4", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    for k in ["ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_rad", "steps", "step_ms_mean", "estimator", "scenario",
              "seed", "landmarks_estimated"]:
        assert k in rec
    assert rec["steps"] == 40 and rec["scenario"] == "room" and rec["seed"] == 4
    assert "ate_rmse_m" in capsys.readouterr().out


def test_set_overrides_reach_the_simulation(tmp_path):
    out = tmp_path / "g.json"
    assert main(["run", "--scenario", "grid", "--set", "landmarks=400", "--set", "steps=25", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["steps"] == 25 and rec["scenario_config"]["landmarks"] == 400


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["run", "--scenario", "nope"], "valid scenarios"),
        (["run", "--estimator", "nope"], "valid estimators"),
        (["run", "--set", "sensor.range_std_m=-1"], "sensor.range_std_m"),
        (["run", "--set", "steps"], "KEY=VALUE"),
        (["run", "--log", "/nonexistent/x.npz"], "no such file"),
    ],
)
def test_bad_input_gives_a_one_line_error(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_console_script_runs_as_module():
    r = subprocess.run([sys.executable, "-m", "slam2d", "--help"], capture_output=True, text=True, check=True)
    assert "simulate" in r.stdout and "run" in r.stdout


def test_a_saved_log_runs_with_its_own_seed_unless_one_is_given(tmp_path):
    log = tmp_path / "loop.npz"
    assert main(["simulate", "--scenario", "loop", "--seed", "3", "--out", str(log), "--set", "steps=30"]) == 0
    recs = {}
    for name, extra in (("log", []), ("scenario", ["--scenario", "loop", "--seed", "3", "--set", "steps=30"]),
                        ("given", ["--seed", "5"])):
        out = tmp_path / f"{name}.json"
        src = [] if name == "scenario" else ["--log", str(log)]
        assert main(["run", *src, *extra, "--estimator", "fastslam", "--set", "particles=20", "--json", str(out)]) == 0
        recs[name] = json.loads(out.read_text())
    assert recs["log"]["seed"] == 3 and recs["given"]["seed"] == 5
    # the log's own seed is the scenario run's: same estimator stream, the same numbers (FastSLAM draws from it)
    assert recs["log"]["ate_rmse_m"] == recs["scenario"]["ate_rmse_m"]
    assert recs["given"]["ate_rmse_m"] != recs["log"]["ate_rmse_m"]


def test_version_and_run_options_that_do_not_apply(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("slam2d ")
    for args, msg in ((["--estimator", "ekf", "--no-loop-closure"], "--no-loop-closure: estimator 'ekf' has no loop"),
                      (["--estimator", "dead-reckoning", "--association", "jcbb"],
                       "--association: estimator 'dead-reckoning' does not associate"),
                      (["--set", "name=loop"], "--set name=...: the scenario is chosen with --scenario"),
                      (["--robot", "3"], "--robot 3: a robot of a multi-robot dataset")):
        assert main(["run", "--scenario", "room", "--set", "steps=5", *args]) == 2
        assert msg in capsys.readouterr().err
    assert main(["run", "--scenario", "room", "--set", "steps=5", "--estimator", "ekf", "--association", "auto"]) == 0


def test_demo_skips_a_back_end_the_world_gives_nothing_to(tmp_path, capsys, monkeypatch):
    import slam2d.cli.demo as demo

    monkeypatch.setattr(demo, "estimator_names", lambda: ["dead-reckoning", "lidar"])
    assert main(["demo", "--scenario", "grid", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "skipped: estimator 'lidar' needs lidar scans; grid has none" in out
    runs = json.loads((tmp_path / "demo.json").read_text())["runs"]
    assert [r["estimator"] for r in runs] == ["dead-reckoning"]


def test_a_reader_that_goes_away_is_not_an_error(tmp_path):
    """``slam2d datasets | head -1``: the pipe closes before the table is written; exit 0, nothing on stderr."""
    import os
    from pathlib import Path

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2] / "src"), "SLAM2D_DATA": str(tmp_path)}
    p = subprocess.Popen([sys.executable, "-m", "slam2d", "datasets"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=env)
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()  # before the child has started: its first write meets a closed pipe
    with p.stderr:
        err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 0, err
    assert err == ""


def test_a_library_warning_is_one_line_naming_the_command(tmp_path, capsys):
    graph = tmp_path / "g.g2o"
    graph.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nFOO 1\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    assert main(["optimize", str(graph), "--out", str(tmp_path / "o.g2o")]) == 0
    err = capsys.readouterr().err
    assert err == f"slam2d optimize: warning: {graph}: skipped lines with unknown tags: FOO x1\n"
