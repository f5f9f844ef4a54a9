"""Helpers tests import by name (``from testkit import dataset_path``).

They live here, not in ``conftest.py``: tests/ and tests/web/ each have a ``conftest`` module, and which one
``from conftest import ...`` finds depends on which folder pytest collected first.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("SLAM2D_DATA", REPO.parent / "shared" / "datasets"))

#: a test beyond the suite's budget (15 min on the loaded 2-core CI machine): whole real logs and 30-run Monte Carlo.
#: It runs with SLAM2D_LONG_TESTS=1 (`make test-long`); `make test` keeps a shorter test of the same kind (one robot,
#: one scenario, one back end on the log; simulated fleets for the MRCLAM multi-robot runs), and the benchmarks print
#: the full numbers the README states
LONG = pytest.mark.skipif(not os.environ.get("SLAM2D_LONG_TESTS"),
                          reason="long test: set SLAM2D_LONG_TESTS=1 (make test-long)")


def dataset_path(*parts: str) -> Path:
    """Path into ../shared/datasets; skips the calling test cleanly when it is absent."""
    p = DATASETS.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"dataset not available: {p}")
    return p


def chain(u: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Dead reckoning: odometry increments ``u`` (T,3) composed from ``start`` (3,) (:func:`slam2d.geometry.se2.
    compose_chain`, in the tests' argument order). Shapes -> (T+1,3)."""
    from slam2d.geometry import se2

    return se2.compose_chain(start, u)


def dense_joseph(mu, P, js, z, R):  # type: ignore[no-untyped-def]
    """The plain textbook EKF update of range-bearing observations ``z`` (K,2) of landmarks ``js``, a reference for
    the fast kernels: stacked dense H (2K x n), K = P H^T S^-1, mean mu + K nu, Joseph-form covariance
    (I-KH) P (I-KH)^T + K R K^T."""
    from slam2d.geometry.angles import wrap_angle
    from slam2d.models.sensors import range_bearing, range_bearing_jacobians

    n, k = mu.size, len(js)
    H = np.zeros((2 * k, n))
    zp = np.zeros((k, 2))
    for i, j in enumerate(js):
        lm = mu[3 + 2 * j: 5 + 2 * j]
        zp[i] = range_bearing(mu[:3], lm)
        hp, hl = range_bearing_jacobians(mu[:3], lm)
        H[2 * i: 2 * i + 2, :3] = hp
        H[2 * i: 2 * i + 2, 3 + 2 * j: 5 + 2 * j] = hl
    nu = np.column_stack([z[:, 0] - zp[:, 0], wrap_angle(z[:, 1] - zp[:, 1])]).reshape(-1)
    Rb = np.kron(np.eye(k), R)
    S = H @ P @ H.T + Rb
    K = P @ H.T @ np.linalg.inv(S)
    ikh = np.eye(n) - K @ H
    mu_new = mu + K @ nu
    mu_new[2] = wrap_angle(mu_new[2])
    return mu_new, ikh @ P @ ikh.T + K @ Rb @ K.T
