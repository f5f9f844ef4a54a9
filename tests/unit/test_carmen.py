"""CARMEN reader: good records, unknown record types, truncated lines, NaN/inf/max-range beams, file:line errors."""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np
import pytest

from slam2d.eval.relations import read_relations
from slam2d.io.carmen import CarmenConfig, flaser_angles, read_carmen
from slam2d.log import LogFormatError


def flaser(ranges: list[float] | np.ndarray, pose: tuple[float, float, float], ts: float) -> str:
    r = " ".join(f"{v}" for v in ranges)
    x, y, th = pose
    return f"FLASER {len(ranges)} {r} {x} {y} {th} {x} {y} {th} {ts} host {ts + 0.01}"


def write(tmp: Path, lines: list[str], name: str = "log.clf", compress: bool = False) -> Path:
    text = "\n".join(lines) + "\n"
    p = tmp / (name + (".bz2" if compress else ""))
    if compress:
        p.write_bytes(bz2.compress(text.encode()))
    else:
        p.write_text(text)
    return p


def good_lines() -> list[str]:
    return [
        "# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp",
        "PARAM robot_use_laser on nohost 0",
        "ODOM 0.0 0.0 0.0 0.1 0.0 0.0 1.0 host 1.01",
        flaser([1.0, 2.0, 3.0, 4.0], (0.0, 0.0, 0.0), 1.05),
        "ODOM 0.1 0.0 0.0 0.1 0.0 0.0 1.1 host 1.11",
        flaser([1.1, 2.1, 3.1, 4.1], (0.1, 0.0, 0.05), 1.15),
    ]


@pytest.mark.parametrize("compress", [False, True])
def test_reads_good_records(tmp_path: Path, compress: bool) -> None:
    log = read_carmen(write(tmp_path, good_lines(), compress=compress))
    assert log.num_scans == 2 and log.ranges_m.shape == (2, 4)
    assert np.allclose(log.stamps_s, [1.05, 1.15]) and np.allclose(log.poses[1], [0.1, 0.0, 0.05])
    assert np.allclose(log.odom_poses[:, 0], [0.0, 0.1]) and np.allclose(log.odom_stamps_s, [1.0, 1.1])
    assert np.allclose(log.angles_rad, -np.pi / 2 + np.arange(4) * np.pi / 4)
    assert log.unknown == {} and log.record_counts["PARAM"] == 1
    lg = log.to_log()
    assert lg.num_steps == 1 and np.allclose(lg.odometry[0], [0.1, 0.0, 0.05])
    assert lg.step(1).scan is not None


def test_flaser_angle_conventions() -> None:
    assert np.allclose(np.diff(flaser_angles(180)), np.pi / 180) and np.isclose(flaser_angles(180)[0], -np.pi / 2)
    assert np.allclose(flaser_angles(361)[[0, -1]], [-np.pi / 2, np.pi / 2])
    assert np.isclose(np.diff(flaser_angles(360))[0], np.pi / 360)


def test_unknown_record_types_are_counted_and_reported(tmp_path: Path) -> None:
    lines = good_lines() + ["RAWLASER1 0 -1.57 3.14 0.017 80 0.01 0 0 0 1.3 host 1.31", "TRUEPOS 1 2 3 4 5 6 1.4 h 1",
                            "TRUEPOS 1 2 3 4 5 6 1.5 h 1"]
    log = read_carmen(write(tmp_path, lines))
    assert log.unknown == {"RAWLASER1": 1, "TRUEPOS": 2}
    assert "RAWLASER1=1" in log.summary() and "TRUEPOS=2" in log.summary()


def test_truncated_and_non_numeric_lines_name_file_and_line(tmp_path: Path) -> None:
    lines = good_lines()
    lines.insert(4, "FLASER 4 1.0 2.0 3.0")  # truncated (line 5)
    p = write(tmp_path, lines)
    with pytest.raises(LogFormatError, match=r"log\.clf:5: truncated FLASER"):
        read_carmen(p)
    log = read_carmen(p, CarmenConfig(on_error="skip"))
    assert log.num_scans == 2 and len(log.problems) == 1 and ":5:" in log.problems[0]
    bad = good_lines()
    bad[2] = "ODOM 0.0 abc 0.0 0.1 0.0 0.0 1.0 host 1.01"
    with pytest.raises(LogFormatError, match=r":3: ODOM record: .* non-numeric value 'abc'"):
        read_carmen(write(tmp_path, bad, name="b.clf"))
    neg = good_lines()
    neg[3] = "FLASER -3 1 2 3"
    with pytest.raises(LogFormatError, match=r":4: FLASER record: num_readings"):
        read_carmen(write(tmp_path, neg, name="c.clf"))
    mixed = good_lines() + [flaser([1.0, 2.0, 3.0], (0, 0, 0), 2.0)]
    with pytest.raises(LogFormatError, match=r":7: FLASER record: 3 beams"):
        read_carmen(write(tmp_path, mixed, name="d.clf"))


def test_nan_inf_and_max_range_beams_become_no_returns(tmp_path: Path) -> None:
    lines = good_lines()
    lines[3] = flaser([float("nan"), float("inf"), 81.83, -1.0, 2.0], (0.0, 0.0, 0.0), 1.05)
    lines[5] = flaser([1.1, 2.1, 3.1, 4.1, 5.1], (0.1, 0.0, 0.05), 1.15)
    log = read_carmen(write(tmp_path, lines), CarmenConfig(max_range_m=40.0))
    assert np.all(log.ranges_m[0, :4] == 40.0) and log.invalid_beams == 3
    assert np.all(log.ranges_m[1] < 40.0)
    nanpose = good_lines()
    nanpose[3] = flaser([1.0, 2.0, 3.0, 4.0], (float("nan"), 0.0, 0.0), 1.05)
    with pytest.raises(LogFormatError, match=r":4: FLASER record: non-finite pose"):
        read_carmen(write(tmp_path, nanpose, name="e.clf"))


def test_corrupt_bz2_and_missing_files(tmp_path: Path) -> None:
    good = bz2.compress(("\n".join(good_lines() * 50) + "\n").encode())
    p = tmp_path / "cut.clf.bz2"
    p.write_bytes(good[: len(good) // 2])
    with pytest.raises(LogFormatError, match="truncated compressed file"):
        read_carmen(p)
    with pytest.raises(FileNotFoundError):
        read_carmen(tmp_path / "nope.clf")
    empty = read_carmen(write(tmp_path, ["# only a comment"], name="empty.clf"))
    assert empty.num_scans == 0
    with pytest.raises(LogFormatError, match="at least 2 scans"):
        empty.to_log()


def test_relations_reader(tmp_path: Path) -> None:
    p = tmp_path / "x.relations"
    p.write_text("1.0 2.0 0.5 0.1 0 0 0 0.2\n3.0 4.0 -0.5 0.0 0 0 0 -0.1\n")
    r = read_relations(p)
    assert np.allclose(r.stamps, [[1, 2], [3, 4]]) and np.allclose(r.rel, [[0.5, 0.1, 0.2], [-0.5, 0.0, -0.1]])
    p.write_text("1.0 2.0 0.5 0.1 0 0 0 0.2\n3.0 4.0 -0.5\n")
    with pytest.raises(LogFormatError, match=r"x\.relations:2: relation needs 8 fields"):
        read_relations(p)


def test_bad_scans_are_errors_or_counted_skips_with_file_and_line(tmp_path: Path) -> None:
    lines = good_lines()
    # NaN / inf / negative beams: kept as no-returns, counted, their line named
    lines[5] = flaser([float("nan"), float("inf"), -1.0, 4.1], (0.1, 0.0, 0.05), 1.15)
    log = read_carmen(write(tmp_path, lines))
    assert log.invalid_beams == 3 and log.invalid_beam_lines == (f"{tmp_path / 'log.clf'}:6: 3 NaN/inf/negative "
                                                                  "ranges read as no return",)
    assert np.all(log.ranges_m[1, :3] == log.max_range_m)
    # zero usable beams (all no-return) and FLASER 0 (used to divide by zero): skipped, named
    lines = [*good_lines(), flaser([81.83] * 4, (0.2, 0, 0), 1.25), "FLASER 0 0 0 0 0 0 0 1.3 nohost 1"]
    log = read_carmen(write(tmp_path, lines))
    assert log.num_scans == 2 and len(log.problems) == 2
    assert log.problems[0].endswith("log.clf:7: FLASER record with no usable beam (4 readings, all NaN, inf, <= 0 "
                                    "or >= max range 40.0 m): scan skipped") and ":8: FLASER" in log.problems[1]
    # timestamps going backwards: kept in file order and listed (default), an error naming the line, or a skip
    lines = [*good_lines(), flaser([1.0, 2.0, 3.0, 4.0], (0.2, 0, 0), 1.10)]
    log = read_carmen(write(tmp_path, lines))
    assert log.num_scans == 3 and len(log.backwards_stamps) == 1 and "log.clf:7: FLASER record: timestamp 1.100000 " \
        "goes backwards" in log.backwards_stamps[0]
    assert np.all(np.diff(log.to_log().stamps_s) >= 0)
    with pytest.raises(LogFormatError, match=r"log\.clf:7: FLASER record: timestamp 1\.100000 goes backwards"):
        read_carmen(write(tmp_path, lines), CarmenConfig(backwards_stamps="raise"))
    log = read_carmen(write(tmp_path, lines), CarmenConfig(backwards_stamps="skip", on_error="skip"))
    assert log.num_scans == 2 and "log.clf:7" in log.problems[0]
    # fewer beams than the first scan's angle table
    lines = [*good_lines(), flaser([1.0, 2.0, 3.0], (0.2, 0, 0), 1.3)]
    with pytest.raises(LogFormatError, match=r"log\.clf:7: FLASER record: 3 beams"):
        read_carmen(write(tmp_path, lines))


@pytest.mark.parametrize("command", ["run", "lidar"])
def test_the_commands_name_every_counted_problem(tmp_path: Path, command: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """``slam2d run`` / ``slam2d lidar`` on a log with NaN beams, a scan with no usable beam, a stamp going
    backwards and a relation whose stamp is not in the log: each kind is a note with its count and first file:line
    on stderr and a count in the JSON record, and the run goes on."""
    import json

    from slam2d.cli.main import main

    lines = [*good_lines(), flaser([float("nan"), float("inf"), -1.0, 4.1], (0.2, 0.0, 0.1), 1.25),
             flaser([81.83] * 4, (0.3, 0, 0.15), 1.35), flaser([1.2, 2.2, 3.2, 4.2], (0.4, 0, 0.2), 1.20),
             "TRUEPOS 1 2 3 4 5 6 1.4 h 1"]
    log = write(tmp_path, lines)
    (tmp_path / "log.relations").write_text("1.05 1.15 0.1 0 0 0 0 0.05\n1.05 9.99 0.1 0 0 0 0 0.05\n")
    out = tmp_path / "r.json"
    args = ["--estimator", "lidar"] if command == "run" else ["--out", str(tmp_path / "m.png")]
    assert main([command, "--dataset", str(log), *args, "--json", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"NaN/inf/negative ranges read as no return: 3; first: {log}:7: 3 NaN/inf" in err
    assert f"a scan with no usable beam): 1; first: {log}:8: FLASER record with no usable beam" in err
    assert f"timestamp goes backwards, kept in file order: 1; first: {log}:9:" in err
    assert "1 of 2 relations name stamps the estimate has no pose for, left out; first: " \
           f"{tmp_path / 'log.relations'}:2: stamp 9.990000" in err
    assert "record types this reader does not use, ignored: TRUEPOS x1" in err
    rec = json.loads(out.read_text())
    assert (rec["log_invalid_beams"], rec["log_skipped_lines"], rec["log_backwards_stamps"]) == (3, 1, 1)
    assert rec["log_unknown_records"] == {"TRUEPOS": 1}
    assert (rec["relations"], rec["relations_used"]) == (2, 1)


def test_to_log_keeps_the_original_stamps(tmp_path: Path) -> None:
    lines = [*good_lines(), flaser([1.2, 2.2, 3.2, 4.2], (0.2, 0.0, 0.1), 976052896.784509)]
    log = read_carmen(write(tmp_path, lines)).to_log()
    assert log.metadata["stamps_original_s"] == [1.05, 1.15, 976052896.784509]
    assert log.num_steps == 2 and log.scan_ranges_m is not None and log.scan_ranges_m.shape == (2, 4)
    assert log.metadata["dataset"] == "log"


def test_bz2_bomb_and_endless_lines_stop_at_the_caps(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # 64 MB of zeros compress to ~50 bytes; the decompressed-size cap must stop the read, not the memory
    bomb = tmp_path / "bomb.clf.bz2"
    comp = bz2.BZ2Compressor(9)
    parts = [comp.compress(b"\0" * (1 << 20)) for _ in range(64)]
    bomb.write_bytes(b"".join(parts) + comp.flush())
    assert bomb.stat().st_size < 10_000
    monkeypatch.setenv("SLAM2D_MAX_FILE_MB", "8")
    with pytest.raises(LogFormatError, match=r"bomb\.clf\.bz2.*(larger than 8 MB|line longer)"):
        read_carmen(bomb)
    monkeypatch.setenv("SLAM2D_MAX_FILE_MB", "2048")
    monkeypatch.setenv("SLAM2D_MAX_LINE_CHARS", "1000")
    long_line = tmp_path / "long.clf"
    long_line.write_text("FLASER 1 1.0 0 0 0 0 0 0 1.0 h 1.0\n" + "ODOM " + "1 " * 5000 + "\n")
    with pytest.raises(LogFormatError, match=r"long\.clf:2: line longer than 1000"):
        read_carmen(long_line)
