"""`slam2d report` on result folders whose results.jsonl holds nothing usable: an error that says why, not an empty
report (or a claim that the file is missing)."""

from __future__ import annotations

from pathlib import Path

import pytest

from slam2d.cli.main import main


def test_a_results_file_of_garbage_is_an_error_naming_its_line(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "results.jsonl").write_text("\n\ngarbage\n")
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "results.jsonl:3:" in err and "no usable run" in err, err
    assert not (tmp_path / "report" / "index.html").exists()


def test_an_empty_results_file_is_said_to_be_empty_not_missing(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "results.jsonl").write_text("")
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "holds no runs yet" in err and "has no results.jsonl" not in err, err
