"""The map server's floor-marker survey file (fleet.survey) and the joint graph's raster thinning."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam2d.fleet.joint import JointGraph
from slam2d.fleet.survey import read_survey, write_survey


def test_round_trip_with_header_comments_and_blank_lines(tmp_path: Path) -> None:
    survey = ((0, 4.0, 3.0), (7, 14.0012, 9.5), (4294967295, -1.25, 0.0))
    p = tmp_path / "s.csv"
    write_survey(p, survey)
    assert read_survey(p) == survey
    p.write_text("# surveyed 2026-12-01\n\nid, x, y\n3, 1.5, 2\n  \n9,0,-4.25\n")
    assert read_survey(p) == ((3, 1.5, 2.0), (9, 0.0, -4.25))


@pytest.mark.parametrize(("text", "where", "what"), [
    ("id,x,y\n1,2\n", ":2", "3 fields"),
    ("1,2,3\n-1,2,3\n", ":2", "outside"),
    ("1,2,3\n2,inf,3\n", ":2", "finite"),
    ("1,2,3\n2,x,3\n", ":2", "numbers"),
    ("1,2,3\n1,2,3\n", ":2", "line 1"),
    ("id,x,y\nid,x,y\n", ":2", "not an integer"),  # a header only as the first row
])
def test_bad_rows_name_file_and_line(tmp_path: Path, text: str, where: str, what: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ValueError) as e:
        read_survey(p)
    assert f"bad.csv{where}:" in str(e.value) and what in str(e.value)


def test_raster_draws_the_newest_keyframe_per_place() -> None:
    """Ten passes over one spot facing east, one facing north, one 3 m away: three places, the newest of each."""
    g = JointGraph()
    g.poses = np.array([[1.2, 1.3, 0.01 * k] for k in range(10)] + [[1.4, 1.1, np.pi / 2], [4.2, 1.3, 0.0]])
    keep = g._newest_per_place(np.arange(len(g.poses)))
    assert keep.tolist() == [9, 10, 11]
