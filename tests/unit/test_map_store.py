"""The SQLite map store: exact round trips, clear errors for files that are not (good) maps, atomic writes."""

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from slam2d.cli.main import main
from slam2d.estimator import SupportsSaveMap
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid, rasterize_segments
from slam2d.maps.store import (
    SCHEMA_VERSION,
    MapFormatError,
    MapSnapshot,
    MapStore,
    range_histogram,
    sim_world_id,
    snapshot_from_truth,
)
from slam2d.sim import simulate


def _snapshot(seed=0, world="sim:test", k=6, beams=90, rows=50, cols=70) -> MapSnapshot:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(k - 1, 3, 3))
    return MapSnapshot(
        world_id=world,
        keyframe_poses=rng.normal(size=(k, 3)),
        keyframe_scans=rng.uniform(0, 30, size=(k, beams)).astype(np.float32),
        descriptors=rng.random((k, 9)),
        scan_angles_rad=np.linspace(-np.pi, np.pi, beams, endpoint=False),
        scan_max_range_m=30.0,
        node_ids=np.arange(10, 10 + k, dtype=np.int64),
        node_poses=rng.normal(size=(k, 3)),
        edge_nodes=np.stack([np.arange(10, 9 + k), np.arange(11, 10 + k)], axis=-1),
        edge_poses=rng.normal(size=(k - 1, 3)),
        edge_information=a @ a.transpose(0, 2, 1),
        occupancy_logodds=rng.normal(size=(rows, cols)).astype(np.float32),
        occupancy_origin=np.array([-1.5, 2.25]),
        occupancy_resolution_m=0.05,
        metadata={"source": "test", "seed": seed},
        layers={"floor_markers": rng.normal(size=(7, 2)), "dynamic": rng.random((rows, cols)).astype(np.float32),
                "mask": rng.random(5) > 0.5, "ids": np.arange(4, dtype=np.int64)},
    )


def test_round_trip_is_exact(tmp_path):
    snap = _snapshot()
    path = MapStore.write(tmp_path / "a.db", snap)
    back = MapStore.read(path)
    assert back.equals(snap) and not back.equals(_snapshot(seed=1))
    for f in ("keyframe_poses", "keyframe_scans", "descriptors", "edge_information", "occupancy_logodds"):
        np.testing.assert_array_equal(getattr(back, f), getattr(snap, f))
        assert getattr(back, f).dtype == getattr(snap, f).dtype
    for name, arr in snap.layers.items():
        assert back.layers[name].dtype == arr.dtype
        np.testing.assert_array_equal(back.layers[name], arr)
    info = MapStore.info(path)
    assert info.counts["layers"] == 4
    assert info.schema_version == SCHEMA_VERSION and info.world_id == "sim:test"
    assert info.counts["keyframes"] == 6 and info.counts["edges"] == 5 and info.created_at
    # WAL mode, our application id, and no journal files left beside the map after a write or a read
    con = sqlite3.connect(path)
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    con.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.db"]


def test_nan_entries_compare_equal_and_real_differences_do_not(tmp_path):
    """Floor markers not yet placed are NaN: a map with them still equals itself and its round trip."""
    snap = _snapshot()
    snap.layers["floor_markers"][2] = np.nan
    back = MapStore.read(MapStore.write(tmp_path / "n.db", snap))
    assert snap.equals(snap) and back.equals(snap)
    other = _snapshot()
    other.layers["floor_markers"][2] = np.nan
    other.layers["floor_markers"][3, 0] += 1e-9
    assert not back.equals(other)


def test_map_from_a_simulated_run_round_trips(tmp_path):
    log = simulate("warehouse", seed=0, steps=150)
    snap = snapshot_from_truth(log)
    assert snap.world_id == sim_world_id(log.metadata) and len(snap.keyframe_poses) > 10
    scan_poses = log.true_poses[log.scan_step]
    idx = [np.flatnonzero((scan_poses == p).all(axis=1))[0] for p in snap.keyframe_poses]
    np.testing.assert_array_equal(snap.keyframe_scans, log.scan_ranges_m[idx].astype(np.float32))
    steps = np.hypot(*np.diff(snap.keyframe_poses[:, :2], axis=0).T)
    turns = np.abs(np.diff(snap.keyframe_poses[:, 2]))
    assert np.all((steps >= 1.0 - 1e-9) | (turns >= 0.5 - 1e-9))
    assert MapStore.read(MapStore.write(tmp_path / "w.db", snap)).equals(snap)
    # the grid holds the shelves: nearly all occupied cells lie on the true walls (the rest: forklifts)
    res = snap.occupancy_resolution_m
    rows, cols = snap.occupancy_logodds.shape
    x0, y0 = snap.occupancy_origin
    grid = OccupancyGrid((x0, y0, x0 + cols * res, y0 + rows * res), OccupancyConfig(resolution_m=res))
    assert grid.shape == (rows, cols)
    occ = snap.occupancy_logodds > 0.6
    near_wall = binary_dilation(rasterize_segments(grid, log.walls), np.ones((5, 5), dtype=bool))
    assert occ.sum() > 200 and (occ & near_wall).sum() > 0.9 * occ.sum()
    assert snap.layers == {}  # no floor markers in the small warehouse; the challenge one keeps its markers
    marked = simulate("warehouse-challenge", seed=0, steps=30, floor_markers=True)
    assert marked.true_markers is not None
    np.testing.assert_array_equal(snapshot_from_truth(marked).layers["floor_markers"], marked.true_markers)
    # flights of one warehouse share a world id; seeds and layouts do not
    base = {"scenario": "warehouse-challenge", "seed": 0, "config": {"name": "warehouse-challenge",
                                                                      "warehouse": {"aisles": 14, "flight": 0}}}
    fl2 = {**base, "config": {"name": "warehouse-challenge", "warehouse": {"aisles": 14, "flight": 2}}}
    other = {**base, "config": {"name": "warehouse-challenge", "warehouse": {"aisles": 12, "flight": 0}}}
    assert sim_world_id(base) == sim_world_id(fl2) != sim_world_id(other)
    assert sim_world_id(base) != sim_world_id({**base, "seed": 1})


def test_range_histogram_is_rotation_invariant():
    r = np.random.default_rng(0).uniform(0, 35, 360)
    h = range_histogram(r, 30.0)
    np.testing.assert_array_equal(h, range_histogram(np.roll(r, 77), 30.0))
    assert h.shape == (17,) and h.sum() == pytest.approx(1.0) and h[-1] == pytest.approx(np.mean(r >= 30))


def _bytes(p: Path) -> bytes:
    return p.read_bytes()


def test_files_that_are_not_good_maps_give_clear_errors_and_are_never_overwritten(tmp_path):
    good = MapStore.write(tmp_path / "good.db", _snapshot())
    data = _bytes(good)
    cases: dict[str, tuple[bytes, str]] = {}
    cases["text.db"] = (b"hello, not a map\n" * 10, "not a slam2d map .not an SQLite database")
    cases["trunc.db"] = (data[: len(data) // 2], "corrupt or truncated")
    cases["tiny.db"] = (data[:50], "truncated")
    other = tmp_path / "other.db"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE t (x)")
    con.commit()
    con.close()
    cases["other.db"] = (_bytes(other), "another application")
    newer = bytearray(data)
    newer[60:64] = (SCHEMA_VERSION + 1).to_bytes(4, "big")
    cases["newer.db"] = (bytes(newer), "newer than this slam2d")
    unfinished = bytearray(data)
    unfinished[60:64] = (0).to_bytes(4, "big")
    cases["unfinished.db"] = (bytes(unfinished), "incomplete")
    for name, (content, msg) in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(MapFormatError, match=f"{name}.*{msg}"):
            MapStore.read(p)
        with pytest.raises(MapFormatError, match=f"{name}.*refusing to overwrite"):
            MapStore.write(p, _snapshot())
        assert _bytes(p) == content, name  # untouched
    with pytest.raises(MapFormatError, match="missing.db: no such file"):
        MapStore.read(tmp_path / "missing.db")
    # a map of another world: reading into this world or overwriting it is refused
    with pytest.raises(MapFormatError, match="good.db: map of world 'sim:test', not of this world 'sim:other'"):
        MapStore.read(good, world_id="sim:other")
    with pytest.raises(MapFormatError, match="good.db: holds a map of world 'sim:test'"):
        MapStore.write(good, _snapshot(world="sim:other"))
    assert _bytes(good) == data
    MapStore.write(good, _snapshot(world="sim:other"), replace_other_world=True)
    assert MapStore.info(good).world_id == "sim:other"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temp files left


def test_bad_snapshots_and_unwritable_targets_are_refused(tmp_path):
    fields = {f: getattr(_snapshot(), f) for f in MapSnapshot.__dataclass_fields__}
    with pytest.raises(ValueError, match="metadata must be JSON"):
        MapSnapshot(**{**fields, "metadata": {"x": object()}})
    with pytest.raises(ValueError, match="layers\\['bad'\\]"):
        MapSnapshot(**{**fields, "layers": {"bad": np.array(["a"])}})
    with pytest.raises(ValueError, match="keyframe_scans"):
        MapSnapshot(**{**fields, "keyframe_scans": fields["keyframe_scans"].astype(np.float64)})
    with pytest.raises(MapFormatError, match="nowhere/m.db: cannot write a map there"):
        MapStore.write(tmp_path / "nowhere" / "m.db", _snapshot())


def _tampered(path, sql):
    """A saved map with one SQL statement applied behind the store's back."""
    p = MapStore.write(path, _snapshot())
    con = sqlite3.connect(p)
    con.execute(sql)
    con.commit()
    con.close()
    return p


def test_rows_that_disagree_with_the_recorded_counts_are_caught(tmp_path):
    p = _tampered(tmp_path / "m.db", "DELETE FROM keyframes WHERE id = 3")
    with pytest.raises(MapFormatError, match="m.db: corrupt slam2d map .rows"):
        MapStore.read(p)


def test_a_metadata_value_that_is_not_json_names_the_file(tmp_path):
    p = _tampered(tmp_path / "m.db", "UPDATE meta SET value = '{bad' WHERE key = 'counts'")
    with pytest.raises(MapFormatError, match=r"m\.db: corrupt slam2d map \(a metadata value is not JSON: "):
        MapStore.info(p)


def test_saving_over_the_loaded_map_is_atomic(tmp_path):
    p = MapStore.write(tmp_path / "same.db", _snapshot(seed=0))
    loaded = MapStore.read(p)
    changed = MapSnapshot(**{**{f: getattr(loaded, f) for f in loaded.__dataclass_fields__},
                             "keyframe_poses": loaded.keyframe_poses + 1.0})
    MapStore.write(p, changed)
    assert MapStore.read(p).equals(changed)


_KILLED_WRITER = textwrap.dedent("""
    import sys, time, zlib
    import numpy as np
    sys.path.insert(0, {src!r})
    import tests_helper_snapshot as h
    from slam2d.maps import store
    real = zlib.compress
    calls = [0]
    def slow(data, level=-1):
        calls[0] += 1
        if calls[0] == 200:
            print("mid-write", flush=True)
            time.sleep(60)
        return real(data, level)
    store.zlib.compress = slow
    store.MapStore.write({path!r}, h.big())
""")


def test_a_writer_killed_mid_save_leaves_the_previous_map_intact(tmp_path):
    target = tmp_path / "map.db"
    first = _snapshot(seed=0)
    MapStore.write(target, first)
    before = _bytes(target)
    (tmp_path / "tests_helper_snapshot.py").write_text(textwrap.dedent("""
        import numpy as np
        from slam2d.maps.store import MapSnapshot
        def big():
            k = 500
            rng = np.random.default_rng(5)
            return MapSnapshot(world_id="sim:test", keyframe_poses=rng.normal(size=(k, 3)),
                keyframe_scans=rng.uniform(0, 30, (k, 360)).astype(np.float32), descriptors=rng.random((k, 9)),
                scan_angles_rad=np.linspace(-3, 3, 360), scan_max_range_m=30.0, node_ids=np.arange(k),
                node_poses=rng.normal(size=(k, 3)), edge_nodes=np.zeros((0, 2), np.int64),
                edge_poses=np.zeros((0, 3)), edge_information=np.zeros((0, 3, 3)),
                occupancy_logodds=np.zeros((10, 10), np.float32), occupancy_origin=np.zeros(2),
                occupancy_resolution_m=0.1)
    """))
    src = str(Path(__file__).resolve().parents[2] / "src")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), src])}
    code = _KILLED_WRITER.format(src=src, path=str(target))
    with subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, env=env, text=True) as proc:
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == "mid-write"
            temps = [p for p in tmp_path.iterdir() if p.name.startswith(".map.db.tmp")]
            assert temps and temps[0].stat().st_size > 0  # the new map was being written beside the old one
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert _bytes(target) == before
    assert MapStore.read(target).equals(first)
    # the next save replaces the map normally (the dead writer's temp file is its own name and harmless)
    MapStore.write(target, _snapshot(seed=3))
    assert MapStore.read(target).equals(_snapshot(seed=3))


def test_an_estimator_can_offer_save_map_through_the_store(tmp_path):
    class Saver:
        def __init__(self, snap):
            self.snap = snap

        def save_map(self, path: str) -> None:
            MapStore.write(path, self.snap)

    est = Saver(_snapshot())
    assert isinstance(est, SupportsSaveMap)
    est.save_map(str(tmp_path / "e.db"))
    assert MapStore.read(tmp_path / "e.db").equals(est.snap)


def test_cli_save_info_load(tmp_path, capsys):
    out = tmp_path / "A.db"
    assert main(["map", "save", "--scenario", "warehouse", "--seed", "0", "--out", str(out), "--set", "steps=60"]) == 0
    assert "built from true poses" in capsys.readouterr().out
    assert main(["map", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "schema_version  1" in text and "sim:warehouse:seed=0" in text and "keyframes" in text
    assert main(["map", "load", str(out), "--scenario", "warehouse", "--seed", "0"]) == 0
    assert "valid slam2d map" in capsys.readouterr().out
    assert main(["map", "load", str(out), "--scenario", "warehouse", "--seed", "1"]) == 2
    assert "not of this world" in capsys.readouterr().err
    junk = tmp_path / "notes.txt"
    junk.write_text("my notes")
    assert main(["map", "save", "--scenario", "warehouse", "--out", str(junk), "--set", "steps=20"]) == 2
    assert "notes.txt" in capsys.readouterr().err and junk.read_text() == "my notes"
