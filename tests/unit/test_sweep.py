"""Sweep configs (validation before any run), the JSONL result store (resume, corruption) and run_sweep."""

import concurrent.futures as cf
import json
from pathlib import Path

import pytest

import slam2d
from slam2d.cli.main import main
from slam2d.lab.sweep import (
    QUARANTINE_FILE,
    ResultStore,
    RunSpec,
    load_sweep,
    parse_sweep,
    run_job,
    run_sweep,
)

TINY = """
estimators = ["dead-reckoning"]
scenarios = ["grid", "room"]
seeds = 3
[set]
steps = 5
[grid]
"sensor.range_std_m" = [0.05, 0.2]
"""


def write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_expansion_is_the_product_of_estimators_scenarios_grid_and_seeds(tmp_path):
    plan = load_sweep(write(tmp_path, TINY))
    assert len(plan.specs) == 4 and plan.seeds == (0, 1, 2) and len(plan.jobs()) == 12
    assert {s.overrides["sensor.range_std_m"] for s in plan.specs} == {0.05, 0.2}
    assert all(s.overrides["steps"] == 5 for s in plan.specs)
    assert len({s.key for s in plan.specs}) == 4
    # the key is a content hash: the same config gives the same key, independent of dict order
    s = plan.specs[0]
    assert RunSpec(s.estimator, s.scenario, dict(reversed(list(s.overrides.items())))).key == s.key
    nested = parse_sweep({"estimators": "all", "seeds": {"start": 5, "count": 2},
                          "grid": {"sensor": {"range_std_m": [0.1]}}, "configs": [{"steps": 4}, {"steps": 6}]})
    assert nested.seeds == (5, 6)
    assert len(nested.specs) == 2 * len(slam2d.estimator_names())
    assert nested.specs[0].overrides == {"steps": 4, "sensor.range_std_m": 0.1}


@pytest.mark.parametrize("text, needle", [
    ("estimators = ['dead-reckoning']\nsteps = 3\n", r"unknown key\(s\) \['steps'\]"),
    ("estimators = ['dead-reckoning']\n[grid]\nsteps = [5, 0]\n", r"grid\.steps = 0 .*steps must be >= 1"),
    ("estimators = ['dead-reckoning']\n[set]\nnot_a_field = 1\n", r"set\.not_a_field = 1 .*unknown key 'not_a_field'"),
    ("estimators = ['dead-reckoning']\n[[configs]]\nsensor.range_std_m = -1\n",
     r"configs\[0\]\.sensor\.range_std_m = -1 .*range_std_m must be a number in"),
    ("estimators = ['dead-reckoning']\n[grid]\nsteps = 5\n", r"grid\.steps must be a non-empty list"),
    ("estimators = ['nope']\n", r"'estimators' has unknown name\(s\) \['nope'\]"),
    ("estimators = ['dead-reckoning']\nscenarios = ['moon']\n", r"'scenarios' has unknown name\(s\) \['moon'\]"),
    ("estimators = ['dead-reckoning']\nseeds = 0\n", r"'seeds' count must be in 1\.\.100000"),
    # a typo in a size is refused at once (a billion seeds hung the dry run while the plan was expanded)
    ("estimators = ['dead-reckoning']\nseeds = 1000000000\n", r"'seeds' count must be in 1\.\.100000"),
    ("estimators = ['dead-reckoning']\nseeds = {start = 9223372036854775800, count = 9}\n", r"seeds are 64-bit"),
    ("estimators = ['dead-reckoning']\n[grid]\nsteps = " + str(list(range(1, 10002))) + "\n",
     r"10001 configurations x 1 seeds is more than a sweep may hold"),
    ("estimators = ['dead-reckoning']\nseeds = {start = 1, cnt = 2}\n", r"unknown key\(s\) \['cnt'\] in 'seeds'"),
    ("scenarios = ['room']\n", r"missing required key 'estimators'"),
    ("estimators = ['dead-reckoning']\n[set]\nname = 'loop'\n", r"set\.name .*not allowed"),
    ("estimators = [\n", r"not valid TOML"),
])
def test_bad_sweep_configs_fail_before_any_run_naming_the_key(tmp_path, capsys, text, needle):
    cfg = write(tmp_path, text)
    out = tmp_path / "out"
    assert main(["sweep", str(cfg), "--out", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert "error" in err
    import re

    assert re.search(needle, err), err
    assert not (out / "results.jsonl").exists()


def test_run_job_matches_a_direct_run_and_reports_errors_as_records():
    spec = RunSpec("dead-reckoning", "room", {"steps": 12, "sensor.range_std_m": 0.3})
    rec = run_job(spec.to_dict(), 4)
    _, direct = slam2d.run_named("dead-reckoning", "room", seed=4, overrides={"steps": 12, "sensor.range_std_m": 0.3})
    assert rec["status"] == "ok" and rec["key"] == spec.key and rec["seed"] == 4
    assert rec["metrics"]["ate_rmse_m"] == pytest.approx(direct["ate_rmse_m"], rel=1e-12)
    assert len(rec["metrics"]["pose_nees"]) == 12
    assert rec["metrics"]["scenario_config"]["sensor"]["range_std_m"] == 0.3
    bad = run_job({"estimator": "dead-reckoning", "scenario": "room", "overrides": {"steps": -1}}, 0)
    assert bad["status"] == "error" and "steps" in bad["error"]


def test_sweep_stores_each_run_once_and_resumes(tmp_path):
    plan = load_sweep(write(tmp_path, TINY))
    msgs: list[str] = []
    with cf.ThreadPoolExecutor(2) as ex:
        s1 = run_sweep(plan, tmp_path / "o", ex, progress=False, report=msgs.append)
    assert (s1.ran, s1.already_done, s1.complete) == (12, 0, True)
    records, problems = ResultStore(tmp_path / "o").scan()
    assert not problems
    assert set(records) == {(s.key, seed) for s, seed in plan.jobs()}
    with cf.ThreadPoolExecutor(2) as ex:
        s2 = run_sweep(plan, tmp_path / "o", ex, progress=False, report=msgs.append)
    assert (s2.ran, s2.already_done) == (0, 12)
    assert len((tmp_path / "o" / "results.jsonl").read_text().splitlines()) == 12
    # a grown sweep runs only the new seeds
    plan3 = parse_sweep({**_toml(TINY), "seeds": 4})
    with cf.ThreadPoolExecutor(2) as ex:
        s3 = run_sweep(plan3, tmp_path / "o", ex, progress=False, report=msgs.append)
    assert (s3.ran, s3.already_done) == (4, 12)


def _toml(text: str) -> dict:
    import tomllib

    return tomllib.loads(text)


def test_corrupt_and_partial_records_are_reported_quarantined_and_rerun(tmp_path):
    plan = load_sweep(write(tmp_path, TINY))
    with cf.ThreadPoolExecutor(2) as ex:
        run_sweep(plan, tmp_path / "o", ex, progress=False, report=lambda m: None)
    path = tmp_path / "o" / "results.jsonl"
    lines = path.read_text().splitlines(keepends=True)
    victims = [json.loads(lines[i]) for i in (3, 11)]
    tampered = json.loads(lines[5])
    tampered["metrics"]["ate_rmse_m"] = 0.0  # still valid JSON, but altered: the checksum catches it
    lines[5] = json.dumps(tampered) + "\n"
    lines[3] = lines[3][: len(lines[3]) // 2] + "\n"  # torn in the middle
    lines[11] = lines[11][:40]  # the writer died mid-record: no newline at the end
    path.write_text("".join(lines))
    msgs: list[str] = []
    with cf.ThreadPoolExecutor(2) as ex:
        s = run_sweep(plan, tmp_path / "o", ex, progress=False, report=msgs.append)
    reported = [m for m in msgs if "moved to" in m]
    assert len(reported) == 3, msgs
    assert any("line 4: not valid JSON" in m for m in reported)
    assert any("line 6: checksum mismatch" in m for m in reported)
    assert any("line 12: partial record" in m for m in reported)
    assert s.ran == 3 and s.already_done == 9 and s.complete
    records, problems = ResultStore(tmp_path / "o").scan()
    assert not problems and len(records) == 12
    assert {(v["key"], v["seed"]) for v in victims} <= set(records)
    assert records[(tampered["key"], tampered["seed"])]["metrics"]["ate_rmse_m"] > 0
    q = (tmp_path / "o" / QUARANTINE_FILE).read_text().splitlines()
    assert len(q) == 3 and all(json.loads(x)["text"] for x in q)


class FlakyExecutor(cf.Executor):
    """Runs jobs inline, but the n-th submission fails as a lost worker would."""

    def __init__(self, fail_at: set[int]):
        self.fail_at, self.count = fail_at, 0

    def submit(self, fn, /, *args, **kwargs):
        f: cf.Future = cf.Future()
        self.count += 1
        if self.count in self.fail_at:
            f.set_exception(RuntimeError("worker lost"))
        else:
            f.set_result(fn(*args, **kwargs))
        return f


def test_runs_lost_by_the_executor_are_not_stored_and_are_rerun(tmp_path):
    plan = load_sweep(write(tmp_path, TINY))
    msgs: list[str] = []
    s = run_sweep(plan, tmp_path / "o", FlakyExecutor({2, 7}), progress=False, report=msgs.append)
    assert s.ran == 10 and len(s.failed) == 2 and not s.complete
    assert any("2 runs did not complete" in m for m in msgs)
    s = run_sweep(plan, tmp_path / "o", FlakyExecutor(set()), progress=False, report=msgs.append)
    assert s.ran == 2 and s.complete


def test_report_writes_html_with_figures(tmp_path):
    pytest.importorskip("matplotlib")
    plan = load_sweep(write(tmp_path, TINY))
    run_sweep(plan, tmp_path / "o", FlakyExecutor(set()), progress=False, report=lambda m: None)
    o = tmp_path / "o"
    assert main(["experiment", "scaling", "--set", "landmarks=20,40", "--set", "steps=30",
                 "--json", str(o / "scaling.json")]) == 0
    assert main(["experiment", "consistency", "--seeds", "3", "--set", "steps=20",
                 "--json", str(o / "consistency.json")]) == 0
    assert main(["experiment", "scaling", "--set", "landmark=5"]) == 2  # unknown key, named
    assert main(["report", str(tmp_path / "o")]) == 0
    page = (tmp_path / "o" / "report" / "index.html").read_text()
    for img in ("ate_boxplot.png", "sweep_nees.png", "scaling.png", "consistency_nees.png"):
        assert f'src="{img}"' in page
        assert (tmp_path / "o" / "report" / img).stat().st_size > 1000
    assert "dead-reckoning / grid (sensor.range_std_m=0.05, steps=5)" in page
    assert main(["report", str(tmp_path / "nothing")]) == 2


def test_two_sweeps_cannot_write_one_store_at_once(tmp_path):
    plan = load_sweep(write(tmp_path, TINY))
    inner: list[str] = []

    def on_record(rec):
        if not inner:
            with pytest.raises(ValueError, match="another sweep is writing"):
                run_sweep(plan, tmp_path / "o", FlakyExecutor(set()), progress=False, report=lambda m: None)
            inner.append("checked")

    run_sweep(plan, tmp_path / "o", FlakyExecutor(set()), progress=False, report=lambda m: None, on_record=on_record)
    assert inner == ["checked"]
