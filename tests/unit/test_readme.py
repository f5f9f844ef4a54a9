"""The README's Python example runs as written and its numbers rank the back ends as the lesson says."""

import contextlib
import io
import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_python_example_runs_and_slam_beats_dead_reckoning():
    text = README.read_text()
    block = re.search(r"## Python in twelve lines\n\n```python\n(.*?)```", text, re.S)
    assert block, "README lost its Python example"
    code = block.group(1)
    assert len(code.strip().splitlines()) <= 12
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README.md", "exec"), {})
    ate = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(\S+)\s+ATE ([0-9.]+) m$", out.getvalue(), re.M)}
    assert set(ate) == {"dead-reckoning", "ekf", "fastslam2", "graph"}
    assert ate["graph"] < ate["ekf"] < ate["dead-reckoning"]
    assert ate["fastslam2"] < 0.5 * ate["dead-reckoning"]
