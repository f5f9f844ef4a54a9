"""Benchmark scripts refuse bad arguments and unwritable outputs at once, in one line, before any work; ``--help``
describes a script instead of running it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _run(script: str, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args], capture_output=True, text=True,
                          timeout=120, env=env, cwd=ROOT.parent)


@pytest.mark.parametrize(("script", "args", "says"), [
    ("fleet.py", ["--out", "/dev/null/x.json"], "--out"),
    ("fleet.py", ["--out", "{tmp}/f.json", "--scaling", "1,x"], "--scaling"),
    ("lidar_backend.py", ["--logs", "bogus"], "--logs"),
    ("warehouse_shift.py", ["--json", "/dev/null/x.json"], "--json"),
    ("web_fps.py", ["--pages", "problem,bogus", "--out", "{tmp}/w.json"], "--pages"),
    ("real_data.py", ["--only", "bogus"], "--only"),
])
def test_bad_arguments_refused_before_work(tmp_path: Path, script: str, args: list[str], says: str) -> None:
    res = _run(script, *(a.replace("{tmp}", str(tmp_path)) for a in args))
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith(f"{script}: error: {says}")
    assert list(tmp_path.iterdir()) == []  # nothing written


@pytest.mark.parametrize("script", ["bench_scaling.py", "ekf_slam.py", "jcbb.py", "lidar_relations_check.py"])
def test_help_describes_instead_of_running(script: str) -> None:
    res = _run(script, "--help")
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("usage:")
