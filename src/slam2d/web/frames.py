"""Binary frames server -> browser: a 16-byte header, then tagged float32 sections.

Layout (little-endian; every offset is a multiple of 4, which ``Float32Array`` views in the browser require)::

    offset  type        meaning
    0       char[4]     magic ``b"SLM1"``
    4       uint32      seq        frame counter of this connection (starts at 0)
    8       uint32      n_sections number of sections that follow
    12      uint32      n_bytes    total length of the frame, header included
    16      section 0, section 1, ...

    section header (16 bytes), then its payload:
    0       char[4]     tag, e.g. ``b"TPOS"`` (true pose), ``b"ELMK"`` (estimated landmarks)
    4       uint32      rows
    8       uint32      cols
    12      uint32      reserved (0)
    16      float32[rows*cols]  row-major values

The tags a session may send are listed in ``TAGS`` (with their shapes); the browser decodes sections it knows and
ignores the rest, so adding a section never breaks an older page. Scalars travel in the ``NUMS`` section, in the
order of the ``scalars`` names announced in the session's ``hello`` message.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

MAGIC = b"SLM1"
HEADER = struct.Struct("<4sIII")
SECTION = struct.Struct("<4sIII")

#: tag -> (shape, meaning); documentation for page authors and the browser decoder
TAGS: dict[str, tuple[str, str]] = {
    "NUMS": ("(1,K)", "scalars, in the order announced by the session's hello message"),
    "WALL": ("(W,4)", "wall segments x0,y0,x1,y1 (m)"),
    "TLMK": ("(N,2)", "true landmark positions (m)"),
    "TPOS": ("(1,3)", "true robot pose x,y,theta"),
    "TPTH": ("(T,2)", "true path so far (downsampled)"),
    "RNGE": ("(1,3)", "sensor range circle: centre x, y (the true robot) and radius (m)"),
    "EPOS": ("(1,3)", "estimated robot pose"),
    "PCOV": ("(1,4)", "estimated pose covariance, xy block, row-major 2x2"),
    "EPTH": ("(T,2)", "estimated path (the back end's trajectory when it re-estimates the past)"),
    "GHST": ("(T,2)", "a ghost: the estimated path before the last correction (loop closure, optimisation)"),
    "ELMK": ("(L,2)", "estimated landmark positions"),
    "ECOV": ("(L,4)", "estimated landmark covariances, row-major 2x2"),
    "OBSV": ("(K,2)", "this step's observations projected from the estimated pose into the world"),
    "OCOV": ("(K,4)", "world-frame covariance of each observation, G_z R G_z^T, row-major 2x2"),
    "PART": ("(M,3)", "particle poses"),
    "HEAT": ("(n,n)", "|correlation| matrix of the full state covariance (block-averaged when large)"),
    "GEDG": ("(E,4)", "graph edges as segments x0,y0,x1,y1"),
    "GNOD": ("(V,2)", "graph nodes (pose positions)"),
    "MTCH": ("(K,5)", "association lines: observation x,y, landmark x,y, 1 correct / 0 wrong"),
    "NEWO": ("(K,2)", "observations declared new or clutter by the association"),
    "SCAN": ("(P,2)", "lidar points in the world"),
    "GRID": ("(rows,cols)", "grid image in [0,1] (occupancy probability or intensity); row 0 = lowest y"),
    "GRDM": ("(1,3)", "grid placement: origin x, origin y (m) of cell (0,0)'s corner, cell size (m)"),
    "FEAT": ("(K,2)", "detected features in the world"),
    "TCOR": ("(C,2)", "true corners in the world"),
    "FORK": ("(4F,4)", "forklift outlines from the simulator (truth), four segments per forklift"),
    "HYPO": ("(H,3)", "relocalisation hypotheses (map-frame poses), best first"),
    "HHIS": ("(N,2)", "relocalisation history: time since the start (s), hypotheses kept"),
}


def encode_frame(seq: int, sections: Sequence[tuple[str, ArrayLike]]) -> bytes:
    """Pack ``sections`` (tag, 2-D array) into one frame. Arrays are cast to float32; 1-D arrays become one row.

    Shapes: each array (rows, cols) or (cols,). Raises ValueError for a tag that is not 4 ASCII characters.
    """
    parts: list[bytes] = []
    for tag, arr in sections:
        a = np.asarray(arr, dtype="<f4")
        if a.ndim == 1:
            a = a.reshape(1, -1)
        elif a.ndim != 2:
            a = a.reshape(a.shape[0], -1)
        t = tag.encode("ascii")
        if len(t) != 4:
            raise ValueError(f"section tag must be 4 ASCII characters, got {tag!r}")
        parts.append(SECTION.pack(t, a.shape[0], a.shape[1], 0))
        parts.append(np.ascontiguousarray(a).tobytes())
    body = b"".join(parts)
    return HEADER.pack(MAGIC, seq & 0xFFFFFFFF, len(sections), HEADER.size + len(body)) + body


def decode_frame(buf: bytes) -> tuple[int, dict[str, NDArray[np.float32]]]:
    """Inverse of :func:`encode_frame` (used by tests and Python clients). Returns (seq, {tag: array})."""
    magic, seq, n, total = HEADER.unpack_from(buf, 0)
    if magic != MAGIC or total != len(buf):
        raise ValueError(f"not a slam2d frame (magic {magic!r}, length {len(buf)} vs header {total})")
    out: dict[str, NDArray[np.float32]] = {}
    off = HEADER.size
    for _ in range(n):
        tag, rows, cols, _r = SECTION.unpack_from(buf, off)
        off += SECTION.size
        count = rows * cols
        out[tag.decode("ascii")] = np.frombuffer(buf, dtype="<f4", count=count, offset=off).reshape(rows, cols)
        off += 4 * count
    return seq, out
