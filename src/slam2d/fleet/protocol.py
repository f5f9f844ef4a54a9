"""The fleet wire protocol: versioned msgpack messages between drones, the map server and watchers.

Every message is one msgpack map with ``v`` (protocol version) and ``type``. Drone -> server:

* ``hello``  {drone, session, dock [x, y, theta]}: claim drone id ``drone``; the server answers ``welcome``
  {acked_seq, keyframes} (what it has committed from this drone) or ``error``.
* ``delta``  {drone, seq, keyframes [{id, stamp, pose, desc, pts, mk?}], edges [{a, b, z, info}]}: new keyframes (ids
  consecutive from the number already committed) and edges between this drone's keyframes (odometry chain and its
  own loop closures). ``seq`` counts from 1 per drone. Answered by ``ack`` {seq, duplicate, poses, tiles} only
  after the delta is committed; a resend of a committed delta (same seq, same content) is acknowledged again and
  changes nothing.
* ``status`` {}: a snapshot of the merged map for watchers (the lab): ``status`` {drones, keyframes, loops}.

Server -> client errors: ``error`` {code, message, seq?}; they concern the one client that sent the message.

A keyframe carries no raw scan: ``desc`` is a 17-byte range histogram (uint8, fraction of beams per range bin * 255)
and ``pts`` a subsampled point set in the keyframe frame as little-endian int16 centimetres (x0 y0 x1 y1 ...).
``mk`` (optional, version 2) holds the floor markers the keyframe read: 10 bytes each, little-endian, uint32 id,
int16 x and y in millimetres in the keyframe frame, uint16 standard deviation in 0.1 mm (at most ``MAX_MARKERS``,
ids distinct). Version 2 is version 1 plus ``mk``; a version-1 peer is refused (it would drop the markers).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

VERSION = 2
MAX_MESSAGE_BYTES = 4 << 20
DESC_BINS = 16
MAX_POINTS = 120
POINT_SCALE = 100.0  # int16 centimetres: +-327 m
MAX_ITEMS = 4096  # keyframes or edges per delta
MAX_MARKERS = 32  # marker sightings per keyframe
MARKER_DTYPE = np.dtype([("id", "<u4"), ("x", "<i2"), ("y", "<i2"), ("sigma", "<u2")])
MARKER_SCALE = 1000.0  # int16 millimetres: +-32 m
SIGMA_SCALE = 1e4  # uint16 tenths of a millimetre: up to 6.5 m
#: largest |value| of a pose, dock or edge component (m or rad) and of an information entry: finite numbers beyond
#: these overflow the joint graph's composition and solve (inf, then NaN) after the delta was committed, and the
#: server could neither go on nor restart on its journal. A drone's own values are orders of magnitude smaller.
MAX_COORD = 1e6
MAX_INFO = 1e12
#: an edge information's smallest eigenvalue (a standard deviation of 1 km or 1000 rad: a drone's edges carry 1e2 and
#: more) and smallest ratio of its eigenvalues (the joint graph refuses a numerically singular factor at 1e-13):
#: weaker edges leave their keyframe numerically unconstrained and the joint solve fails
MIN_INFO = 1e-6
MIN_INFO_CONDITION = 1e-12


class ProtocolError(ValueError):
    """A message the server refuses; ``code`` names the kind of refusal for the client."""

    def __init__(self, code: str, message: str, seq: int | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.seq = seq


def encode(msg: dict[str, Any]) -> bytes:
    return bytes(msgpack.packb({"v": VERSION, **msg}, use_bin_type=True))


def decode(data: bytes) -> dict[str, Any]:
    """Parse and check the envelope (size, msgpack, map, version, type)."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError("too-large", f"message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    try:
        msg = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES)
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise ProtocolError("garbled", f"not a msgpack message ({type(e).__name__})") from None
    if not isinstance(msg, dict):
        raise ProtocolError("garbled", f"a message must be a map, got {type(msg).__name__}")
    v = msg.get("v")
    if v != VERSION:
        raise ProtocolError("version", f"protocol version {v!r} is not supported (this server speaks {VERSION})")
    if not isinstance(msg.get("type"), str):
        raise ProtocolError("garbled", "message has no 'type'")
    return msg


def _int(msg: dict[str, Any], key: str, lo: int = 0, hi: int = 2**31) -> int:
    x = msg.get(key)
    if not isinstance(x, int) or isinstance(x, bool) or not lo <= x < hi:
        raise ProtocolError("garbled", f"field '{key}' must be an integer in [{lo}, {hi}) (got {x!r})")
    return x


def _floats(x: Any, n: int, what: str, bound: float | None = None, seq: int | None = None) -> Array:
    if not isinstance(x, list | tuple) or len(x) != n:
        raise ProtocolError("garbled", f"{what} must be a list of {n} numbers", seq)
    a = np.asarray([v if isinstance(v, int | float) and not isinstance(v, bool) else np.nan for v in x], np.float64)
    if not np.all(np.isfinite(a)):
        raise ProtocolError("garbled", f"{what} must hold finite numbers", seq)
    if bound is not None and np.abs(a).max() > bound:
        raise ProtocolError("garbled", f"{what} must hold numbers within +-{bound:g}", seq)
    return a


@dataclass(frozen=True)
class Keyframe:
    id: int
    stamp: float
    pose: Array  # (3,) in the drone's frame
    desc: bytes
    pts: bytes
    mk: bytes = b""  # floor markers read (MARKER_DTYPE records)


@dataclass(frozen=True)
class Edge:
    a: int
    b: int
    z: Array  # (3,) T_a_b
    info: Array  # (6,) upper triangle of the 3x3 information, row-major


@dataclass(frozen=True)
class Delta:
    drone: int
    seq: int
    keyframes: tuple[Keyframe, ...]
    edges: tuple[Edge, ...]
    digest: str


def parse_hello(msg: dict[str, Any]) -> tuple[int, str, Array]:
    session = msg.get("session")
    if not isinstance(session, str) or not 1 <= len(session) <= 64:
        raise ProtocolError("garbled", "hello: 'session' must be a string of 1..64 characters")
    return _int(msg, "drone", 0, 1 << 16), session, _floats(msg.get("dock"), 3, "hello: 'dock'", MAX_COORD)


def parse_delta(msg: dict[str, Any]) -> Delta:
    drone, seq = _int(msg, "drone", 0, 1 << 16), _int(msg, "seq", 1)
    kfs, edges = msg.get("keyframes"), msg.get("edges")
    if not isinstance(kfs, list) or not isinstance(edges, list) or len(kfs) + len(edges) > MAX_ITEMS:
        raise ProtocolError("garbled", f"delta {seq}: 'keyframes' and 'edges' must be lists (at most {MAX_ITEMS})",
                            seq)
    out_k = []
    for i, k in enumerate(kfs):
        if not isinstance(k, dict):
            raise ProtocolError("garbled", f"delta {seq}: keyframes[{i}] must be a map", seq)
        desc, pts = k.get("desc"), k.get("pts")
        if not isinstance(desc, bytes) or len(desc) != DESC_BINS + 1:
            raise ProtocolError("garbled", f"delta {seq}: keyframes[{i}].desc must be {DESC_BINS + 1} bytes", seq)
        if not isinstance(pts, bytes) or len(pts) % 4 or len(pts) > 4 * MAX_POINTS:
            raise ProtocolError("garbled", f"delta {seq}: keyframes[{i}].pts must be at most {MAX_POINTS} int16 "
                                           "pairs", seq)
        stamp = _floats([k.get("stamp")], 1, f"delta {seq}: keyframes[{i}].stamp", seq=seq)[0]
        mk = k.get("mk", b"")
        check_markers(mk, f"delta {seq}: keyframes[{i}].mk", seq)
        pose = _floats(k.get("pose"), 3, f"delta {seq}: keyframes[{i}].pose", MAX_COORD, seq)
        out_k.append(Keyframe(_int(k, "id"), float(stamp), pose, desc, pts, mk))
    ids = [k.id for k in out_k]
    if ids and ids != list(range(ids[0], ids[0] + len(ids))):
        raise ProtocolError("garbled", f"delta {seq}: keyframe ids must be consecutive (got {ids[:5]}...)", seq)
    out_e = []
    for i, e in enumerate(edges):
        if not isinstance(e, dict):
            raise ProtocolError("garbled", f"delta {seq}: edges[{i}] must be a map", seq)
        info = _floats(e.get("info"), 6, f"delta {seq}: edges[{i}].info", MAX_INFO, seq)
        ev = np.linalg.eigvalsh(info_matrix(info))
        if not (ev[0] >= MIN_INFO and ev[0] > MIN_INFO_CONDITION * ev[-1]):
            raise ProtocolError("garbled", f"delta {seq}: edges[{i}].info is not positive definite (eigenvalues at "
                                           f"least {MIN_INFO:g} and {MIN_INFO_CONDITION:g} of the largest)", seq)
        a, b = _int(e, "a"), _int(e, "b")
        if a == b:
            raise ProtocolError("garbled", f"delta {seq}: edges[{i}] joins keyframe {a} to itself", seq)
        out_e.append(Edge(a, b, _floats(e.get("z"), 3, f"delta {seq}: edges[{i}].z", MAX_COORD, seq), info))
    body = msgpack.packb([msg.get("keyframes"), msg.get("edges")], use_bin_type=True)
    return Delta(drone, seq, tuple(out_k), tuple(out_e), hashlib.sha256(body).hexdigest())


def check_markers(mk: Any, what: str, seq: int | None = None) -> None:
    """Refuse a marker field that is not whole records, too many, repeated ids or a non-positive sigma."""
    if not isinstance(mk, bytes) or len(mk) % MARKER_DTYPE.itemsize or len(mk) > MAX_MARKERS * MARKER_DTYPE.itemsize:
        raise ProtocolError("garbled", f"{what} must be at most {MAX_MARKERS} records of {MARKER_DTYPE.itemsize} "
                                       "bytes", seq)
    rec = np.frombuffer(mk, MARKER_DTYPE)
    if len(np.unique(rec["id"])) != len(rec):
        raise ProtocolError("garbled", f"{what} repeats a marker id", seq)
    if np.any(rec["sigma"] == 0):
        raise ProtocolError("garbled", f"{what} has a marker with zero standard deviation", seq)


def pack_markers(ids: NDArray[np.int64], xy: Array, sigma: Array) -> bytes:
    """Marker sightings (K,) ids, (K,2) keyframe-frame positions (m), (K,) standard deviations (m) as ``mk``."""
    rec = np.zeros(len(ids), MARKER_DTYPE)
    rec["id"] = ids
    q = np.clip(np.round(np.asarray(xy, np.float64).reshape(-1, 2) * MARKER_SCALE), -32767, 32767)
    rec["x"], rec["y"] = q[:, 0], q[:, 1]
    rec["sigma"] = np.clip(np.round(np.asarray(sigma, np.float64) * SIGMA_SCALE), 1, 65535)
    return rec.tobytes()


def unpack_markers(mk: bytes) -> tuple[NDArray[np.int64], Array, Array]:
    """(ids (K,), xy (K,2) m, sigma (K,) m) of a ``mk`` field."""
    rec = np.frombuffer(mk, MARKER_DTYPE)
    xy = np.stack([rec["x"], rec["y"]], axis=-1).astype(np.float64) / MARKER_SCALE
    return rec["id"].astype(np.int64), xy.reshape(-1, 2), rec["sigma"].astype(np.float64) / SIGMA_SCALE


def info_matrix(upper: Array) -> Array:
    """The symmetric 3x3 information from its row-major upper triangle (6,)."""
    a, b, c, d, e, f = upper
    return np.array([[a, b, c], [b, d, e], [c, e, f]], dtype=np.float64)


def info_upper(m: Array) -> list[float]:
    return [float(m[0, 0]), float(m[0, 1]), float(m[0, 2]), float(m[1, 1]), float(m[1, 2]), float(m[2, 2])]


def pack_points(pts: Array) -> bytes:
    """At most MAX_POINTS points (evenly subsampled in beam order), int16 centimetres, clipped to +-327 m."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(p) > MAX_POINTS:
        p = p[np.linspace(0, len(p) - 1, MAX_POINTS).round().astype(np.int64)]
    q = np.clip(np.round(p * POINT_SCALE), -32767, 32767).astype("<i2")
    return q.tobytes()


def unpack_points(b: bytes) -> Array:
    return np.frombuffer(b, dtype="<i2").reshape(-1, 2).astype(np.float64) / POINT_SCALE


def pack_descriptor(hist: Array) -> bytes:
    return np.clip(np.round(np.asarray(hist) * 255), 0, 255).astype(np.uint8).tobytes()


def unpack_descriptor(b: bytes) -> Array:
    return np.frombuffer(b, dtype=np.uint8).astype(np.float64) / 255.0
