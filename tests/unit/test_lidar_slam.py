"""Lidar SLAM on CARMEN logs through the CLI: a simulated drive written as a CARMEN log, and the real logs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam2d.cli.main import main
from slam2d.eval.relations import read_relations, relation_errors
from slam2d.geometry import se2
from slam2d.io.tum import read_tum
from slam2d.lab.registry import make_estimator
from slam2d.lab.runner import run
from slam2d.sim import simulate
from testkit import dataset_path


def write_carmen_from_sim(tmp: Path, steps: int = 300) -> tuple[Path, np.ndarray, np.ndarray]:
    """A simulated room drive written as a CARMEN log (odometry-integrated FLASER poses) + a relations file."""
    log = simulate("room", seed=2, steps=steps)
    assert log.true_poses is not None and log.scan_ranges_m is not None
    odo = [log.initial_pose]
    for u in log.odometry:
        odo.append(se2.compose(odo[-1], u))
    odo_arr = np.array(odo)
    stamps = 100.0 + log.stamps_s
    lines = ["# simulated", "PARAM laser yes nohost 0"]
    for k, t in enumerate(log.scan_step):
        # no-return beams carry the simulator's max range; real SICK logs write 81.83 for them
        r = " ".join(f"{v:.3f}" if v < log.scan_max_range_m else "81.83" for v in log.scan_ranges_m[k])
        x, y, th = odo_arr[t]
        lines.append(f"FLASER {len(log.scan_ranges_m[k])} {r} {x:.6f} {y:.6f} {th:.6f} {x:.6f} {y:.6f} {th:.6f} "
                     f"{stamps[t]:.6f} sim {stamps[t]:.6f}")
    p = tmp / "room.clf"
    p.write_text("\n".join(lines) + "\n")
    pairs = [(a, a + 5) for a in range(1, steps - 5, 7)] + [(a, a + 60) for a in range(1, steps - 60, 23)]
    rel = [se2.between(log.true_poses[a], log.true_poses[b]) for a, b in pairs]
    (tmp / "room.relations").write_text("".join(
        f"{stamps[a]:.6f} {stamps[b]:.6f} {d[0]:.6f} {d[1]:.6f} 0 0 0 {d[2]:.6f}\n" for (a, b), d in zip(pairs, rel,
                                                                                                      strict=True)))
    return p, log.true_poses[log.scan_step], odo_arr[log.scan_step]


def test_run_on_a_simulated_carmen_log_writes_trajectory_map_and_relation_errors(tmp_path: Path) -> None:
    path, truth, _ = write_carmen_from_sim(tmp_path)
    out, traj, js = tmp_path / "map.png", tmp_path / "t.txt", tmp_path / "r.json"
    assert main(["run", "--dataset", str(path), "--estimator", "lidar", "--map", str(out), "--trajectory", str(traj),
                 "--json", str(js)]) == 0
    rec = json.loads(js.read_text())
    assert out.exists() and out.stat().st_size > 1000
    # scan matching must beat the drifting odometry on the relations, and be accurate in absolute terms
    assert rec["relations_used"] == rec["relations"] > 50
    assert rec["rel_trans_mean_m"] < 0.5 * rec["odometry_rel_trans_mean_m"]
    assert rec["rel_trans_mean_m"] < 0.05 and rec["rel_rot_mean_deg"] < 1.0
    # the TUM file carries the log's own stamps (exact text) and the same trajectory, in the first scan's frame
    stamps, poses = read_tum(traj)
    lines = [ln for ln in path.read_text().splitlines() if ln.startswith("FLASER")]
    assert [float(ln.split()[0]) for ln in traj.read_text().splitlines()[1:]] == [float(ln.split()[-3])
                                                                                 for ln in lines]
    aligned = se2.compose(truth[0], se2.between(poses[0], poses))
    assert len(poses) == len(truth) and np.mean(np.hypot(*(aligned[:, :2] - truth[:, :2]).T)) < 0.15
    rel = read_relations(tmp_path / "room.relations")
    assert relation_errors(stamps, poses, rel).summary()["trans_mean_m"] == pytest.approx(rec["rel_trans_mean_m"])


def test_lidar_alias_bad_dataset_name_and_bad_override(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["lidar", "--dataset", "no-such-log"]) == 2
    assert "not a known laser log" in capsys.readouterr().err
    path, _, _ = write_carmen_from_sim(tmp_path, steps=40)
    assert main(["lidar", "--dataset", str(path), "--out", str(tmp_path / "m.png")]) == 0
    assert (tmp_path / "m.png").exists()
    assert main(["lidar", "--dataset", str(path), "--set", "keyframe_distance_m=-1"]) == 2
    assert "keyframe_distance_m" in capsys.readouterr().err
    assert main(["lidar", "--dataset", str(path), "--set", "no_such_field=1"]) == 2
    assert "no_such_field" in capsys.readouterr().err
    # a failed run leaves an existing map alone
    before = (tmp_path / "m.png").read_bytes()
    assert main(["lidar", "--dataset", str(path), "--out", str(tmp_path / "m.png"), "--relations",
                 str(tmp_path / "none.relations")]) == 2
    assert (tmp_path / "m.png").read_bytes() == before


#: ACES, first 3000 scans, default config (measured at 479a220 on an AMD EPYC VM; deterministic on a machine, while
#: another CPU's rounding moves it a little: the fixed trim before gave 0.0329 m / 0.339 deg on the earlier VM and
#: 0.0332 / 0.335 on this one). The logged odometry scores 0.0315 m on these 483 (short) relations: ACES odometry is
#: good locally, it fails on loops.
ACES_HEAD = 3000
PIN = {"relations": 483, "trans_mean_m": 0.0318, "rot_mean_deg": 0.360}


@pytest.mark.slow
def test_aces_head_relation_errors_are_pinned() -> None:
    """The default lidar estimator on the first 3000 ACES scans, scored on the relations that fall inside them."""
    from slam2d.cli.lidar import load_laser_log, original_stamps

    log = load_laser_log(str(dataset_path("radish-laser-logs", "aces.clf.bz2"))).head(ACES_HEAD - 1)
    rel = read_relations(dataset_path("radish-laser-logs", "aces.relations"))
    res = run(make_estimator("lidar"), log, rng=np.random.default_rng(0), progress=False)
    slam = relation_errors(original_stamps(log), res.trajectory, rel, on_missing="skip").summary()
    assert slam["relations"] == PIN["relations"]
    assert slam["trans_mean_m"] == pytest.approx(PIN["trans_mean_m"], abs=0.002)
    assert slam["rot_mean_deg"] == pytest.approx(PIN["rot_mean_deg"], abs=0.03)
    assert res.final.diagnostics.loops_accepted > 0
