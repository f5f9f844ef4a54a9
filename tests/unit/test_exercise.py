"""``slam2d exercise check``: a correct learner passes, wrong ones fail with the part named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam2d.cli import exercise
from slam2d.cli.main import main

# a learner's file: written from the chapter's formulas, independently of the library's implementation
CORRECT = '''
import numpy as np

def augment_state(mu, P, z_range, z_bearing, R_obs):
    x, y, th = mu[0], mu[1], mu[2]
    a = th + z_bearing
    lm = np.array([x + z_range * np.cos(a), y + z_range * np.sin(a)])
    Gr = np.array([[1.0, 0.0, -z_range * np.sin(a)], [0.0, 1.0, z_range * np.cos(a)]])
    Gz = np.array([[np.cos(a), -z_range * np.sin(a)], [np.sin(a), z_range * np.cos(a)]])
    n = len(mu)
    P_new = np.zeros((n + 2, n + 2))
    P_new[:n, :n] = P
    cross = Gr @ P[:3, :]
    P_new[n:, :n] = cross
    P_new[:n, n:] = cross.T
    P_new[n:, n:] = Gr @ P[:3, :3] @ Gr.T + Gz @ R_obs @ Gz.T
    return np.concatenate([mu, lm]), P_new
'''
# the classic bug: a new landmark with no correlation to the robot or the map
NO_CROSS = CORRECT.replace("cross = Gr @ P[:3, :]", "cross = np.zeros((2, n))")
# forgets the pose uncertainty in the new block
NO_POSE_TERM = CORRECT.replace("Gr @ P[:3, :3] @ Gr.T + ", "")
WRONG_SHAPE = CORRECT.replace("return np.concatenate([mu, lm]), P_new", "return lm, P_new")


def _load(tmp_path: Path, name: str, text: str) -> exercise.AugmentFn:
    p = tmp_path / f"{name}.py"
    p.write_text(text)
    return exercise.load_learner(p)


def test_checker_against_an_independent_reference(tmp_path: Path) -> None:
    good = _load(tmp_path, "good", CORRECT)
    verdicts = exercise.check(good, good, random_count=10)
    assert len(verdicts) == 11 and all(v.ok for v in verdicts)
    # the lesson's numbers: robot (5, 3, pi/4), range 2, bearing 0 -> (6.414, 4.414); P 5x5 -> 7x7
    case = exercise.lesson_case()
    mu, P = good(case.mu, case.P, 2.0, 0.0, case.R_obs)
    assert P.shape == (7, 7)
    np.testing.assert_allclose(mu[-2:], [5 + np.sqrt(2), 3 + np.sqrt(2)], atol=1e-12)
    for name, text, part in [("nocross", NO_CROSS, "cross-covariance"), ("nopose", NO_POSE_TERM, "new landmark block"),
                             ("shape", WRONG_SHAPE, "shapes")]:
        bad = _load(tmp_path, name, text)
        verdicts = exercise.check(bad, good, random_count=5)
        assert not verdicts[0].ok and part in verdicts[0].message
        assert not any(v.ok for v in verdicts)


def test_loader_explains_bad_files(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="defines no function augment_state"):
        _load(tmp_path, "empty", "x = 1\n")
    with pytest.raises(ValueError, match="importing it failed"):
        _load(tmp_path, "broken", "def augment_state(:\n")
    with pytest.raises(ValueError, match="must take"):
        _load(tmp_path, "twoargs", "def augment_state(mu, P):\n    return mu, P\n")


def test_command_passes_a_correct_learner_against_the_library(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "good.py"
    p.write_text(CORRECT)
    assert main(["exercise", "check", str(p)]) == 0
    out = capsys.readouterr().out
    assert "21/21 cases pass" in out and "6.414, 4.414" in out


def test_command_fails_a_wrong_learner_against_the_library(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "bad.py"
    p.write_text(NO_CROSS)
    assert main(["exercise", "check", str(p)]) == 1
    out = capsys.readouterr().out
    assert "FAIL" in out and "cross-covariance" in out
