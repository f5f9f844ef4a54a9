"""A saved map in one SQLite file (Python's embedded ``sqlite3``, no server).

What a map holds (:class:`MapSnapshot`): keyframes (pose, lidar scan stored as zlib-compressed float32 ranges, place
descriptor), the pose graph (nodes, and edges with their relative pose and 3x3 information), the static occupancy
layer (zlib-compressed float32 log-odds, origin, resolution) and metadata (world id, schema version, creation time,
creator, free-form JSON). ``MapStore.write(path, snapshot)`` / ``MapStore.read(path) -> MapSnapshot`` are the whole
API; an estimator's ``save_map(path)`` (``slam2d.estimator.SupportsSaveMap``) builds a snapshot and writes it.

Safety:

* A write builds the complete map in a temporary file beside the target inside one transaction, checkpoints it
  (WAL mode, so the file needs no journal afterwards) and only then renames it over the target. A process killed at
  any point leaves the previous map untouched, and saving to the path a map was loaded from is atomic.
* The file is tagged with an SQLite ``application_id`` and a schema version (``user_version``). Reading a file
  that is not a SQLite database, not ours, truncated or corrupt (``PRAGMA quick_check`` plus row counts recorded
  at write time), written by a newer schema, or built for another world raises :class:`MapFormatError` naming the
  file. Reads open the file read-only. A SHA-256 digest of every row, recorded at write time, finds a changed number
  that SQLite's own checks pass (a bit flip on disk, an edit by hand); files written before the digest have none
  and are read without it.
* A write refuses to replace an existing file that is not a slam2d map (or is from a newer schema), and a map of
  another world unless ``replace_other_world=True``.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import os
import secrets
import sqlite3
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry import se2
from slam2d.log import Log
from slam2d.maps.layers import LayersConfig, MapLayers
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid
from slam2d.models.lidar import scan_to_points
from slam2d.sim.scenarios import SCENARIOS

Array = NDArray[np.float64]

SCHEMA_VERSION = 1
#: SQLite application_id of slam2d map files: "S2DM" as a big-endian 32-bit integer.
APPLICATION_ID = int.from_bytes(b"S2DM", "big")

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE keyframes (id INTEGER PRIMARY KEY, x REAL NOT NULL, y REAL NOT NULL, theta REAL NOT NULL,
                        scan BLOB NOT NULL, descriptor BLOB NOT NULL);
CREATE TABLE nodes (id INTEGER PRIMARY KEY, x REAL NOT NULL, y REAL NOT NULL, theta REAL NOT NULL);
CREATE TABLE edges (id INTEGER PRIMARY KEY, a INTEGER NOT NULL REFERENCES nodes(id),
                    b INTEGER NOT NULL REFERENCES nodes(id), dx REAL NOT NULL, dy REAL NOT NULL,
                    dtheta REAL NOT NULL, information BLOB NOT NULL);
CREATE TABLE arrays (name TEXT PRIMARY KEY, dtype TEXT NOT NULL, shape TEXT NOT NULL, data BLOB NOT NULL);
"""


class MapFormatError(ValueError):
    """A map file is missing, not ours, corrupt, truncated, too new or of another world; the message names it."""


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """Everything a saved map holds. Shapes: K keyframes, B beams, D descriptor length, N nodes, E edges,
    occupancy (rows, cols) with row index y and column index x (as ``slam2d.maps.occupancy.OccupancyGrid``).

    keyframe_poses (K,3) float64; keyframe_scans (K,B) float32 ranges; descriptors (K,D) float64;
    scan_angles_rad (B,); node_ids (N,) int64; node_poses (N,3); edge_nodes (E,2) int64 node ids;
    edge_poses (E,3) relative pose of b in a's frame; edge_information (E,3,3); occupancy_logodds (rows, cols)
    float32; occupancy_origin (2,) [x0, y0] of cell (0, 0)'s corner; occupancy_resolution_m.
    """

    world_id: str
    """which world this map describes; a map is only loaded into the same world."""
    keyframe_poses: Array
    keyframe_scans: NDArray[np.float32]
    descriptors: Array
    scan_angles_rad: Array
    scan_max_range_m: float
    node_ids: NDArray[np.int64]
    node_poses: Array
    edge_nodes: NDArray[np.int64]
    edge_poses: Array
    edge_information: Array
    occupancy_logodds: NDArray[np.float32]
    occupancy_origin: Array
    occupancy_resolution_m: float
    metadata: Mapping[str, Any] = field(default_factory=dict)
    """free-form JSON (what made the map, seeds, configs); ``created_at``/``created_by`` are filled on write."""
    layers: Mapping[str, NDArray[Any]] = field(default_factory=dict)
    """optional extra named arrays (float64, float32, int64 or bool), e.g. ``floor_markers`` (M,2) or a dynamic
    layer: stored and returned exactly, without a schema change."""

    def __post_init__(self) -> None:
        k = self.keyframe_poses.shape[0]
        checks = [
            ("keyframe_poses", self.keyframe_poses.shape == (k, 3)),
            ("keyframe_scans", self.keyframe_scans.ndim == 2 and self.keyframe_scans.shape[0] == k
             and self.keyframe_scans.dtype == np.float32),
            ("scan_angles_rad", self.scan_angles_rad.shape == (self.keyframe_scans.shape[1],)),
            ("descriptors", self.descriptors.ndim == 2 and self.descriptors.shape[0] == k),
            ("node_poses", self.node_poses.shape == (len(self.node_ids), 3) and self.node_ids.ndim == 1),
            ("edge_nodes", self.edge_nodes.ndim == 2 and self.edge_nodes.shape[1] == 2),
            ("edge_poses", self.edge_poses.shape == (len(self.edge_nodes), 3)),
            ("edge_information", self.edge_information.shape == (len(self.edge_nodes), 3, 3)),
            ("occupancy_logodds", self.occupancy_logodds.ndim == 2 and self.occupancy_logodds.dtype == np.float32),
            ("occupancy_origin", self.occupancy_origin.shape == (2,)),
        ]
        bad = [n for n, ok in checks if not ok]
        if bad:
            raise ValueError(f"MapSnapshot: inconsistent shapes or dtypes in {bad} (see the class docstring)")
        if len(np.unique(self.node_ids)) != len(self.node_ids):
            raise ValueError("MapSnapshot.node_ids must be unique")
        if len(self.edge_nodes) and not np.all(np.isin(self.edge_nodes, self.node_ids)):
            raise ValueError("MapSnapshot.edge_nodes must refer to node_ids")
        if not self.occupancy_resolution_m > 0:
            raise ValueError(f"MapSnapshot.occupancy_resolution_m must be > 0 (got {self.occupancy_resolution_m})")
        if not self.world_id:
            raise ValueError("MapSnapshot.world_id must not be empty")
        try:
            json.dumps(dict(self.metadata))
        except (TypeError, ValueError) as e:
            raise ValueError(f"MapSnapshot.metadata must be JSON-serialisable ({e})") from None
        for name, a in self.layers.items():
            if not (isinstance(name, str) and name) or np.asarray(a).dtype not in _LAYER_DTYPES:
                raise ValueError(f"MapSnapshot.layers[{name!r}] must be a named array of dtype float64, float32, "
                                 f"int64 or bool")

    def counts(self) -> dict[str, int]:
        return {"keyframes": int(self.keyframe_poses.shape[0]), "nodes": len(self.node_ids),
                "edges": len(self.edge_nodes), "beams": int(self.keyframe_scans.shape[1]),
                "descriptor_dim": int(self.descriptors.shape[1]),
                "occupancy_cells": int(self.occupancy_logodds.size), "layers": len(self.layers)}

    def equals(self, other: MapSnapshot) -> bool:
        """Exact equality of every array, scalar and the metadata."""
        for f in ("keyframe_poses", "keyframe_scans", "descriptors", "scan_angles_rad", "node_ids", "node_poses",
                  "edge_nodes", "edge_poses", "edge_information", "occupancy_logodds", "occupancy_origin"):
            if not _same_array(getattr(self, f), getattr(other, f)):
                return False
        if sorted(self.layers) != sorted(other.layers):
            return False
        if not all(_same_array(a, other.layers[n]) for n, a in self.layers.items()):
            return False
        return (self.world_id == other.world_id and self.scan_max_range_m == other.scan_max_range_m
                and self.occupancy_resolution_m == other.occupancy_resolution_m
                and json.dumps(dict(self.metadata), sort_keys=True) == json.dumps(dict(other.metadata),
                                                                                  sort_keys=True))


def _same_array(a: np.ndarray, b: np.ndarray) -> bool:
    """Same dtype, shape and values; NaN equals NaN (floor markers not yet placed are stored as NaN)."""
    nan_ok = a.dtype.kind in "fc"
    return a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=nan_ok))


@dataclass(frozen=True)
class MapInfo:
    """The cheap summary of a map file: metadata and row counts (no arrays decoded)."""

    path: Path
    schema_version: int
    world_id: str
    created_at: str
    created_by: str
    counts: dict[str, int]
    metadata: dict[str, Any]


def _fsync_dir(directory: Path) -> None:
    """Make a rename durable (POSIX); a no-op where directories cannot be opened."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_LAYER_DTYPES = (np.dtype(np.float64), np.dtype(np.float32), np.dtype(np.int64), np.dtype(np.bool_))


def _blob(a: NDArray[Any], dtype: type) -> bytes:
    return zlib.compress(np.ascontiguousarray(a, dtype=dtype).tobytes(), 6)


def _unblob(b: bytes, dtype: type, shape: tuple[int, ...]) -> NDArray[Any]:
    """The array of a blob, decompressed no further than its recorded shape needs (a damaged or crafted blob must
    not expand without bound)."""
    n = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    raw = zlib.decompressobj().decompress(b, n + 1) if n >= 0 else b""
    if len(raw) != n:
        raise ValueError(f"a blob holds {'more than ' if len(raw) > n else ''}{len(raw)} bytes, not the {n} of "
                         f"shape {shape}")
    return np.frombuffer(raw, dtype=dtype).reshape(shape).copy()


#: what the digest covers, in this order: every table, the digest's own row left out
_DIGESTED = ("SELECT key, value FROM meta WHERE key != 'digest' ORDER BY key", "SELECT * FROM keyframes ORDER BY id",
             "SELECT * FROM nodes ORDER BY id", "SELECT * FROM edges ORDER BY id",
             "SELECT name, dtype, shape, data FROM arrays ORDER BY name")


def _content_digest(con: sqlite3.Connection) -> str:
    """SHA-256 of the map's rows as SQLite returns them, each value tagged with its type and length (so that no two
    different contents give the same byte stream)."""
    h = hashlib.sha256()
    for query in _DIGESTED:
        h.update(query.encode())
        for row in con.execute(query):
            for v in row:
                if isinstance(v, float):
                    h.update(b"f" + struct.pack("<d", v))
                elif isinstance(v, int):
                    h.update(b"i%d;" % v)
                else:
                    raw = v if isinstance(v, bytes) else str(v).encode()
                    h.update(b"b" if isinstance(v, bytes) else b"s")
                    h.update(b"%d:" % len(raw))
                    h.update(raw)
    return h.hexdigest()


class MapStore:
    """Reads and writes :class:`MapSnapshot` files (see the module docstring for the guarantees)."""

    @staticmethod
    def write(path: str | Path, snapshot: MapSnapshot, *, created_by: str = "slam2d",
              replace_other_world: bool = False) -> Path:
        """Write ``snapshot`` to ``path`` atomically; returns the path. The previous file is replaced only once
        the new one is complete."""
        path = Path(path)
        if not path.parent.is_dir():
            why = "is not a directory" if path.parent.exists() else "does not exist"
            raise MapFormatError(f"{path}: cannot write a map there ({path.parent} {why})")
        if path.exists():
            MapStore.check_replaceable(path, snapshot.world_id, replace_other_world)
        # unique per write, not only per process: two threads saving the same path must not share (and unlink,
        # or rename half-written) one temporary file
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
        try:
            MapStore._write_file(tmp, snapshot, created_by)
            os.replace(tmp, path)
            _fsync_dir(path.parent)
        except (sqlite3.Error, OSError) as e:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            raise MapFormatError(f"{path}: could not write the map ({type(e).__name__}: {e}); the previous file, "
                                 "if any, is unchanged") from None
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            raise
        return path

    @staticmethod
    def check_replaceable(path: Path, world_id: str, replace_other_world: bool = False) -> None:
        """Refuse (:class:`MapFormatError` naming ``path``) to replace an existing file that is not a readable
        slam2d map, or that holds another world's map unless ``replace_other_world``; callers check before a long
        run, :meth:`write` checks again when it writes."""
        try:
            info = MapStore.info(path)
        except MapFormatError as e:
            raise MapFormatError(f"{e}; refusing to overwrite it") from None
        if info.world_id != world_id and not replace_other_world:
            raise MapFormatError(f"{path}: holds a map of world {info.world_id!r}, not {world_id!r}; refusing to "
                                 "overwrite it (choose another file or allow replacing another world's map)")

    @staticmethod
    def _write_file(tmp: Path, s: MapSnapshot, created_by: str) -> None:
        con = sqlite3.connect(tmp, isolation_level=None)
        try:
            con.execute("PRAGMA journal_mode=WAL")
            con.execute(f"PRAGMA application_id={APPLICATION_ID}")
            con.execute("BEGIN")
            for statement in _SCHEMA.split(";"):
                if statement.strip():
                    con.execute(statement)
            meta = {
                "format": "slam2d-map",
                "schema_version": SCHEMA_VERSION,
                "world_id": s.world_id,
                "created_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                "created_by": created_by,
                "counts": s.counts(),
                "scan_max_range_m": s.scan_max_range_m,
                "occupancy_resolution_m": s.occupancy_resolution_m,
                "user": dict(s.metadata),
            }
            con.executemany("INSERT INTO meta VALUES (?, ?)", [(k, json.dumps(v)) for k, v in meta.items()])
            con.executemany(
                "INSERT INTO keyframes VALUES (?, ?, ?, ?, ?, ?)",
                ((i, float(p[0]), float(p[1]), float(p[2]), _blob(r, np.float32), _blob(d, np.float64))
                 for i, (p, r, d) in enumerate(zip(s.keyframe_poses, s.keyframe_scans, s.descriptors, strict=True))))
            con.executemany("INSERT INTO nodes VALUES (?, ?, ?, ?)",
                            ((int(i), float(p[0]), float(p[1]), float(p[2]))
                             for i, p in zip(s.node_ids, s.node_poses, strict=True)))
            con.executemany(
                "INSERT INTO edges VALUES (?, ?, ?, ?, ?, ?, ?)",
                ((i, int(ab[0]), int(ab[1]), float(z[0]), float(z[1]), float(z[2]), _blob(info, np.float64))
                 for i, (ab, z, info) in enumerate(zip(s.edge_nodes, s.edge_poses, s.edge_information,
                                                       strict=True))))
            arrays: dict[str, tuple[NDArray[Any], type]] = {
                "scan_angles_rad": (s.scan_angles_rad, np.float64),
                "occupancy_logodds": (s.occupancy_logodds, np.float32),
                "occupancy_origin": (s.occupancy_origin, np.float64),
                **{f"layer:{n}": (np.asarray(a), np.asarray(a).dtype.type) for n, a in s.layers.items()}}
            con.executemany("INSERT INTO arrays VALUES (?, ?, ?, ?)",
                            ((n, np.dtype(dt).name, json.dumps(list(a.shape)), _blob(a, dt))
                             for n, (a, dt) in arrays.items()))
            # a digest of everything above: a changed number (which SQLite's own checks pass) is found on reading
            con.execute("INSERT INTO meta VALUES ('digest', ?)", (json.dumps(_content_digest(con)),))
            # the schema version goes in last: a file without it was never finished
            con.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            con.execute("COMMIT")
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        finally:
            con.close()
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())

    # ------------------------------------------------------------------ reading
    @staticmethod
    def _open(path: Path) -> sqlite3.Connection:
        """A read-only connection to a file that is a slam2d map of a schema we can read."""
        if not path.exists():
            raise MapFormatError(f"{path}: no such file")
        if path.is_dir():
            raise MapFormatError(f"{path}: is a directory, not a slam2d map")
        with open(path, "rb") as fh:
            head = fh.read(100)
        if not head.startswith(b"SQLite format 3\x00"):
            raise MapFormatError(f"{path}: not a slam2d map (not an SQLite database)")
        if len(head) < 100:
            raise MapFormatError(f"{path}: corrupt or truncated slam2d map (shorter than an SQLite header)")
        if int.from_bytes(head[68:72], "big") != APPLICATION_ID:
            raise MapFormatError(f"{path}: not a slam2d map (an SQLite database of another application)")
        version = int.from_bytes(head[60:64], "big")
        if version > SCHEMA_VERSION:
            raise MapFormatError(f"{path}: map schema version {version} is newer than this slam2d reads "
                                 f"({SCHEMA_VERSION}); upgrade slam2d")
        if version < 1:
            raise MapFormatError(f"{path}: incomplete slam2d map (no schema version: the write never finished)")
        try:
            # immutable: our files are never changed in place (writes rename a new file over them), and a read-only
            # reader then leaves no -wal/-shm files behind
            con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)
            con.execute("SELECT count(*) FROM sqlite_master").fetchone()
        except sqlite3.DatabaseError as e:
            raise MapFormatError(f"{path}: corrupt or truncated slam2d map ({e})") from None
        return con

    @staticmethod
    def info(path: str | Path) -> MapInfo:
        """Metadata and counts, after checking the file is an intact slam2d map of a readable schema."""
        path = Path(path)
        con = MapStore._open(path)
        try:
            check = con.execute("PRAGMA quick_check").fetchall()
            if check != [("ok",)]:
                raise MapFormatError(f"{path}: corrupt or truncated slam2d map (integrity check: "
                                     f"{'; '.join(str(r[0]) for r in check[:3])})")
            meta = {k: json.loads(v) for k, v in con.execute("SELECT key, value FROM meta")}
            counts = {t: int(con.execute(f"SELECT count(*) FROM {t}").fetchone()[0])
                      for t in ("keyframes", "nodes", "edges")}
            # files written before the digest have none; every file since must match its own
            digest = _content_digest(con) if "digest" in meta else None
        except sqlite3.DatabaseError as e:
            raise MapFormatError(f"{path}: corrupt or truncated slam2d map ({e})") from None
        except json.JSONDecodeError as e:
            raise MapFormatError(f"{path}: corrupt slam2d map (a metadata value is not JSON: {e})") from None
        finally:
            con.close()
        if meta.get("format") != "slam2d-map":
            raise MapFormatError(f"{path}: not a slam2d map (format tag {meta.get('format')!r})")
        recorded = meta.get("counts")
        expected = {k: recorded.get(k) if isinstance(recorded, dict) else None for k in counts}
        if expected != counts:
            raise MapFormatError(f"{path}: corrupt slam2d map (rows {counts} but the metadata records {expected})")
        if digest is not None and digest != meta["digest"]:
            raise MapFormatError(f"{path}: corrupt slam2d map (its contents no longer match the digest recorded "
                                 "when it was written)")
        try:
            return MapInfo(path, int(meta["schema_version"]), str(meta["world_id"]), str(meta.get("created_at", "")),
                           str(meta.get("created_by", "")), dict(meta["counts"]), dict(meta.get("user", {})))
        except (KeyError, TypeError, ValueError) as e:  # a metadata row missing or of the wrong kind
            raise MapFormatError(f"{path}: corrupt slam2d map (metadata: {type(e).__name__}: {e})") from None

    @staticmethod
    def read(path: str | Path, *, world_id: str | None = None) -> MapSnapshot:
        """The map in ``path``; with ``world_id``, also check that it was built for that world."""
        path = Path(path)
        info = MapStore.info(path)
        if world_id is not None and info.world_id != world_id:
            raise MapFormatError(f"{path}: map of world {info.world_id!r}, not of this world {world_id!r}")
        con = MapStore._open(path)
        try:
            meta = {k: json.loads(v) for k, v in con.execute("SELECT key, value FROM meta")}
            arrays = {n: _unblob(d, np.dtype(dt).type, tuple(json.loads(sh)))
                      for n, dt, sh, d in con.execute("SELECT name, dtype, shape, data FROM arrays")}
            angles = arrays["scan_angles_rad"]
            b = len(angles)
            kf = con.execute("SELECT x, y, theta, scan, descriptor FROM keyframes ORDER BY id").fetchall()
            dim = int(info.counts["descriptor_dim"])
            poses = np.array([r[:3] for r in kf], dtype=np.float64).reshape(-1, 3)
            scans = np.stack([_unblob(r[3], np.float32, (b,)) for r in kf]) if kf else np.zeros((0, b), np.float32)
            desc = np.stack([_unblob(r[4], np.float64, (dim,)) for r in kf]) if kf else np.zeros((0, dim))
            nodes = con.execute("SELECT id, x, y, theta FROM nodes ORDER BY id").fetchall()
            edges = con.execute("SELECT a, b, dx, dy, dtheta, information FROM edges ORDER BY id").fetchall()
        except (sqlite3.DatabaseError, zlib.error, ValueError, KeyError, TypeError) as e:
            raise MapFormatError(f"{path}: corrupt slam2d map ({type(e).__name__}: {e})") from None
        finally:
            con.close()
        try:
            return MapSnapshot(
                world_id=str(meta["world_id"]),
                keyframe_poses=poses,
                keyframe_scans=scans,
                descriptors=desc,
                scan_angles_rad=angles,
                scan_max_range_m=float(meta["scan_max_range_m"]),
                node_ids=np.array([r[0] for r in nodes], dtype=np.int64),
                node_poses=np.array([r[1:] for r in nodes], dtype=np.float64).reshape(-1, 3),
                edge_nodes=np.array([r[:2] for r in edges], dtype=np.int64).reshape(-1, 2),
                edge_poses=np.array([r[2:5] for r in edges], dtype=np.float64).reshape(-1, 3),
                edge_information=(np.stack([_unblob(r[5], np.float64, (3, 3)) for r in edges]) if edges
                                  else np.zeros((0, 3, 3))),
                occupancy_logodds=arrays["occupancy_logodds"],
                occupancy_origin=arrays["occupancy_origin"],
                occupancy_resolution_m=float(meta["occupancy_resolution_m"]),
                metadata=meta.get("user", {}),
                layers={n.split(":", 1)[1]: a for n, a in arrays.items() if n.startswith("layer:")},
            )
        except (ValueError, KeyError) as e:
            raise MapFormatError(f"{path}: inconsistent slam2d map ({e})") from None


# ---------------------------------------------------------------------- mapping from truth
def sim_world_id(metadata: Mapping[str, Any]) -> str:
    """The world id of a simulated Log: scenario, seed, and a hash of the config fields that shape the building.

    Flight-to-flight changes (``warehouse.flight``, ``warehouse.relocate_fraction``) and everything about the run
    (steps, sensors, noise) are left out, so every flight in the same warehouse shares one id.
    """
    cfg = dict(metadata.get("config", {}))
    shape = {k: cfg.get(k) for k in ("name", "landmarks")}
    shape["warehouse"] = {k: v for k, v in dict(cfg.get("warehouse", {})).items()
                          if k not in ("flight", "relocate_fraction", "floor_markers", "marker_spacing_m")}
    digest = hashlib.sha1(json.dumps(shape, sort_keys=True).encode()).hexdigest()[:10]
    return f"sim:{metadata.get('scenario', cfg.get('name'))}:seed={metadata.get('seed')}:{digest}"


def range_histogram(ranges: ArrayLike, max_range: float, bins: int = 16) -> Array:
    """A rotation-invariant place descriptor of scans: the fraction of beams per range bin, plus the fraction with
    no return. Shapes: (..., B) -> (..., bins + 1). A placeholder until the lidar estimator brings its own."""
    r = np.asarray(ranges, dtype=np.float64)
    hit = np.isfinite(r) & (r > 0) & (r < max_range)
    k = np.where(hit, np.minimum((r / max_range * bins).astype(np.int64), bins - 1), bins)
    onehot = k[..., None] == np.arange(bins + 1)
    return np.asarray(onehot.mean(axis=-2), dtype=np.float64)


def snapshot_from_truth(log: Log, *, keyframe_every_m: float = 1.0, keyframe_every_rad: float = 0.5,
                        occupancy: OccupancyConfig | None = None, layers: LayersConfig | None = None) -> MapSnapshot:
    """A map built from a simulated run's TRUE poses: keyframes where the robot moved ``keyframe_every_m`` or
    turned ``keyframe_every_rad`` since the last one, the occupancy grid of the keyframe scans, and a chain pose
    graph over the keyframes (true relative poses, nominal information for 5 cm / 0.6 deg), and the floor markers
    (layer ``floor_markers``, marker ``i`` has id ``i``) when the world has them. ``layers``: also a lifelong
    static layer (:meth:`MapLayers.saved`), every scan integrated at its true pose by the layers' own persistence
    rule, so forklifts stay out of it as they do in a lifelong session. A mapping-from-truth utility for tests and
    pages that must start in seconds; the lidar sessions write their own maps."""
    if log.true_poses is None or log.scan_step is None or log.scan_ranges_m is None or log.scan_angles_rad is None:
        raise ValueError("map from truth needs a simulated log with true poses and lidar scans")
    if not (keyframe_every_m > 0 and keyframe_every_rad > 0):
        raise ValueError("keyframe_every_m and keyframe_every_rad must be > 0")
    poses = log.true_poses[log.scan_step]
    keep = [0]
    for i in range(1, len(poses)):  # one pass over scans (not beams): keyframe selection is sequential
        d = se2.between(poses[keep[-1]], poses[i])
        if np.hypot(d[0], d[1]) >= keyframe_every_m or abs(d[2]) >= keyframe_every_rad:
            keep.append(i)
    kf_poses = poses[keep]
    scans = log.scan_ranges_m[keep]
    grid_cfg = occupancy or OccupancyConfig()
    corners = kf_poses[:, :2] if log.walls is None or not len(log.walls) else np.vstack(
        [kf_poses[:, :2], log.walls.reshape(-1, 2)])
    grid = OccupancyGrid.around(corners, 1.0, grid_cfg)
    grid.integrate(kf_poses, scans, log.scan_angles_rad, log.scan_max_range_m)
    n = len(keep)
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], axis=-1).astype(np.int64).reshape(-1, 2)
    info = np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.01**2])
    meta = log.metadata
    cfg = dict(meta.get("config", {}))
    name = str(meta.get("scenario", cfg.get("name")))
    flight = dict(cfg.get("warehouse", {})).get("flight") if name in SCENARIOS and SCENARIOS[name].uses_warehouse \
        else None
    return MapSnapshot(
        world_id=sim_world_id(meta),
        keyframe_poses=kf_poses.copy(),
        keyframe_scans=scans.astype(np.float32),
        descriptors=range_histogram(scans, log.scan_max_range_m),
        scan_angles_rad=log.scan_angles_rad.copy(),
        scan_max_range_m=float(log.scan_max_range_m),
        node_ids=np.arange(n, dtype=np.int64),
        node_poses=kf_poses.copy(),
        edge_nodes=edges,
        edge_poses=se2.between(kf_poses[:-1], kf_poses[1:]).reshape(-1, 3),
        edge_information=np.broadcast_to(info, (len(edges), 3, 3)).copy(),
        occupancy_logodds=grid.logodds.astype(np.float32),
        occupancy_origin=grid.origin.copy(),
        occupancy_resolution_m=float(grid.resolution),
        metadata={"source": "truth", "scenario": meta.get("scenario"), "seed": meta.get("seed"),
                  "flight": flight,
                  "steps": log.num_steps, "keyframe_every_m": keyframe_every_m,
                  "keyframe_every_rad": keyframe_every_rad},
        layers={**({} if log.true_markers is None else {"floor_markers": log.true_markers.copy()}),
                **({} if layers is None else _static_layer_from_truth(log, layers))},
    )


def _static_layer_from_truth(log: Log, config: LayersConfig) -> dict[str, NDArray[Any]]:
    """The saved static layer of every scan of ``log`` integrated at its true pose (one scan at a time: the
    persistence rule is sequential)."""
    assert log.true_poses is not None and log.scan_step is not None and log.scan_ranges_m is not None
    assert log.scan_angles_rad is not None
    lay = MapLayers(config)
    for k, (step, ranges) in enumerate(zip(log.scan_step.tolist(), log.scan_ranges_m, strict=True)):
        pose = log.true_poses[step]
        pts = scan_to_points(ranges, log.scan_angles_rad, log.scan_max_range_m)
        lay.integrate(pose, pts, lay.classify(pose, pts), float(log.stamps_s[step]), bootstrap=k == 0)
    return lay.saved()
