"""`slam2d report` on result folders whose results.jsonl holds nothing usable: said on stderr (and in the page),
and an empty one is called empty, not missing."""

from __future__ import annotations

from pathlib import Path

import pytest

from slam2d.cli.main import main


def test_a_results_file_of_garbage_is_reported_and_said_on_stderr(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """The page lists unusable lines (by design: the next sweep re-runs them); stderr says so as well."""
    (tmp_path / "results.jsonl").write_text("\n\ngarbage\n")
    assert main(["report", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "1 unusable lines" in err and "0 usable runs" in err and "line 3:" in err, err
    assert "unusable store lines" in (tmp_path / "report" / "index.html").read_text()


def test_an_empty_results_file_is_said_to_be_empty_not_missing(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "results.jsonl").write_text("")
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "holds no runs yet" in err and "has no results.jsonl" not in err, err
