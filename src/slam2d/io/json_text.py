"""JSON that every parser reads: Python's ``json`` writes ``NaN`` and ``Infinity``, which JSON does not have (a strict
parser, JavaScript's ``JSON.parse`` among them, rejects the file). Records carry NaN for "not measured" (a relation
error on a log without relations); it is written as ``null``."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np


def json_ready(v: Any) -> Any:
    """A JSON-safe copy: numpy scalars and arrays to Python, non-finite floats to None, mapping keys to str."""
    if isinstance(v, Mapping):
        return {str(k): json_ready(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [json_ready(x) for x in v]
    if isinstance(v, np.ndarray):
        return json_ready(v.tolist())
    if isinstance(v, np.generic):
        return json_ready(v.item())
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def dumps(v: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`json_ready` ``(v)``: standard JSON (it raises rather than write NaN)."""
    return json.dumps(json_ready(v), allow_nan=False, **kwargs)
