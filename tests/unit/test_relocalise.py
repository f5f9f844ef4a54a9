"""Global relocalisation against a saved map, and ``slam2d run --map-in/--map-out``.

A centrally symmetric room (every scan at a pose is also the scan at its half-turn image) must stay undecided
without markers and decide the right way with two ID'd markers; an aisle warehouse with floor markers must
relocalise from a map of an earlier flight; bad map files give one-line CLI errors and stay unchanged.
"""

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from slam2d.cli.main import main
from slam2d.config import with_overrides
from slam2d.frontend.relocalise import RelocaliseConfig, Relocaliser
from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle
from slam2d.log import MarkerReadings, Observations, Scan, Step
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid, rasterize_segments
from slam2d.maps.store import MapSnapshot, MapStore, range_histogram, snapshot_from_truth
from slam2d.models.floor_markers import marker_in_robot
from slam2d.models.lidar import cast_rays
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import simulate
from slam2d.sim.world import box_walls

BEAMS = 360
ANGLES = np.linspace(-np.pi * (BEAMS - 1) / BEAMS, np.pi * (BEAMS - 1) / BEAMS, BEAMS)
CENTRE = np.array([10.0, 5.0])
# a 20 x 10 m room with pillars placed symmetrically under a half turn about (10, 5)
WALLS = np.vstack([box_walls(0, 0, 20, 10), box_walls(5, 3, 6, 4), box_walls(14, 6, 15, 7),
                   box_walls(3, 6, 4, 7.5), box_walls(16, 2.5, 17, 4)])
MARKERS = np.array([[5.5, 2.0], [14.5, 8.0]])  # symmetric places, different ids


def _half_turn(p):
    return np.array([2 * CENTRE[0] - p[0], 2 * CENTRE[1] - p[1], wrap_angle(p[2] + np.pi)])


def room_map(with_markers: bool, walls: np.ndarray = WALLS, keyframes_to_x: float = 19.0) -> MapSnapshot:
    """A saved map of a 20 x 10 m room drawn from ``walls``: keyframes on a 1 m grid up to x = ``keyframes_to_x``,
    the floor markers when asked."""
    grid = OccupancyGrid((-1.0, -1.0, 21.0, 11.0), OccupancyConfig(resolution_m=0.05))
    logodds = np.where(rasterize_segments(grid, walls), 3.5, -2.0).astype(np.float32)
    gx, gy = np.meshgrid(np.arange(1.5, keyframes_to_x, 1.0), np.arange(1.5, 9, 1.0))
    poses = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=-1)
    scans = np.stack([cast_rays(p, ANGLES, walls, 30.0) for p in poses]).astype(np.float32)
    n = len(poses)
    return MapSnapshot(
        world_id="test:room", keyframe_poses=poses, keyframe_scans=scans, descriptors=range_histogram(scans, 30.0),
        scan_angles_rad=ANGLES, scan_max_range_m=30.0, node_ids=np.arange(n, dtype=np.int64), node_poses=poses,
        edge_nodes=np.zeros((0, 2), np.int64), edge_poses=np.zeros((0, 3)), edge_information=np.zeros((0, 3, 3)),
        occupancy_logodds=logodds, occupancy_origin=grid.origin.copy(), occupancy_resolution_m=0.05,
        layers={"floor_markers": MARKERS.copy()} if with_markers else {})


def _drive(start, steps=70, speed=1.0, dt=0.1, turn=0.0, seed=0):
    """Steps of a drive from ``start`` (noise-free odometry, 2 cm range noise, markers within 1 m)."""
    rng = np.random.default_rng(seed)
    poses = [np.asarray(start, dtype=np.float64)]
    out = []
    for i in range(1, steps + 1):
        poses.append(se2.compose(poses[-1], np.array([speed * dt, 0.0, turn * dt])))
        r = cast_rays(poses[-1], ANGLES, WALLS, 30.0)
        r = np.where(r < 30.0, r + rng.normal(0, 0.02, r.shape), 30.0)
        z = marker_in_robot(poses[-1], MARKERS)
        seen = np.hypot(z[:, 0], z[:, 1]) <= 1.0
        out.append(Step(i, i * dt, dt, se2.between(poses[-2], poses[-1]),
                        Observations(np.zeros(0), np.zeros(0), np.zeros(0, np.int64)),
                        scan=Scan(r, ANGLES, 30.0),
                        markers=MarkerReadings(z[seen], np.flatnonzero(seen).astype(np.int64))))
    return out, np.array(poses)


def test_a_symmetric_room_without_markers_stays_undecided_with_both_answers_kept():
    snap = room_map(with_markers=False)
    steps, truth = _drive([3.0, 2.0, 0.0], steps=50)
    rel = Relocaliser(snap, rng=np.random.default_rng(0))
    for st in steps:
        status = rel.step(st)
        assert not status.decided, f"accepted a pose in a symmetric room at step {st.index}"
    assert status.evidence >= RelocaliseConfig().min_evidence  # it had the evidence, and still could not decide
    mirror = _half_turn(truth[-1])
    for target in (truth[-1], mirror):  # the truth and its half-turn image are both among the hypotheses
        d = se2.between(target[None], rel.hyp)
        assert np.any((np.hypot(d[:, 0], d[:, 1]) < 0.3) & (np.abs(d[:, 2]) < 0.1))
    assert status.margin < RelocaliseConfig().accept_margin


def test_two_id_markers_break_the_symmetry_and_the_right_pose_is_accepted():
    snap = room_map(with_markers=True)
    steps, truth = _drive([3.0, 2.0, 0.0])
    rel = Relocaliser(snap, rng=np.random.default_rng(0))
    decided = None
    for st in steps:
        status = rel.step(st)
        if status.decided:
            decided = (st.index, status.pose)
            break
    assert decided is not None, "never decided although marker 0 was read"
    k, pose = decided
    e = se2.local(truth[k], pose)
    assert np.hypot(e[0], e[1]) < 0.1 and abs(e[2]) < 0.02
    assert rel.history[0]["hypotheses"] >= 2  # it started with several answers


SMALL = {"warehouse.width_m": "30", "warehouse.depth_m": "22", "warehouse.aisles": "2",
         "warehouse.cross_aisles": "1", "warehouse.pallets": "18", "moving_objects": "1", "dt_s": "0.1",
         "warehouse.floor_markers": "true"}


def _small(flight: int, steps: int) -> ScenarioConfig:
    return with_overrides(ScenarioConfig(name="warehouse-challenge"),
                          {**SMALL, "warehouse.flight": str(flight), "steps": str(steps)})


@pytest.fixture(scope="module")
def aisle_map():
    return snapshot_from_truth(simulate(_small(0, 700), 0), keyframe_every_m=1.0)


def test_aisle_world_with_markers_relocalises_from_an_earlier_flights_map(aisle_map):
    log = simulate(_small(1, 560), 0)  # pallets moved since the map was made
    steps = list(log)
    cfg = RelocaliseConfig(descriptor_candidates=80, max_hypotheses=150)
    for start in (120, 460):
        rel = Relocaliser(aisle_map, cfg, rng=np.random.default_rng(start))
        accepted = None
        for st in steps[start:start + 100]:  # 10 s of motion
            status = rel.step(st)
            if status.decided:
                accepted = (st.index, status.pose)
                break
        assert accepted is not None, f"start {start}: undecided after 10 s"
        e = se2.local(log.true_poses[accepted[0]], accepted[1])
        assert np.hypot(e[0], e[1]) < 0.3 and abs(e[2]) < 0.05, f"start {start}: wrong pose accepted ({e})"


def _cli(tmp_path: Path, *extra: str) -> list[str]:
    sets = [a for k, v in SMALL.items() for a in ("--set", f"{k}={v}")]
    return ["run", "--scenario", "warehouse-challenge", "--estimator", "lidar", *sets, *extra]


def test_map_in_bad_files_are_one_line_errors_and_nothing_is_touched(tmp_path, capsys, aisle_map):
    good = MapStore.write(tmp_path / "good.db", aisle_map)
    data = good.read_bytes()
    newer = tmp_path / "newer.db"
    newer.write_bytes(data)
    con = sqlite3.connect(newer)
    con.execute("PRAGMA user_version=99")
    con.commit()
    con.close()
    other = MapStore.write(tmp_path / "other.db", snapshot_from_truth(simulate(_small(0, 40), 5)))
    cases = {"text.db": b"not a map at all\n" * 20, "trunc.db": data[: len(data) // 3],
             "newer.db": newer.read_bytes(), "other.db": other.read_bytes()}
    for name, content in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        out = tmp_path / "out.db"
        out.write_bytes(b"keep me")
        code = main(_cli(tmp_path, "--set", "steps=5", "--map-in", str(p), "--map-out", str(p)))
        err = capsys.readouterr().err.strip()
        assert code == 2, name
        assert name in err and "\n" not in err and "Traceback" not in err, err
        assert p.read_bytes() == content, name
    # a --map-out that is not a slam2d map is refused before the run, and left as it was
    junk = tmp_path / "notes.db"
    junk.write_bytes(b"my notes")
    assert main(_cli(tmp_path, "--set", "steps=5", "--map-in", str(good), "--map-out", str(junk))) == 2
    assert "notes.db" in capsys.readouterr().err and junk.read_bytes() == b"my notes"
    assert main(_cli(tmp_path, "--set", "steps=5", "--estimator", "graph", "--map-in", str(good))) == 2
    capsys.readouterr()


def test_map_out_equal_to_map_in_is_replaced_atomically_and_only_after_a_decision(tmp_path, capsys, aisle_map):
    path = MapStore.write(tmp_path / "A.db", aisle_map)
    before = path.read_bytes()
    # too short to decide: the map is not written, the file is unchanged
    assert main(_cli(tmp_path, "--set", "steps=4", "--set", "warehouse.flight=1", "--map-in", str(path),
                     "--map-out", str(path))) == 2
    assert "undecided" in capsys.readouterr().err and path.read_bytes() == before
    js = tmp_path / "r.json"
    assert main(_cli(tmp_path, "--set", "steps=60", "--set", "warehouse.flight=1", "--map-in", str(path),
                     "--map-out", str(path), "--json", str(js))) == 0
    assert "relocalisation: accepted" in capsys.readouterr().out
    import json

    rel = json.loads(js.read_text())["relocalisation"]
    assert rel["relocalised"] and rel["error_m"] < 0.3 and len(rel["history"]) >= 1
    info = MapStore.info(path)
    assert info.created_by == "slam2d lidar session" and info.world_id == aisle_map.world_id
    assert info.counts["keyframes"] > len(aisle_map.keyframe_poses)  # the old keyframes and the new ones
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp file left


def test_map_save_from_the_lidar_estimator(tmp_path, capsys):
    out = tmp_path / "L.db"
    assert main(["map", "save", "--source", "lidar", "--scenario", "warehouse", "--set", "steps=60", "--out",
                 str(out)]) == 0
    assert "built by the lidar estimator" in capsys.readouterr().out
    snap = MapStore.read(out)
    assert snap.metadata["source"] == "estimator" and len(snap.keyframe_poses) >= 2
    assert len(snap.edge_nodes) >= len(snap.keyframe_poses) - 1  # the keyframe chain (and any loops)
