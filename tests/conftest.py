"""Shared test fixtures: dataset location and deterministic generators."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

settings.register_profile("ci", deadline=None, max_examples=60, derandomize=True)
settings.load_profile("ci")

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("SLAM2D_DATA", REPO.parent / "shared" / "datasets"))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def dataset_path(*parts: str) -> Path:
    """Path into ../shared/datasets; skips the calling test cleanly when it is absent."""
    p = DATASETS.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"dataset not available: {p}")
    return p
