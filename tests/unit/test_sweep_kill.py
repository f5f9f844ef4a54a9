"""``kill -9`` of a running sweep leaves no process behind; every unusable store line is quarantined."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slam2d.cli.main import main
from slam2d.lab.store import QUARANTINE_FILE, STORE_FILE, ResultStore

PY = sys.executable
SRC = str(Path(__file__).resolve().parents[2] / "src")


def _children() -> dict[int, int]:
    """pid -> ppid of every live (non-zombie) process."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if fields[0] != "Z":
            out[int(d.name)] = int(fields[1])
    return out


def _descendants(root: int) -> set[int]:
    procs = _children()
    found, frontier = set(), {root}
    while frontier:
        frontier = {p for p, pp in procs.items() if pp in frontier} - found
        found |= frontier
    return found


def _wait(cond, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux only")
def test_kill_9_of_a_sweep_leaves_no_process_behind(tmp_path):
    cfg = tmp_path / "s.toml"
    cfg.write_text('estimators = ["dead-reckoning"]\nscenarios = ["grid"]\nseeds = 6\n[set]\nsteps = 200000\n'
                   'landmarks = 10\n')
    env = {**os.environ, "PYTHONPATH": SRC, "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.Popen([PY, "-m", "slam2d", "sweep", str(cfg), "--out", str(tmp_path / "out"), "--workers", "2",
                             "--no-progress"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen: set[int] = set()
    try:
        # forkserver + 2 workers + resource tracker under the sweep
        assert _wait(lambda: len(seen.__ior__(_descendants(proc.pid))) >= 3, 180), "workers never started"
        time.sleep(1.0)
        seen |= _descendants(proc.pid)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        alive = lambda: {p for p in seen if p in _children()}  # noqa: E731
        assert _wait(lambda: not alive(), 60), f"left behind: {alive()}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for p in seen & set(_children()):
            os.kill(p, signal.SIGKILL)


BAD_LINES = {
    "deep": "[" * 200_000,
    "long_int": '{"key": "k", "seed": ' + "9" * 5000 + "}",
    "not_json": "{oops",
    "partial": '{"key": "k"',
}


def test_every_unusable_store_line_is_quarantined(tmp_path):
    d = tmp_path / "r"
    d.mkdir()
    (d / STORE_FILE).write_text("\n".join(BAD_LINES.values()) + "\n")
    store = ResultStore(d)
    records, problems = store.scan()
    assert records == {} and len(problems) == len(BAD_LINES)
    store.quarantine(problems)
    assert (d / STORE_FILE).read_text() == ""
    q = [json.loads(line) for line in (d / QUARANTINE_FILE).read_text().splitlines()]
    assert [r["text"] for r in q] == list(BAD_LINES.values())


def test_a_store_that_is_a_directory_is_moved_aside_and_the_sweep_resumes(tmp_path, capsys):
    out = tmp_path / "r"
    (out / STORE_FILE).mkdir(parents=True)
    (out / STORE_FILE / "x").write_text("keep me")
    cfg = tmp_path / "s.toml"
    cfg.write_text('estimators = ["dead-reckoning"]\nscenarios = ["room"]\nseeds = 1\n[set]\nsteps = 5\n')
    # report reads without changing anything
    assert main(["report", str(out), "--out", str(tmp_path / "rep")]) == 0
    assert (out / STORE_FILE).is_dir()
    assert main(["sweep", str(cfg), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    assert (out / STORE_FILE).is_file() and len(ResultStore(out).records()) == 1
    aside = [p for p in out.iterdir() if p.name.startswith(f"{STORE_FILE}.quarantined-")]
    assert len(aside) == 1 and (aside[0] / "x").read_text() == "keep me"


def test_report_on_a_store_with_unreadable_lines(tmp_path, capsys):
    d = tmp_path / "r"
    d.mkdir()
    (d / STORE_FILE).write_text("\n".join(BAD_LINES.values()) + "\n")
    before = (d / STORE_FILE).read_bytes()
    assert main(["report", str(d)]) == 0
    assert (d / STORE_FILE).read_bytes() == before
    assert "unusable store lines" in (d / "report" / "index.html").read_text()
