"""JSON records are standard JSON: NaN and infinities become null, numpy values become Python values."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam2d.cli.common import write_json
from slam2d.io.json_text import dumps, json_ready


def strict_loads(text: str) -> object:
    """json.loads that refuses NaN / Infinity, as JavaScript's JSON.parse and other strict parsers do."""
    def refuse(name: str) -> object:
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)


def test_non_finite_values_become_null_and_numpy_values_python() -> None:
    rec = {"a": float("nan"), "b": [1.0, float("inf"), -float("inf")], "c": np.float64(np.nan), "d": np.int64(3),
           "e": np.array([[0.5, np.nan]]), "f": {1: np.bool_(True)}, "g": (np.float32(0.25), "x")}
    out = strict_loads(dumps(rec, sort_keys=True))
    assert out == {"a": None, "b": [1.0, None, None], "c": None, "d": 3, "e": [[0.5, None]], "f": {"1": True},
                   "g": [0.25, "x"]}
    assert json_ready(rec)["d"].__class__ is int


def test_plain_json_would_not_parse_strictly() -> None:
    # the failure the helper exists for: Python's default output is not JSON
    with pytest.raises(ValueError, match="NaN"):
        strict_loads(json.dumps({"a": float("nan")}))


def test_cli_json_records_parse_strictly(tmp_path: Path) -> None:
    path = tmp_path / "r.json"
    write_json(path, {"rel_trans_mean_m": float("nan"), "ate_rmse_m": np.float64(0.125), "steps": np.int64(200)})
    assert strict_loads(path.read_text()) == {"ate_rmse_m": 0.125, "rel_trans_mean_m": None, "steps": 200}
