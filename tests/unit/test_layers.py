"""Importing a low layer loads nothing above it (the root package is lazy; see docs/ARCHITECTURE.md). The full
layer contract is checked statically by `lint-imports` (pyproject [tool.importlinter], run by `make lint`)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src"

#: module -> the slam2d packages it may load (itself and the layers below it)
ALLOWED = {
    "slam2d.geometry": ("slam2d.geometry",),
    "slam2d.models": ("slam2d.geometry", "slam2d.models", "slam2d.config"),
    "slam2d.log": ("slam2d.log",),
    "slam2d.estimator": ("slam2d.estimator", "slam2d.log"),
}


def _loaded_slam2d_modules(module: str) -> set[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}
    err = subprocess.run([sys.executable, "-X", "importtime", "-c", f"import {module}"], capture_output=True,
                         text=True, check=True, env=env).stderr
    # lines: "import time: self [us] | cumulative | imported package" (nested imports are indented)
    names = {m.group(1) for m in re.finditer(r"\|\s+(slam2d[\w.]*)\s*$", err, flags=re.M)}
    assert module in names, f"-X importtime output not understood:\n{err[:2000]}"
    return names


@pytest.mark.parametrize("module", sorted(ALLOWED))
def test_importing_a_layer_loads_nothing_above_it(module):
    loaded = _loaded_slam2d_modules(module)
    ok = ALLOWED[module]
    above = sorted(m for m in loaded if m != "slam2d" and not any(m == p or m.startswith(p + ".") for p in ok))
    assert above == [], f"import {module} loaded {above}"
