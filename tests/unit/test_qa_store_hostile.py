"""The SQLite map store against concurrent writers in one process and damaged or crafted files: every write that
returns has its map in place, and a bad file is a MapFormatError naming it (never a bare KeyError, never an
unbounded decompression)."""

from __future__ import annotations

import sqlite3
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest

from slam2d.maps.store import MapFormatError, MapSnapshot, MapStore


def _snap(seed: int = 0, k: int = 4) -> MapSnapshot:
    rng = np.random.default_rng(seed)
    return MapSnapshot(
        world_id="sim:qa", keyframe_poses=rng.normal(size=(k, 3)),
        keyframe_scans=rng.uniform(0, 30, (k, 36)).astype(np.float32), descriptors=rng.random((k, 5)),
        scan_angles_rad=np.linspace(-np.pi, np.pi, 36, endpoint=False), scan_max_range_m=30.0,
        node_ids=np.arange(k, dtype=np.int64), node_poses=rng.normal(size=(k, 3)),
        edge_nodes=np.stack([np.arange(k - 1), np.arange(1, k)], axis=-1), edge_poses=rng.normal(size=(k - 1, 3)),
        edge_information=np.repeat(np.eye(3)[None], k - 1, axis=0), occupancy_logodds=np.zeros((8, 9), np.float32),
        occupancy_origin=np.zeros(2), occupancy_resolution_m=0.1, metadata={"seed": seed},
        layers={"ids": np.arange(3, dtype=np.int64)})


def test_two_writers_of_one_path_in_one_process_both_land(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Thread B saving the same path while thread A is between building its file and renaming it: both used the
    temporary name ``.NAME.tmp-PID``, so B unlinked A's finished file (or A renamed B's half-written one into place)
    and A failed with 'could not write the map'. Replayed deterministically: B's whole write runs inside A's."""
    path = tmp_path / "m.db"
    a, b = _snap(1), _snap(2)
    real = MapStore._write_file
    nested: list[Path] = []
    started = []

    def write_file(tmp: Path, s: MapSnapshot, created_by: str) -> None:
        real(tmp, s, created_by)
        if not started:  # A has built its temporary file; B saves the same path now
            started.append(True)
            nested.append(MapStore.write(path, b))

    monkeypatch.setattr(MapStore, "_write_file", staticmethod(write_file))
    assert MapStore.write(path, a) == path  # raised MapFormatError (FileNotFoundError on the rename)
    assert nested == [path]
    assert MapStore.read(path).equals(a)  # A renamed last: its map is the one in place
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.db"]  # no temporary file left behind


def _tamper(path: Path, sql: str, *params: object, keep_digest: bool = False) -> Path:
    """A map changed by ``sql``; without ``keep_digest`` its digest goes too (as in a file written before digests),
    so that the checks behind the digest are the ones tested."""
    MapStore.write(path, _snap())
    _sql(path, sql, *params)
    if not keep_digest:
        _sql(path, "DELETE FROM meta WHERE key = 'digest'")
    return path


def _sql(path: Path, sql: str, *params: object) -> None:
    """One statement applied behind the store's back."""
    con = sqlite3.connect(path)
    con.execute(sql, params)
    con.commit()
    con.close()


@pytest.mark.parametrize("sql", ["UPDATE nodes SET x = x + 1e-9 WHERE id = 2",
                                 "UPDATE edges SET dtheta = -dtheta WHERE id = 0",
                                 "UPDATE keyframes SET y = 0.0 WHERE id = 1",
                                 "UPDATE meta SET value = '30.5' WHERE key = 'scan_max_range_m'",
                                 "UPDATE arrays SET shape = '[9, 8]' WHERE name = 'occupancy_logodds'"])
def test_a_changed_number_is_found_by_the_digest(tmp_path: Path, sql: str) -> None:
    """A changed REAL in a row passed SQLite's quick_check, the row counts and zlib's own checksum: the map was read
    with the wrong number. The digest recorded at write time finds it."""
    p = _tamper(tmp_path / "flip.db", sql, keep_digest=True)
    with pytest.raises(MapFormatError, match="flip.db: corrupt slam2d map .*digest"):
        MapStore.read(p)
    # the same file without its digest (as written before digests) is read, changed number and all
    _sql(p, "DELETE FROM meta WHERE key = 'digest'")
    assert isinstance(MapStore.read(p), MapSnapshot)


def test_an_untouched_map_matches_its_digest_after_a_rewrite(tmp_path: Path) -> None:
    p = tmp_path / "m.db"
    MapStore.write(p, _snap(3))
    snap = MapStore.read(p)
    MapStore.write(p, snap)  # read back and saved again: the same rows, the same digest check
    assert MapStore.read(p).equals(_snap(3))


@pytest.mark.parametrize("sql", ["DELETE FROM meta WHERE key = 'world_id'",
                                 "DELETE FROM meta WHERE key = 'schema_version'",
                                 "UPDATE meta SET value = '[1, 2]' WHERE key = 'counts'"])
def test_missing_or_wrong_metadata_rows_name_the_file(tmp_path: Path, sql: str) -> None:
    """They raised a bare KeyError / AttributeError from MapStore.info (and from `slam2d map info`)."""
    p = _tamper(tmp_path / "meta.db", sql)
    with pytest.raises(MapFormatError, match="meta.db: corrupt slam2d map"):
        MapStore.info(p)


def test_a_blob_that_expands_beyond_its_shape_is_refused_without_expanding(tmp_path: Path) -> None:
    """A 3-element layer whose blob inflates to 64 MB: the whole 64 MB were decompressed before the shape was
    checked (a crafted file could ask for any amount of memory). Now decompression stops past the recorded size."""
    bomb = zlib.compress(bytes(64 << 20), 9)
    p = _tamper(tmp_path / "bomb.db", "UPDATE arrays SET data = ? WHERE name = 'layer:ids'", bomb)
    tracemalloc.start()
    try:
        with pytest.raises(MapFormatError, match="bomb.db: corrupt slam2d map"):
            MapStore.read(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, peak
