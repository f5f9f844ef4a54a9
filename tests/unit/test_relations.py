"""The Kümmerle relation metric (slam2d.eval.relations): reader, exact small cases, missing stamps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam2d.eval.relations import read_relations, relation_errors
from slam2d.log import LogFormatError


def write(tmp: Path, text: str) -> Path:
    p = tmp / "x.relations"
    p.write_text(text)
    return p


def test_exact_small_case(tmp_path: Path) -> None:
    # estimate: poses at t=1,2,3; relation 1->2 says (1, 0, 0), the estimate moved (1, 0.1, 0): error 0.1 m, 0 rad;
    # relation 1->3 says (0, 2, pi/2), the estimate went (0, 2, pi/2 + 0.05): error 0 m, 0.05 rad
    p = write(tmp_path, "# header\n1.0 2.0 1 0 0 0 0 0\n\n1.0 3.0000004 0 2 0 0 0 1.5707963267948966\n")
    rel = read_relations(p)
    assert len(rel) == 2 and rel.lines.tolist() == [2, 4]
    poses = np.array([[5.0, 5.0, np.pi / 2], [5.0 - 0.1, 6.0, np.pi / 2], [3.0, 5.0, np.pi + 0.05]])
    err = relation_errors([1.0, 2.0, 3.0], poses, rel)
    assert np.allclose(err.trans_m, [0.1, 0.0], atol=1e-12)
    assert np.allclose(err.rot_rad, [0.0, 0.05], atol=1e-12)
    s = err.summary()
    assert s["trans_mean_m"] == pytest.approx(0.05) and s["trans_std_m"] == pytest.approx(0.05)
    assert s["rot_mean_deg"] == pytest.approx(np.degrees(0.025)) and s["missing"] == 0


def test_error_is_invariant_to_a_global_frame_change(rng: np.random.Generator) -> None:
    poses = rng.normal(0, 3, (20, 3))
    stamps = np.arange(20.0)
    pairs = rng.integers(0, 20, (30, 2))
    from slam2d.eval.relations import Relations
    from slam2d.geometry import se2

    truth = se2.between(poses[pairs[:, 0]], poses[pairs[:, 1]]) + rng.normal(0, 0.01, (30, 3))
    rel = Relations("mem", stamps[pairs], truth, np.arange(1, 31))
    a = relation_errors(stamps, poses, rel)
    b = relation_errors(stamps, se2.compose(np.array([1.0, -2.0, 0.7]), poses), rel)
    assert np.allclose(a.trans_m, b.trans_m) and np.allclose(a.rot_rad, b.rot_rad)
    assert a.trans_m.max() > 0


def test_stamp_not_in_log_names_file_and_line_or_is_counted(tmp_path: Path) -> None:
    p = write(tmp_path, "1.0 2.0 1 0 0 0 0 0\n1.0 9.5 1 0 0 0 0 0\n")
    rel = read_relations(p)
    poses = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"x\.relations:2: stamp 9\.5"):
        relation_errors([1.0, 2.0, 3.0], poses, rel)
    err = relation_errors([1.0, 2.0, 3.0], poses, rel, on_missing="skip")
    assert err.missing == 1 and len(err.trans_m) == 1 and "x.relations:2" in err.skipped[0]


def test_malformed_files_name_file_and_line(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match=r"x\.relations:2: relation needs 8 fields"):
        read_relations(write(tmp_path, "1 2 0 0 0 0 0 0\n1 2 3\n"))
    with pytest.raises(LogFormatError, match=r"x\.relations:1: non-numeric"):
        read_relations(write(tmp_path, "1 2 a 0 0 0 0 0\n"))
    with pytest.raises(LogFormatError, match=r"x\.relations:1: non-finite"):
        read_relations(write(tmp_path, "1 2 nan 0 0 0 0 0\n"))
    with pytest.raises(FileNotFoundError):
        read_relations(tmp_path / "none.relations")
