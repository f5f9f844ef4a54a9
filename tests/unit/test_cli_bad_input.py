"""Every CLI sub-command against bad paths and values: exit != 0, ONE stderr line, no stack, no file changed.

Placeholders in the table: {dir} an existing directory, {file} an existing plain file, {g2o} a valid graph,
{log} a valid simulated log, {toml} a valid sweep file, {res} a sweep result directory, {d} the scratch folder,
{survey_*} floor-marker survey CSV files with one bad row each.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest

from slam2d.cli.main import main

G2O = "\n".join(["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0", "VERTEX_SE2 2 2 0 0",
                 "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1", "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1", "FIX 0"]) + "\n"
TOML = 'estimators = ["dead-reckoning"]\nscenarios = ["room"]\nseeds = 1\n[set]\nsteps = 5\n'

# (command, argv, what the message must mention); the table of the issue
CASES: list[tuple[str, str, str]] = [
    # optimize
    ("optimize", "optimize {dir} --out {d}/o.g2o", "directory"),
    ("optimize", "optimize /tmp --out {d}/o.g2o", "directory"),
    ("optimize", "optimize {d}/missing.g2o --out {d}/o.g2o", "missing.g2o"),
    ("optimize", "optimize {file}/x.g2o --out {d}/o.g2o", "x.g2o"),
    ("optimize", "optimize /dev/zero --out {d}/o.g2o", "/dev/zero"),
    ("optimize", "optimize {g2o} --out {g2o}", "--force"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --json {g2o}", "--force"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --json {d}/o.g2o", "same file"),
    # a directory where even root cannot create a file: refused before the work, naming the option
    ("optimize", "optimize {g2o} --out /proc/o.g2o", "--out /proc/o.g2o: cannot create a file in /proc"),
    ("optimize", "optimize {g2o} --out {dir}", "directory"),
    ("optimize", "optimize {g2o} --out {file}/o.g2o", "not a directory"),
    ("optimize", "optimize {g2o} --out /dev/full", "/dev/full"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --json /dev/full", "/dev/full"),
    ("optimize", "optimize {g2o} --format toro --out {d}/o.g2o", "wrong --format"),
    ("optimize", "optimize {file} --format g2o --out {d}/o.g2o", "wrong --format"),
    ("optimize", "optimize {file} --out {d}/o.g2o", "--format"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --max-iterations -1", "--max-iterations"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --max-iterations 1000000000000", "--max-iterations"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --lambda-initial nan", "--lambda-initial"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --lambda-initial inf", "--lambda-initial"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --lambda-initial 0", "--lambda-initial"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --lambda-initial -1", "--lambda-initial"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --lambda-initial 1e300", "--lambda-initial"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --robust huber:nan", "--robust"),
    ("optimize", "optimize {g2o} --out {d}/o.g2o --robust huber:1e-300", "--robust"),
    # simulate
    ("simulate", "simulate --out {dir}", "directory"),
    ("simulate", "simulate --out {file}/x.npz", "not a directory"),
    ("simulate", "simulate --out /dev/full --set steps=3", "/dev/full"),
    ("simulate", "simulate --out {d}/s.npz --set steps=0", "steps"),
    ("simulate", "simulate --out {d}/s.npz --set steps=-1", "steps"),
    ("simulate", "simulate --out {d}/s.npz --set steps=nan", "steps"),
    ("simulate", "simulate --out {d}/s.npz --set steps=1e300", "steps"),
    ("simulate", "simulate --out {d}/s.npz --set steps=100000000", "SLAM2D_MAX_MEMORY_MB"),
    ("simulate", "simulate --out {d}/s.txt", "ending in .npz"),
    ("simulate", "simulate --out {d}/s.npz --set warehouse.aisles=3", "cannot be set for scenario 'room'"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.clutter_rate=1e9", "clutter_rate"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.clutter_rate=inf", "clutter_rate"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.clutter_rate=-1", "clutter_rate"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.descriptor_dim=100000000", "descriptor_dim"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.range_std_m=1e300", "range_std_m"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.range_std_m=1e-300", "range_std_m"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.range_std_m=0", "range_std_m"),
    ("simulate", "simulate --out {d}/s.npz --set sensor.range_std_m=nan", "range_std_m"),
    ("simulate", "simulate --out {d}/s.npz --set landmarks=1000000000", "SLAM2D_MAX_MEMORY_MB"),
    ("simulate", "simulate --out {d}/s.npz --seed -1", "seed"),
    # run
    ("run", "run --log {dir}", "directory"),
    ("run", "run --log {d}/missing.npz", "missing.npz"),
    ("run", "run --log /dev/zero", "/dev/zero"),
    ("run", "run --log {g2o}", "g2o"),
    ("run", "run --log {log} --json {log}", "--force"),
    ("run", "run --log {log} --json {dir}", "directory"),
    ("run", "run --log {log} --json /dev/full", "/dev/full"),
    ("run", "run --log {log} --estimator nope", "nope"),
    ("run", "run --set steps=3 --set estimator.gps_std_m=1e300 --estimator ekf", "gps_std_m"),
    ("run", "run --dataset mrclam --dataset-path {dir}", "Barcodes.dat"),
    ("run", "run --seed -1", "--seed"),
    ("run", "run --estimator fastslam --set steps=3 --set estimator.particles=1000000000", "SLAM2D_MAX_MEMORY_MB"),
    ("run", "run --set steps=3 --set sensor.descriptor_dim=100000000", "descriptor_dim"),
    ("run", "run --dataset mrclam --max-steps 0", "--max-steps"),
    ("run", "run --dataset mrclam --max-time nan", "--max-time"),
    # datasets
    ("datasets", "datasets --json {dir}", "directory"),
    ("datasets", "datasets --json /dev/full", "/dev/full"),
    ("datasets", "datasets --json {file}/x.json", "not a directory"),
    # report
    ("report", "report {d}/missing", "missing"),
    ("report", "report {file}", "file"),
    ("report", "report {dir}", "results.jsonl"),
    ("report", "report {res} --out {file}", "folder"),
    ("report", "report {broken}", "scaling.json:2: not JSON"),
    # sweep
    ("sweep", "sweep {dir} --out {d}/sw", "directory"),
    ("sweep", "sweep {d}/missing.toml --out {d}/sw", "missing.toml"),
    ("sweep", "sweep {toml} --out {file}", "file"),
    ("sweep", "sweep {g2o} --out {d}/sw", "TOML"),
    ("sweep", "sweep /dev/zero --out {d}/sw", "/dev/zero"),
    ("sweep", "sweep {toml} --out {d}/sw --workers 0", "--workers"),
    # lidar
    ("lidar", "lidar --dataset {d}/missing.clf", "missing.clf"),
    ("lidar", "lidar --dataset {dir}", "directory"),
    ("lidar", "lidar --dataset /dev/zero", "regular file"),
    ("lidar", "lidar --dataset {file} --resolution 0", "--resolution"),
    ("lidar", "lidar --dataset {file} --resolution nan", "--resolution"),
    ("lidar", "lidar --dataset {file} --resolution 1e-300", "--resolution"),
    ("lidar", "lidar --dataset {file} --resolution -1", "--resolution"),
    ("lidar", "lidar --dataset {file} --out {file}", "--force"),
    ("lidar", "lidar --dataset {file} --out {dir}", "directory"),
    ("lidar", "lidar --dataset {file} --json {file}", "--force"),
    # experiment, exercise, demo, lab
    ("experiment", "experiment scaling --seeds 0", "--seeds"),
    ("experiment", "experiment scaling --seeds 1000000000", "--seeds"),
    ("experiment", "experiment scaling --json {dir}", "directory"),
    ("exercise", "exercise check {d}/missing.py", "missing.py"),
    ("exercise", "exercise check {dir}", "directory"),
    ("exercise", "exercise check {file} --random 1000000000", "--random"),
    ("demo", "demo --out {file}", "folder"),
    ("lab", "lab --port 0", "--port"),
    ("lab", "lab --port 70000", "--port"),
    ("lab", "lab --allow-origin notaurl", "--allow-origin: expected an origin"),
    ("lab", "lab --allow-origin https://lab.example.org/path", "no path"),
    # map
    ("map", "map info {dir}", "directory"),
    ("map", "map info {d}/missing.db", "missing.db"),
    ("map", "map info {file}", "afile"),
    ("map", "map load {g2o}", "g.g2o"),
    ("map", "map load /dev/zero", "/dev/zero"),
    ("map", "map save --scenario room --out {dir}", "directory"),
    ("map", "map save --scenario room --out {file}/m.db", "not a directory"),
    ("map", "map save --scenario room --out /dev/full", "/dev/full"),
    ("map", "map save --scenario room --out {file}", "not a slam2d map"),
    ("map", "map save --scenario room --out {d}/m.db --resolution 0", "resolution"),
    ("map", "map save --scenario room --out {d}/m.db --resolution nan", "resolution"),
    ("map", "map save --scenario nowhere --out {d}/m.db", "nowhere"),
    # map-server, drone (validation before any socket or simulation)
    ("map-server", "map-server --db {dir}", "directory"),
    ("map-server", "map-server --db {file}/m.db", "m.db"),
    ("map-server", "map-server --db {file}", "afile"),
    ("map-server", "map-server --db {d}/f.db --port -1", "--port"),
    ("map-server", "map-server --db {d}/f.db --port 70000", "--port"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {d}/missing.csv", "missing.csv"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {dir}", "adir"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {file}", "afile:1"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {survey_bad_id}", "survey_bad_id.csv:3"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {survey_nan}", "survey_nan.csv:1"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {survey_dup}", "survey_dup.csv:4"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {survey_empty}", "no marker"),
    ("map-server", "map-server --db {d}/f.db --marker-survey /dev/zero", "/dev/zero"),
    ("map-server", "map-server --db {d}/f.db --survey-sigma 0", "--survey-sigma"),
    ("map-server", "map-server --db {d}/f.db --survey-sigma 0.02", "--survey-sigma needs --marker-survey"),
    ("map-server", "map-server --db {d}/f.db --marker-survey {survey} --survey-sigma 0", "--survey-sigma"),
    ("map-server", "map-server --db {d}/f.db --survey-sigma nan", "--survey-sigma"),
    ("drone", "drone --server nowhere --drone 0", "--server"),
    ("drone", "drone --server nohost.invalid:5555 --drone 0", "cannot resolve host 'nohost.invalid'"),
    ("drone", "drone --server 127.0.0.1:1 --drone -1", "--drone"),
    ("drone", "drone --server 127.0.0.1:1 --drone 0 --minutes nan", "--minutes"),
    ("drone", "drone --server 127.0.0.1:1 --drone 0 --minutes -1", "--minutes"),
    ("drone", "drone --server 127.0.0.1:1 --drone 0 --minutes 1e300", "--minutes"),
    ("drone", "drone --server 127.0.0.1:1 --drone 0 --blackout x", "--blackout"),
    ("drone", "drone --server 127.0.0.1:1 --drone 0 --scenario nowhere", "nowhere"),
    ("drone", "drone --server 127.0.0.1:1 --drone 0 --json {dir}", "directory"),
    # run with saved maps (checked before the run starts)
    ("run", "run --scenario room --estimator lidar --map-in {file}", "afile"),
    ("run", "run --scenario room --estimator lidar --map-in {d}/missing.db", "missing.db"),
    ("run", "run --scenario room --estimator lidar --map-in {dir}", "directory"),
    ("run", "run --scenario room --estimator lidar --map-out {file}", "afile"),
    ("run", "run --scenario room --estimator lidar --map-out {dir}", "directory"),
    ("run", "run --scenario room --estimator ekf --map-out {d}/m.db", "lidar"),
    # floor-marker surveys (read before the run starts; file:line named)
    ("run", "run --scenario room --estimator lidar --marker-survey {survey}", "lidar-lifelong"),
    ("run", "run --scenario room --estimator lidar-lifelong --marker-survey {file}", "afile:1"),
    ("run", "run --scenario room --estimator lidar-lifelong --marker-survey {d}/missing.csv", "missing.csv"),
    ("run", "run --scenario room --estimator lidar-lifelong --marker-survey {dir}", "adir"),
    ("run", "run --scenario room --estimator lidar-lifelong --marker-survey /dev/zero", "/dev/zero"),
    ("simulate", "simulate --out {d}/s.npz --set steps=3 --marker-survey {d}/s.csv", "no floor markers"),
    ("simulate", "simulate --out {d}/s.npz --set steps=3 --marker-survey {dir}", "directory"),
    ("simulate", "simulate --out {d}/s.npz --set steps=3 --marker-survey {file}/s.csv", "not a directory"),
    ("simulate", "simulate --out {d}/s.npz --set steps=3 --survey-sigma nan", "--survey-sigma"),
    ("simulate", "simulate --out {d}/s.npz --set steps=3 --survey-sigma -1", "--survey-sigma"),
]


def _snapshot(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[str(p.relative_to(root))] = "dir"
    return out


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("bad")
    (d / "adir").mkdir()
    (d / "afile").write_text("just some text\n")
    (d / "g.g2o").write_text(G2O)
    (d / "sweep.toml").write_text(TOML)
    (d / "survey.csv").write_text("id,x,y\n0,1.0,2.0\n")
    assert main(["simulate", "--out", str(d / "log.npz"), "--set", "steps=5"]) == 0
    surveys = {"survey_bad_id": "id,x,y\n0,1.0,2.0\nseven,1,2\n", "survey_nan": "0,1.0,nan\n",
               "survey_dup": "# floor markers\nid,x,y\n3,1,2\n3,4,5\n", "survey_empty": "id,x,y\n\n"}
    for name, text in surveys.items():
        (d / f"{name}.csv").write_text(text)
    (d / "res").mkdir()
    (d / "res" / "results.jsonl").write_text("")
    (d / "broken").mkdir()
    (d / "broken" / "scaling.json").write_text('{"fits":\n  }\n')
    return {"d": str(d), "dir": str(d / "adir"), "file": str(d / "afile"), "g2o": str(d / "g.g2o"),
            "survey": str(d / "survey.csv"), "log": str(d / "log.npz"), "toml": str(d / "sweep.toml"),
            "res": str(d / "res"), "broken": str(d / "broken"), **{name: str(d / f"{name}.csv") for name in surveys}}


@pytest.mark.parametrize(("command", "template", "mention"), CASES, ids=[c[1] for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(command, template, mention, scratch, capsys, monkeypatch):
    monkeypatch.setenv("SLAM2D_DATA", scratch["dir"])  # no dataset is found there
    argv = template.format(**scratch).split()
    before = _snapshot(Path(scratch["d"]))
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err
    assert code not in (0, None), err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"slam2d {command}: error: "), err
    assert "Traceback" not in err
    assert mention.lower() in lines[0].lower(), lines[0]
    assert _snapshot(Path(scratch["d"])) == before


def test_debug_shows_the_stack(scratch):
    with pytest.raises(IsADirectoryError):
        main(["optimize", scratch["dir"], "--out", scratch["d"] + "/o.g2o", "--debug"])


def test_a_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    """A full disk during the write (ENOSPC from fsync) leaves the previous output intact and no temporary."""
    import errno

    from slam2d.io import atomic

    target = tmp_path / "out.g2o"
    target.write_text("precious\n")

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    g = tmp_path / "in.g2o"
    g.write_text(G2O)
    assert main(["optimize", str(g), "--out", str(target)]) == 2
    assert target.read_text() == "precious\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.g2o", "out.g2o"]


def test_force_allows_overwriting_the_input(tmp_path):
    g = tmp_path / "in.g2o"
    g.write_text(G2O)
    assert main(["optimize", str(g), "--out", str(g), "--force"]) == 0
    assert g.read_text().startswith("VERTEX_SE2 0")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_directory(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert main(["simulate", "--out", str(ro / "s.npz"), "--set", "steps=3"]) == 2
        assert "not writable" in capsys.readouterr().err
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


def test_atomic_write_to_a_device_writes_in_place():
    from slam2d.io.atomic import atomic_write

    with atomic_write("/dev/null") as fh:
        fh.write("x")
    assert Path("/dev/null").exists() and not Path("/dev/null").is_file()
    assert np.isfinite(1.0)


def test_optimize_dev_zero_stays_small(tmp_path):
    """``slam2d optimize /dev/zero`` ends with one error line and a small peak RSS (the reader stops at the first
    over-long line instead of reading forever). The elapsed time is measured in the report, not asserted."""
    import subprocess
    import sys

    src = str(Path(__file__).resolve().parents[2] / "src")
    # a small wrapper reports the peak RSS of the command alone (this process's other children do not count)
    wrapper = ("import resource, subprocess, sys; "
               "r = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
               "sys.stderr.write(r.stderr); "
               "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    res = subprocess.run([sys.executable, "-c", wrapper, sys.executable, "-m", "slam2d", "optimize", "/dev/zero",
                          "--out", str(tmp_path / "o.g2o")], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": src, "OPENBLAS_NUM_THREADS": "1"})
    code, peak_kb = (int(v) for v in res.stdout.split())
    assert code == 2 and "/dev/zero" in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert peak_kb / 1024 < 300, peak_kb
    assert not (tmp_path / "o.g2o").exists()


def test_every_subcommand_is_in_the_table():
    from slam2d.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    assert set(sub.choices) <= {c[0] for c in CASES}, set(sub.choices) - {c[0] for c in CASES}
