"""Divergence and non-finite states are errors naming the step or iteration, never an "ok" result."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from slam2d.cli.main import main
from slam2d.lab.runner import DivergenceError, run_named
from slam2d.sim.simulator import simulate


@pytest.mark.parametrize(("estimator", "value"), [("dead-reckoning", np.nan), ("dead-reckoning", np.inf),
                                                   ("fastslam", 1e300)])
def test_non_finite_odometry_is_an_error_naming_the_step(estimator, value):
    log = simulate("room", seed=0, steps=12)
    od = log.odometry.copy()
    od[5] = value
    with warnings.catch_warnings(), pytest.raises(DivergenceError, match="step 6"):
        warnings.simplefilter("ignore", RuntimeWarning)
        run_named(estimator, log=dataclasses.replace(log, odometry=od), seed=0)


def test_cli_run_on_a_log_with_nan_odometry_fails_in_one_line(tmp_path, capsys):
    log = simulate("room", seed=0, steps=12)
    od = log.odometry.copy()
    od[3] = np.nan
    p = dataclasses.replace(log, odometry=od).save(tmp_path / "nan.npz")
    assert main(["run", "--log", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "odometry has non-finite values" in err[0], err  # refused at load time


def test_gauss_newton_divergence_from_chordal_init_is_an_error(tmp_path, capsys):
    g = tmp_path / "ang.g2o"
    g.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 1e300\nVERTEX_SE2 2 1 0 -1e300\n"
                 "EDGE_SE2 0 1 1 0 1e300 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 1e300 1 0 0 1 0 1\n"
                 "EDGE_SE2 0 2 1 0 1e300 1 0 0 1 0 1\n")
    assert main(["optimize", str(g), "--out", str(tmp_path / "o.g2o"), "--solver", "gn", "--init", "chordal"]) == 2
    err = capsys.readouterr().err
    assert "diverged" in err and "iteration" in err
    assert not (tmp_path / "o.g2o").exists()
