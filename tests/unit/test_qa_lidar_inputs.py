"""QA pass on lidar log input and the ``slam2d run`` / ``slam2d lidar`` paths for CARMEN logs: inputs never
overwritten, bad relations files fail before the run, devices and FIFOs refused, cuts that leave nothing refused,
``--dataset-opt`` reaching the CARMEN reader, counts that match the lines they name."""

from __future__ import annotations

import json
import math
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slam2d.cli.main import main
from slam2d.eval.relations import read_relations
from slam2d.io.carmen import CarmenConfig, read_carmen
from slam2d.log import LogFormatError


def flaser(ranges: list[float], pose: tuple[float, float, float], ts: float) -> str:
    r = " ".join(f"{v}" for v in ranges)
    x, y, th = pose
    return f"FLASER {len(ranges)} {r} {x} {y} {th} {x} {y} {th} {ts} host {ts + 0.01}"


def robotlaser(ranges: list[float], head: str, ts: float) -> str:
    r = " ".join(f"{v}" for v in ranges)
    return f"ROBOTLASER1 0 {head} 80 0.01 0 {len(ranges)} {r} 0 0 0 0 0 0 0 0 0 0.5 0.5 0 {ts} host {ts}"


def small_log(tmp: Path, name: str = "log.clf", scans: int = 6, extra: list[str] | None = None) -> Path:
    """``scans`` FLASER records 0.1 s apart turning 0.3 rad each, plus ``extra`` lines at the end."""
    lines = ["PARAM robot_use_laser on nohost 0"]
    for k in range(scans):
        lines.append(flaser([1.0 + 0.1 * k, 2.0, 3.0, 4.0], (0.1 * k, 0.0, 0.3 * k), 10.0 + 0.1 * k))
    p = tmp / name
    p.write_text("\n".join(lines + (extra or [])) + "\n")
    return p


def one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("argv", [
    ["run", "--dataset", "{log}", "--trajectory", "{log}"],
    ["run", "--dataset", "{log}", "--estimator", "dead-reckoning", "--map", "{log}"],
    ["run", "--dataset", "{log}", "--json", "{rel}"],
    ["lidar", "--dataset", "{log}", "--out", "{d}/m.png", "--json", "{rel}"],
])
def test_outputs_never_overwrite_the_carmen_log_or_the_relations_beside_it(
        tmp_path: Path, argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    log = small_log(tmp_path)
    rel = tmp_path / "log.relations"
    rel.write_text("10.0 10.1 0.1 0 0 0 0 0.3\n")
    before = (log.read_bytes(), rel.read_bytes())
    args = [a.format(log=log, rel=rel, d=tmp_path) for a in argv]
    assert main(args) == 2
    err = one_line_error(capsys)
    assert "would overwrite the input" in err and "--force" in err
    assert (log.read_bytes(), rel.read_bytes()) == before


def test_a_bad_relations_file_fails_before_the_run_and_writes_nothing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    import slam2d.cli.run as run_mod
    import slam2d.lab.runner as runner

    def no_run(*_: Any, **__: Any) -> Any:
        raise AssertionError("the estimator ran before the relations file was checked")

    monkeypatch.setattr(run_mod, "run_named", no_run)
    monkeypatch.setattr(runner, "run_named", no_run)
    log = small_log(tmp_path)
    (tmp_path / "log.relations").write_text("10.0 10.1 0.1 0 0 0 0\n")  # 7 fields
    traj, js = tmp_path / "t.txt", tmp_path / "r.json"
    assert main(["run", "--dataset", str(log), "--trajectory", str(traj), "--json", str(js)]) == 2
    assert "log.relations:1: relation needs 8 fields" in one_line_error(capsys)
    assert main(["lidar", "--dataset", str(log), "--out", str(tmp_path / "m.png"), "--relations",
                 str(tmp_path / "missing.relations")]) == 2
    assert "missing.relations: no such relations file" in one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.clf", "log.relations"]


def test_relations_reader_refuses_devices_directories_and_binary_lines(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match="/dev/zero: not a regular file"):
        read_relations("/dev/zero")  # used to read without end (out of memory)
    with pytest.raises(IsADirectoryError):
        read_relations(tmp_path)
    blob = tmp_path / "blob.relations"
    blob.write_bytes(b"1 2 0 0 0 0 0 0\n" + b"\x01" * 200_000)
    with pytest.raises(LogFormatError, match=r"blob\.relations:2: line longer than"):
        read_relations(blob)


def _finishes(fn: Any, seconds: float = 20.0) -> BaseException | None:
    """Run ``fn`` in a daemon thread; the exception it raised (None if none), failing the test if it blocks."""
    out: list[BaseException | None] = []

    def target() -> None:
        try:
            fn()
            out.append(None)
        except BaseException as e:  # handed back to the test
            out.append(e)

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(seconds)
    assert out, "blocked (a FIFO opened for reading without a writer)"
    return out[0]


def test_carmen_reader_refuses_a_fifo_and_a_directory(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.clf"
    os.mkfifo(fifo)
    try:
        e = _finishes(lambda: read_carmen(fifo))
        assert isinstance(e, LogFormatError) and "fifo.clf: not a regular file" in str(e)
    finally:  # unblock a reader stuck in open() (a reader without the check) so its thread can end
        try:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:
            pass
    (tmp_path / "dir.clf").mkdir()
    with pytest.raises(IsADirectoryError, match="is a directory"):
        read_carmen(tmp_path / "dir.clf")


def test_max_time_shorter_than_the_first_step_is_an_error_not_the_whole_log(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from slam2d.cli.lidar import load_laser_log

    log = small_log(tmp_path)
    with pytest.raises(ValueError, match=r"log\.clf: the requested cut .* leaves no step"):
        load_laser_log(str(log), max_time_s=0.05)  # the second scan comes 0.1 s after the first
    assert load_laser_log(str(log), max_time_s=0.25).num_steps == 2
    assert load_laser_log(str(log), max_steps=3, max_time_s=10.0).num_steps == 3
    assert main(["run", "--dataset", str(log), "--max-time", "0.05"]) == 2
    assert "leaves no step" in one_line_error(capsys)


def test_dataset_opt_reaches_the_carmen_reader_and_dataset_path_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = small_log(tmp_path, extra=["FLASER 4 1.0 2.0"])  # a truncated last line (line 8)
    js = tmp_path / "r.json"
    assert main(["run", "--dataset", str(log), "--json", str(js)]) == 2
    assert "log.clf:8: truncated FLASER" in one_line_error(capsys)
    assert main(["run", "--dataset", str(log), "--dataset-opt", "on_error=skip", "--json", str(js)]) == 0
    rec = json.loads(js.read_text())
    assert rec["log_skipped_lines"] == 1 and rec["steps"] == 5
    assert "log.clf:8: truncated FLASER" in capsys.readouterr().err
    for opt, msg in [("nope=1", "unknown field(s) ['nope'] in CarmenConfig"),
                     ("max_range_m=abc", "max_range_m must be of type float"),
                     ("on_error=maybe", "on_error must be one of ['raise', 'skip']")]:
        assert main(["run", "--dataset", str(log), "--dataset-opt", opt]) == 2
        assert msg in one_line_error(capsys)
    assert main(["run", "--dataset", str(log), "--dataset-path", str(tmp_path)]) == 2
    assert "--dataset-path does not apply to a CARMEN log" in one_line_error(capsys)
    # the alias takes the same options
    out = tmp_path / "m.png"
    assert main(["lidar", "--dataset", str(log), "--dataset-opt", "nope=1", "--out", str(out)]) == 2
    assert "unknown field(s) ['nope'] in CarmenConfig" in one_line_error(capsys)
    assert main(["lidar", "--dataset", str(log), "--dataset-opt", "on_error=skip", "--out", str(out)]) == 0
    assert "log.clf:8: truncated FLASER" in capsys.readouterr().err and out.exists()


def test_invalid_beam_count_matches_the_lines_it_names(tmp_path: Path) -> None:
    # a 0 reading is a no-return like 81.83, not a NaN/inf/negative one: not counted (the note would name no line)
    log = read_carmen(small_log(tmp_path, extra=[flaser([0.0, 2.0, 3.0, 4.0], (1, 0, 0), 11.0)]))
    assert log.num_scans == 7 and log.ranges_m[6, 0] == log.max_range_m
    assert (log.invalid_beams, log.invalid_beam_lines) == (0, ())
    # the NaN beams of a line skipped for its beam count are neither counted nor listed
    lines = [flaser([float("nan"), 2.0, 3.0], (1, 0, 0), 11.0), flaser([float("nan"), -1.0, 3.0, 4.0], (1, 0, 0), 11.1)]
    log = read_carmen(small_log(tmp_path, "b.clf", extra=lines), CarmenConfig(on_error="skip"))
    assert log.num_scans == 7 and len(log.problems) == 1 and ":8: FLASER record: 3 beams" in log.problems[0]
    assert log.invalid_beams == 2 and len(log.invalid_beam_lines) == 1 and ":9: 2 NaN" in log.invalid_beam_lines[0]


def test_robotlaser_header_that_is_not_finite_names_its_own_line(tmp_path: Path) -> None:
    good = robotlaser([1.0] * 4, f"{-math.pi / 2} {math.pi} {math.pi / 4}", 1.1)
    for head in ("nan 3.14 0.785", "-1.57 3.14 inf", "-1.57 3.14 0"):
        p = tmp_path / "r.clf"
        p.write_text(robotlaser([1.0] * 4, head, 1.0) + "\n" + good + "\n")
        with pytest.raises(LogFormatError, match=r"r\.clf:1: ROBOTLASER1 record: start_angle, fov, resolution"):
            read_carmen(p)


def test_huge_counts_and_too_few_scans_have_short_clear_messages(tmp_path: Path) -> None:
    p = tmp_path / "h.clf"
    p.write_text("FLASER 1e300 1 1 1 0 0 0 0 0 0 1.0 h 1\n")
    with pytest.raises(LogFormatError) as e:
        read_carmen(p)
    assert "h.clf:1: truncated FLASER record: num_readings is 1e300" in str(e.value) and len(str(e.value)) < 200
    # every scan skipped (no usable beam): the error says why there are no scans
    p.write_text("PARAM x 1 nohost 0\n" + flaser([81.83] * 4, (0, 0, 0), 1.0) + "\n")
    with pytest.raises(LogFormatError, match=r"need at least 2 scans to build a log \(got 0; 1 lines skipped, "
                                             r"first: .*h\.clf:2: FLASER record with no usable beam"):
        read_carmen(p).to_log()


def test_a_map_that_cannot_be_built_leaves_no_trajectory_behind(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    log = small_log(tmp_path, extra=[flaser([1.0, 2.0, 3.0, 4.0], (1e6, 0.0, 0.0), 11.0)])
    traj = tmp_path / "t.txt"
    assert main(["run", "--dataset", str(log), "--trajectory", str(traj), "--map", str(tmp_path / "m.png")]) == 2
    assert "too large" in one_line_error(capsys)
    assert not traj.exists()


def test_trajectory_on_a_full_device_names_the_file(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    log = small_log(tmp_path)
    for opt in ("--trajectory", "--map"):
        assert main(["run", "--dataset", str(log), opt, "/dev/full"]) == 2
        assert "/dev/full: No space left on device" in one_line_error(capsys)


def test_tum_file_with_skipped_scans_keeps_original_stamps_and_headings(tmp_path: Path) -> None:
    """A log with a skipped scan (no usable beam), a NaN beam and CRLF line ends: the TUM file has one row per kept
    scan, the log's own stamps, and quaternions whose heading is the pose's (dead reckoning: the logged poses)."""
    log = small_log(tmp_path, extra=[flaser([81.83] * 4, (0.7, 0, 1.9), 10.65),
                                     flaser([float("nan"), 2.0, 3.0, 4.0], (0.8, 0.1, 2.5), 10.7)])
    log.write_bytes(log.read_bytes().replace(b"\n", b"\r\n"))
    traj = tmp_path / "t.txt"
    assert main(["run", "--dataset", str(log), "--trajectory", str(traj)]) == 0
    rows = np.loadtxt(traj)
    assert rows[:, 0].tolist() == [10.0, 10.1, 10.2, 10.3, 10.4, 10.5, 10.7]
    heading = 2 * np.arctan2(rows[:, 6], rows[:, 7])
    expect = np.array([0.0, 0.3, 0.6, 0.9, 1.2, 1.5, 2.5])  # pose 0 is the origin: headings relative to the first
    assert np.allclose(np.angle(np.exp(1j * (heading - expect))), 0, atol=1e-8)
    assert np.allclose(np.hypot(rows[:, 6], rows[:, 7]), 1) and np.all(rows[:, 3:6] == 0)
