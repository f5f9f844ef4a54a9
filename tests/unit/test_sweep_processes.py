"""Sweeps across processes: a local Dask cluster losing a worker mid-way, and ``slam2d sweep`` interrupted by SIGINT.

Every process started here is bound to 127.0.0.1 and ended by its PID.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slam2d.lab.sweep import ResultStore, make_executor, parse_sweep, run_sweep

PY = sys.executable


def _stop(procs):
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _wait_for(cond, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


@pytest.mark.slow
def test_dask_sweep_survives_a_killed_worker(tmp_path):
    pytest.importorskip("distributed")
    psutil = pytest.importorskip("psutil")
    from distributed import Client

    sched_file = tmp_path / "scheduler.json"
    logs = [open(tmp_path / f"{n}.log", "w") for n in ("scheduler", "w1", "w2")]
    procs = [subprocess.Popen(
        [PY, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
         "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(sched_file)],
        stdout=logs[0], stderr=subprocess.STDOUT, cwd=tmp_path)]
    try:
        _wait_for(lambda: sched_file.exists() and sched_file.stat().st_size > 0, 300, "the scheduler")
        address = json.loads(sched_file.read_text())["address"]
        for i in (1, 2):
            procs.append(subprocess.Popen(
                [PY, "-m", "distributed.cli.dask_worker", address, "--host", "127.0.0.1",
                 "--dashboard-address", "127.0.0.1:0", "--nthreads", "1", "--no-nanny", "--name", f"w{i}",
                 "--local-directory", str(tmp_path / f"dw{i}"), "--death-timeout", "300"],
                stdout=logs[i], stderr=subprocess.STDOUT, cwd=tmp_path))
        with Client(address, timeout=300) as c:
            c.wait_for_workers(2, timeout=300)
        # every listener of the cluster is on loopback (STACK.md pitfall C2)
        for p in procs:
            for conn in psutil.Process(p.pid).net_connections(kind="tcp"):
                if conn.status == psutil.CONN_LISTEN:
                    assert conn.laddr.ip == "127.0.0.1", (p.args[2], conn.laddr)

        plan = parse_sweep({"estimators": ["dead-reckoning"], "scenarios": ["grid", "room"], "seeds": 55,
                            "set": {"steps": 5}, "grid": {"sensor.range_std_m": [0.05, 0.2]}})
        assert len(plan.jobs()) == 220
        victim = procs[1]
        seen: list[tuple[int, bool]] = []  # (worker pid, arrived after the kill)

        def on_record(rec):
            seen.append((rec["pid"], victim.poll() is not None))
            if len(seen) == 60:
                victim.send_signal(signal.SIGKILL)
                victim.wait(timeout=10)

        with make_executor(scheduler=address) as ex:
            summary = run_sweep(plan, tmp_path / "out", ex, progress=False, max_in_flight=16,
                                report=lambda m: None, on_record=on_record)
        assert summary.complete and summary.ran == 220 and summary.errors == 0
        records, problems = ResultStore(tmp_path / "out").scan()
        assert not problems
        assert sorted(records) == sorted((s.key, seed) for s, seed in plan.jobs())
        assert len((tmp_path / "out" / "results.jsonl").read_text().splitlines()) == 220  # each exactly once
        # both workers did work before the kill; once the (at most 16) runs in flight at the kill are through,
        # every record comes from the survivor
        assert {pid for pid, _ in seen[:60]} == {procs[1].pid, procs[2].pid}
        assert {pid for pid, _ in seen[60 + 16:]} == {procs[2].pid}
        assert sum(late for _, late in seen) >= 150
    finally:
        _stop(procs[::-1])
        for f in logs:
            f.close()


# runs long enough (~2 s CPU each on a 2.0 GHz core, ~0.8 s on a 3 GHz one) that the interrupt, sent after 4
# records, lands mid-sweep even when this test process is starved of CPU (with 100 steps a loaded machine finished
# all 40 runs before the test saw the first records); 40 runs of 1000 steps took 94 s of a slow CI worker
SIGINT_RUNS = 20
SIGINT_SWEEP = f"""
estimators = ["dead-reckoning"]
scenarios = ["room"]
seeds = {SIGINT_RUNS}
[set]
steps = 400
"""


@pytest.mark.slow
def test_sigint_then_rerun_finishes_only_the_missing_runs(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    cfg = tmp_path / "s.toml"
    cfg.write_text(SIGINT_SWEEP)
    out = tmp_path / "out"
    store = out / "results.jsonl"
    cmd = [PY, "-m", "slam2d", "sweep", str(cfg), "--out", str(out), "--workers", "2", "--no-progress"]
    env = {**os.environ, "DASK_SCHEDULER_ADDRESS": ""}
    # a program started with SIGINT ignored keeps ignoring it (as a background job should), and Python inherits an
    # ignored SIGINT from its parent; this test process may have it ignored by the time it runs, so the child
    # installs Python's own Ctrl-C handler first, as an interactive shell's child would have it
    child = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
             "sys.argv = ['slam2d', *sys.argv[1:]]; runpy.run_module('slam2d', run_name='__main__')")
    proc = subprocess.Popen([PY, "-c", child, *cmd[3:]], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    try:
        _wait_for(lambda: store.exists() and len(store.read_bytes().splitlines()) >= 4, 600, "the first records")
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        _stop([proc])
    assert proc.returncode == 130, (stdout, stderr)
    assert "interrupted" in stdout
    first = len(store.read_bytes().splitlines())
    assert 4 <= first < SIGINT_RUNS, "the sweep finished before the interrupt: make its runs longer"

    # the re-run (in this process, to save an interpreter start) does only what is missing
    from slam2d.cli.main import main

    assert main(cmd[3:]) == 0
    printed = capsys.readouterr().out
    assert f"{first} already stored, {SIGINT_RUNS - first} to run" in printed
    assert f"ran {SIGINT_RUNS - first} runs" in printed
    records, problems = ResultStore(out).scan()
    assert not problems and len(records) == SIGINT_RUNS
    assert len(store.read_bytes().splitlines()) == SIGINT_RUNS  # nothing ran twice
    assert sorted(seed for _, seed in records) == list(range(SIGINT_RUNS))
    assert Path(out / "plan.json").exists()
