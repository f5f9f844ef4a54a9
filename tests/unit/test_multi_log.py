"""The multi-robot MRCLAM loader (``load_mrclam_all`` / ``load_dataset(..., robot="all")``) and MultiRobotLog.

Synthetic folders with exact measurements check the conventions (one clock, every landmark measurement and every
robot-robot sighting exactly on a step of both robots, ids); the staged MRCLAM 7 checks the counts against the
single-robot loader and PROVENANCE.md and that the sightings agree with the motion-capture truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam2d.geometry import se2
from slam2d.geometry.angles import angle_diff
from slam2d.io.datasets import DatasetFormatError, load_dataset
from slam2d.io.datasets.mrclam import CAMERA_DELAY_S, ODOMETRY_DELAY_S, load_mrclam, load_mrclam_all
from slam2d.log import Log
from slam2d.models.sensors import range_bearing
from slam2d.multi_log import MultiRobotLog, RobotSightings
from testkit import dataset_path

HEADER = "# synthetic\n# file\n# for\n# tests\n"
LANDMARKS = {6: (2.0, 1.0), 7: (-1.0, 2.5), 8: (0.5, -2.0)}
BARCODES = {1: 5, 2: 14, 3: 41, 4: 32, 5: 23, 6: 63, 7: 81, 8: 7}
STARTS = {1: (0.3, -0.2, 0.7), 2: (-1.5, 0.5, -2.0), 3: (1.0, 1.0, 0.0), 4: (-1.0, -1.0, 1.0), 5: (0.0, 2.0, 3.0)}


def _truth(t_cmd: np.ndarray, v: np.ndarray, w: np.ndarray, start, h: float = 1e-3):
    """Fine Euler integration of the commands from ``start`` (an independent reference)."""
    t = np.arange(t_cmd[0], t_cmd[-1] + 0.5, h)
    k = np.searchsorted(t_cmd, t[:-1], side="right") - 1
    th = np.concatenate([[0.0], np.cumsum(w[k] * h)])
    mid = 0.5 * (th[:-1] + th[1:])
    x = np.concatenate([[0.0], np.cumsum(v[k] * np.cos(mid) * h)])
    y = np.concatenate([[0.0], np.cumsum(v[k] * np.sin(mid) * h)])
    return t, se2.compose(np.asarray(start, dtype=float), np.column_stack([x, y, th]))


def write_multi(folder: Path, robots=(1, 2), duration: float = 10.0, offset_s: dict | None = None) -> None:
    """Robots drive different arcs from different starts; each measures every landmark and every other robot
    exactly, every 0.25 s (times on the shared motion-capture samples); robot 1 also sees robot 3 (absent)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "Barcodes.dat").write_text(HEADER + "".join(f"{s}\t{b}\n" for s, b in BARCODES.items()))
    (folder / "Landmark_Groundtruth.dat").write_text(
        HEADER + "".join(f"{s} {x} {y} 0.001 0.001\n" for s, (x, y) in LANDMARKS.items()))
    gts = {}
    for r in robots:
        t0 = 1000.0 + (offset_s or {}).get(r, 0.0)
        t_cmd = t0 + 0.02 * np.arange(int(duration / 0.02))
        v = 0.1 + 0.03 * r * np.sin(0.3 * (t_cmd - t0))
        w = 0.3 * np.sin(0.5 * r * (t_cmd - t0))
        (folder / f"Robot{r}_Odometry.dat").write_text(
            HEADER + "".join(f"{t - ODOMETRY_DELAY_S:.3f} {a:.17g} {b:.17g}\n"
                             for t, a, b in zip(t_cmd, v, w, strict=True)))
        t_ref, gt = _truth(t_cmd, v, w, STARTS[r])
        gts[r] = (t_ref, gt)
        sel = np.arange(0, t_ref.size, 10)  # 100 Hz ground truth
        (folder / f"Robot{r}_Groundtruth.dat").write_text(
            HEADER + "".join(f"{t_ref[i]:.4f} {gt[i, 0]:.17g} {gt[i, 1]:.17g} {gt[i, 2]:.17g}\n" for i in sel))
    for r in robots:
        t_ref, gt = gts[r]
        rows = []
        for i in range(50 + 37 * r, t_ref.size - 600, 250):  # robots see at different times
            t = t_ref[i]
            for s, (x, y) in LANDMARKS.items():
                z = range_bearing(gt[i], np.array([x, y]))
                rows.append(f"{t + CAMERA_DELAY_S:.4f} {BARCODES[s]} {z[0]:.17g} {z[1]:.17g}\n")
            for o in robots:
                if o != r:
                    t_o, gt_o = gts[o]
                    j = int(np.argmin(np.abs(t_o - t)))
                    z = range_bearing(gt[i], gt_o[j, :2])
                    rows.append(f"{t + CAMERA_DELAY_S:.4f} {BARCODES[o]} {z[0]:.17g} {z[1]:.17g}\n")
            if r == 1:
                rows.append(f"{t + CAMERA_DELAY_S:.4f} 41 2.0 0.1\n")  # robot 3: not loaded
        (folder / f"Robot{r}_Measurement.dat").write_text(HEADER + "".join(rows))


def test_one_clock_and_exact_sightings(tmp_path: Path):
    write_multi(tmp_path / "M", offset_s={2: 0.7})
    m = load_mrclam_all(tmp_path / "M", (1, 2))
    assert m.robots == (1, 2) and len(m.logs) == 2
    a, b = m.logs
    assert np.array_equal(a.stamps_s, b.stamps_s) and a.stamps_s[0] == 0.0
    # the shared run starts at the later start (robot 2 starts 0.7 s after robot 1)
    assert m.metadata["t0_unix_s"] == pytest.approx(1000.7, abs=1e-6)
    # each robot's landmark measurements sit exactly on its (shared) steps
    for log in m.logs:
        assert set(log.obs_id.tolist()) == {0, 1, 2}
        pred = range_bearing(log.true_poses[log.obs_step], log.true_landmarks[log.obs_id])
        assert np.max(np.abs(pred[:, 0] - log.obs_range_m)) < 2e-3
    # sightings: both directions, exactly at the step of both robots (the observer's time)
    s = m.sightings
    assert set(zip(s.observer.tolist(), s.observed.tolist(), strict=True)) == {(1, 2), (2, 1)}
    assert m.metadata["counts"]["sightings_of_unselected_robots"] > 0  # robot 3 sightings dropped, counted
    truth = {r: m.log_of(r).true_poses for r in m.robots}
    pred = np.array([range_bearing(truth[o][k], truth[t][k, :2])
                     for k, o, t in zip(s.step, s.observer, s.observed, strict=True)])
    assert np.max(np.abs(pred[:, 0] - s.range_m)) < 5e-3  # truth sampled at 100 Hz, 1 ms clock rounding
    assert np.max(np.abs(angle_diff(pred[:, 1], s.bearing_rad))) < 5e-3
    assert m.metadata["sighting_noise"]["range_std_m"] < 5e-3


def test_single_robot_loader_unchanged_and_cut(tmp_path: Path):
    write_multi(tmp_path / "M")
    one = load_mrclam(tmp_path / "M", 1)
    m = load_mrclam_all(tmp_path / "M", (1, 2))
    # same start here, so the same span; the shared grid holds robot 2's measurement times too
    assert np.all(np.isin(one.stamps_s, m.stamps_s)) and m.num_steps > one.num_steps
    assert np.array_equal(np.sort(one.obs_range_m), np.sort(m.log_of(1).obs_range_m))
    cut = load_mrclam_all(tmp_path / "M", (1, 2), max_time_s=4.0)
    assert cut.stamps_s[-1] <= 4.0 and cut.metadata["cut"]["of"] == m.num_steps
    assert len(cut.sightings) and cut.sightings.step.max() <= cut.num_steps
    assert np.array_equal(cut.sightings.range_m, m.sightings.range_m[: len(cut.sightings)])


def test_load_dataset_all_and_errors(tmp_path: Path):
    write_multi(tmp_path / "M")
    with pytest.raises(DatasetFormatError, match=r"Robot3_Odometry\.dat: missing odometry of robot 3"):
        load_dataset("mrclam", tmp_path / "M", robot="all")
    write_multi(tmp_path / "F", robots=(1, 2, 3, 4, 5), duration=6.0)
    m = load_dataset("mrclam", tmp_path / "F", robot="all", max_steps=30)
    assert isinstance(m, MultiRobotLog) and m.robots == (1, 2, 3, 4, 5) and m.num_steps == 30
    with pytest.raises(ValueError, match="robot must be an integer or 'all'"):
        load_dataset("mrclam", tmp_path / "F", robot="some")  # type: ignore[call-overload]
    with pytest.raises(ValueError, match="robots must be distinct"):
        load_mrclam_all(tmp_path / "F", (1, 1))


def _log(stamps: np.ndarray) -> Log:
    t = stamps.size - 1
    z = np.zeros(0, dtype=np.int64)
    return Log(stamps, np.zeros((t, 3)), z, np.zeros(0), np.zeros(0), z)


def test_multi_robot_log_validation():
    grid = np.arange(5.0)
    s = RobotSightings(np.array([1, 2]), np.array([1, 2]), np.array([2, 1]), np.array([1.0, 2.0]),
                       np.array([0.1, -0.1]))
    m = MultiRobotLog((1, 2), (_log(grid), _log(grid)), s)
    assert m.num_steps == 4 and len(m.head(1).sightings) == 1
    with pytest.raises(ValueError, match="not on the shared step grid"):
        MultiRobotLog((1, 2), (_log(grid), _log(grid + 0.5)), s)
    with pytest.raises(ValueError, match="duplicate robot ids"):
        MultiRobotLog((1, 1), (_log(grid), _log(grid)))
    with pytest.raises(ValueError, match="names robot 1 -> 3"):
        MultiRobotLog((1, 2), (_log(grid), _log(grid)), s.subset(np.array([0])).__class__(
            np.array([1]), np.array([1]), np.array([3]), np.array([1.0]), np.array([0.0])))
    with pytest.raises(ValueError, match="cannot sight itself"):
        RobotSightings(np.array([1]), np.array([2]), np.array([2]), np.array([1.0]), np.array([0.0]))
    with pytest.raises(KeyError, match="robot 4 not in this log"):
        m.log_of(4)


@pytest.mark.slow
def test_mrclam7_all_robots_counts_and_sightings_match_truth():
    m = load_mrclam_all(dataset_path("utias-mrclam-7"))
    assert m.robots == (1, 2, 3, 4, 5) and m.stamps_s[-1] > 880
    # landmark observations: exactly those of the single-robot loader inside the shared (shorter) run
    for r in m.robots:
        one = load_mrclam(dataset_path("utias-mrclam-7"), r)
        t_one = one.stamps_s[one.obs_step] + one.metadata["t0_unix_s"]
        inside = (t_one > m.metadata["t0_unix_s"]) & (t_one <= m.metadata["t0_unix_s"] + m.stamps_s[-1] + 1e-9)
        assert len(m.log_of(r).obs_id) == int(inside.sum())
    # PROVENANCE.md: 650 + 700 + 965 + 555 + 1336 sightings of robots in the files; a few fall outside the run
    assert 4100 <= len(m.sightings) <= 4206
    truth = np.stack([log.true_poses for log in m.logs])
    s = m.sightings
    pred = range_bearing(truth[s.observer - 1, s.step], truth[s.observed - 1, s.step, :2])
    assert np.median(np.abs(s.range_m - pred[:, 0])) < 0.1
    assert np.median(np.abs(angle_diff(s.bearing_rad, pred[:, 1]))) < 0.01
