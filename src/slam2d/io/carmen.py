"""CARMEN ``.clf`` laser logs (plain or ``.bz2``): FLASER / ROBOTLASER1 scans and ODOM records.

One message per line; the last three fields of a message are ``ipc_timestamp ipc_hostname logger_timestamp``.

* ``FLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_ts host logger_ts``: beams spread evenly over 180 deg
  starting at -90 deg (the CARMEN convention; 1 deg for n=180, 0.5 deg for n=360, both ends included for n=361).
* ``ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r_1..r_n m rem_1..rem_m
  laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd_safety side_safety turn_axis ipc_ts host
  logger_ts``: beam angles are given by the record.
* ``ODOM x y theta tv rv accel ipc_ts host logger_ts``.

Other record types (PARAM, SYNC, RAWLASER*, TRUEPOS, NMEA-*...) are counted and reported, never silently dropped.
A line that is too short, has a non-number where a number belongs or has a different beam count than the first
scan is an error naming ``file:line`` (or, with ``on_error="skip"``, skipped and
listed in :attr:`CarmenLog.problems`). A scan whose timestamp goes backwards is kept in file order and listed
(see ``CarmenConfig.backwards_stamps``). Ranges that are NaN, inf, <= 0 or at/beyond ``max_range_m`` are no-return
beams: they are stored as exactly ``max_range_m`` so ``Scan`` consumers ignore them; NaN/inf/negative ones are
counted (``invalid_beams``) and their lines listed (``invalid_beam_lines``). A scan with no usable beam at all
(every reading a no-return, or ``FLASER 0``) carries nothing to match: it is always skipped and listed in
``problems``.
"""

from __future__ import annotations

import bz2
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from slam2d.config import check_positive
from slam2d.geometry import se2
from slam2d.io import bounded
from slam2d.log import Log, LogFormatError

Array = NDArray[np.float64]

_KNOWN_IGNORED = {"PARAM", "SYNC"}


@dataclass(frozen=True, slots=True, kw_only=True)
class CarmenConfig:
    """How a CARMEN log is read."""

    max_range_m: float = 40.0
    """readings at or beyond this range (including the sensors' 50 / 81.83 / 81.91 m "no return" codes) count as
    no return (m)."""
    on_error: Literal["raise", "skip"] = "raise"
    """what to do with a malformed line: raise a ``LogFormatError`` naming file:line, or skip it and record it."""
    max_lines: int = 0
    """stop after this many lines (0: read everything); for quick looks at big logs."""
    backwards_stamps: Literal["keep", "skip", "raise"] = "keep"
    """a scan whose timestamp is older than an earlier scan's: ``keep`` it in file order (listed in
    ``CarmenLog.backwards_stamps``), ``skip`` it, or ``raise`` (both via ``on_error``'s file:line handling: ``raise``
    fails unless ``on_error="skip"``). intel.clf has 1612 such scans; its file order is the physical one (odometry
    path 508 m in file order, 661 m when sorted by time) and its relations name 731 of them, so keep is the default."""

    def __post_init__(self) -> None:
        check_positive(self, "max_range_m")
        if self.on_error not in ("raise", "skip"):
            raise ValueError(f"CarmenConfig.on_error must be 'raise' or 'skip' (got {self.on_error!r})")
        if self.backwards_stamps not in ("keep", "skip", "raise"):
            raise ValueError(f"CarmenConfig.backwards_stamps must be 'keep', 'skip' or 'raise' "
                             f"(got {self.backwards_stamps!r})")
        if self.max_lines < 0:
            raise ValueError(f"CarmenConfig.max_lines must be >= 0 (got {self.max_lines})")


@dataclass(frozen=True)
class CarmenLog:
    """The laser scans and odometry of one CARMEN log.

    Shapes (S scans, B beams, O odometry records): stamps_s (S,) ipc timestamps of the scans, ranges_m (S,B) with
    no-return beams set to ``max_range_m``, angles_rad (B,), poses (S,3) the pose logged with each scan (odometry
    frame; the laser pose for ROBOTLASER1), odom_stamps_s (O,), odom_poses (O,3).
    ``record_counts`` counts every record type seen; ``unknown`` the ones this reader does not use;
    ``invalid_beams`` the number of NaN/inf/negative readings (of the scans kept) replaced by no-return (a 0 reading
    is a no-return too, not counted); ``problems`` lists
    ``file:line: message`` for skipped lines; ``invalid_beam_lines`` and ``backwards_stamps`` the lines with such
    beams / with a timestamp older than an earlier scan's (kept).
    """

    path: str
    stamps_s: Array
    ranges_m: Array
    angles_rad: Array
    max_range_m: float
    poses: Array
    odom_stamps_s: Array
    odom_poses: Array
    record_counts: dict[str, int] = field(default_factory=dict)
    unknown: dict[str, int] = field(default_factory=dict)
    invalid_beams: int = 0
    problems: tuple[str, ...] = ()
    invalid_beam_lines: tuple[str, ...] = ()
    backwards_stamps: tuple[str, ...] = ()

    @property
    def num_scans(self) -> int:
        return int(self.stamps_s.shape[0])

    def summary(self) -> str:
        """One human-readable line: scans, beams, record types, unknown types, problems."""
        unk = ", ".join(f"{k}={v}" for k, v in sorted(self.unknown.items())) or "none"
        return (f"{self.path}: {self.num_scans} scans x {self.ranges_m.shape[1] if self.num_scans else 0} beams, "
                f"{len(self.odom_stamps_s)} ODOM, unknown record types: {unk}, invalid beams: {self.invalid_beams}, "
                f"skipped lines: {len(self.problems)}, backwards timestamps kept: {len(self.backwards_stamps)}")

    def to_log(self) -> Log:
        """A slam2d :class:`Log` with one step per scan: odometry between consecutive scan poses, scan at each step.

        Pose 0 is the first scan's pose; its scan is not in the ``Log`` (a ``Log`` holds scans at steps 1..T), so
        the log has S-1 steps and S poses, pose k taken at scan k. ``stamps_s`` start at 0; the original ipc
        timestamps of the S poses are ``metadata["stamps_original_s"]`` (exact floats, for trajectory files and the
        relations). No ground truth.
        """
        if self.num_scans < 2:
            why = (f"; {len(self.problems)} lines skipped, first: {self.problems[0]}" if self.problems else
                   f"; records read: {', '.join(f'{k} x{v}' for k, v in sorted(self.record_counts.items())) or 'none'}")
            raise LogFormatError(f"{self.path}: need at least 2 scans to build a log (got {self.num_scans}{why})")
        odo = se2.between(self.poses[:-1], self.poses[1:])
        t = odo.shape[0]
        return Log(
            # never backwards (a scan kept in file order gets the latest stamp so far; dt_s >= 0)
            stamps_s=np.maximum.accumulate(self.stamps_s) - self.stamps_s[0],
            odometry=odo,
            obs_step=np.zeros(0, dtype=np.int64),
            obs_range_m=np.zeros(0),
            obs_bearing_rad=np.zeros(0),
            obs_id=np.zeros(0, dtype=np.int64),
            initial_pose=np.zeros(3),
            scan_step=np.arange(1, t + 1, dtype=np.int64),
            scan_ranges_m=self.ranges_m[1:],
            scan_angles_rad=self.angles_rad,
            scan_max_range_m=self.max_range_m,
            metadata={"source": "carmen", "path": self.path, "dataset": Path(self.path).name.split(".")[0],
                      "units": {"length": "m", "angle": "rad", "time": "s"},
                      "start_stamp_s": float(self.stamps_s[0]),
                      "stamps_original_s": [float(v) for v in self.stamps_s],
                      "initial_odometry_pose": [float(v) for v in self.poses[0]],
                      "skipped_lines": len(self.problems), "invalid_beams": self.invalid_beams,
                      "backwards_stamps": len(self.backwards_stamps), "unknown_records": dict(self.unknown),
                      # the first few file:line messages of each kind, for a caller to show (bounded: a broken
                      # file can have a million)
                      "problem_examples": {"skipped_lines": list(self.problems[:3]),
                                           "invalid_beams": list(self.invalid_beam_lines[:3]),
                                           "backwards_stamps": list(self.backwards_stamps[:3])}},
        )


def flaser_angles(n: int) -> Array:
    """CARMEN FLASER beam angles: 180 deg field of view from -90 deg. Shapes: -> (n,) (n = 0: empty)."""
    if n <= 0:
        return np.zeros(0)
    if n == 361 or n == 181:
        return np.linspace(-np.pi / 2, np.pi / 2, n)
    return np.asarray(-np.pi / 2 + np.arange(n) * (np.pi / n), dtype=np.float64)


def _open_lines(path: Path) -> Iterator[str]:
    # bounded: file size (decompressed for .bz2) and line length are capped, so a bz2 bomb or /dev/zero fails fast
    opener = (lambda name: bz2.open(name, "rb")) if path.suffix == ".bz2" else None
    yield from bounded.iter_lines(path, LogFormatError, encoding="ascii", errors="replace", opener=opener)


class _Bad(Exception):
    pass


def _floats(tok: list[str], start: int, count: int, what: str) -> list[float]:
    if start + count > len(tok):
        raise _Bad(f"truncated {tok[0]} record: {what} needs fields {start}..{start + count - 1}, line has "
                   f"{len(tok)} fields")
    try:
        return [float(t) for t in tok[start:start + count]]
    except ValueError:
        bad = next(t for t in tok[start:start + count] if not _is_float(t))
        raise _Bad(f"{tok[0]} record: {what} has non-numeric value {bad!r}") from None


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def _count(tok: list[str], i: int, what: str) -> int:
    v = _floats(tok, i, 1, what)[0]
    if not (math.isfinite(v) and v >= 0 and v == int(v)):
        raise _Bad(f"{tok[0]} record: {what} must be a non-negative integer (got {tok[i]!r})")
    if v > len(tok):  # 1e300 readings: say so, not "needs fields 2..1000000000000000052504760255204420248704..."
        raise _Bad(f"truncated {tok[0]} record: {what} is {tok[i]}, the line has {len(tok)} fields")
    return int(v)


def read_carmen(path: str | Path, config: CarmenConfig | None = None) -> CarmenLog:
    """Read a CARMEN log. Raises :class:`LogFormatError` with ``file:line`` on malformed lines (see ``on_error``).

    Scans whose beam count or beam angles differ from the first scan's are errors too (one log, one laser).
    """
    cfg = config or CarmenConfig()
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such CARMEN log")
    if path.is_dir():
        raise IsADirectoryError(21, "is a directory, not a CARMEN log", str(path))
    if not path.is_file():  # a FIFO would block the open, /dev/zero never ends
        raise LogFormatError(f"{path}: not a regular file (a CARMEN log is a .clf or .clf.bz2 file)")
    counts: Counter[str] = Counter()
    stamps: list[float] = []
    ranges: list[list[float]] = []
    poses: list[list[float]] = []
    ostamps: list[float] = []
    oposes: list[list[float]] = []
    angles: Array | None = None
    problems: list[str] = []
    empty_scans: list[str] = []
    backwards: list[str] = []
    latest = -math.inf
    beam_lines: list[str] = []
    invalid_count = 0

    def fail(lineno: int, msg: str) -> None:
        full = f"{path}:{lineno}: {msg}"
        if cfg.on_error == "raise":
            raise LogFormatError(full)
        problems.append(full)

    try:
        for lineno, line in enumerate(_open_lines(path), start=1):
            if cfg.max_lines and lineno > cfg.max_lines:
                break
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                continue
            kind = tok[0]
            counts[kind] += 1
            try:
                if kind == "FLASER":
                    n = _count(tok, 1, "num_readings")
                    r = _floats(tok, 2, n, "range readings")
                    rest = _floats(tok, 2 + n, 7, "poses and ipc_timestamp")
                    if len(tok) < 2 + n + 9:
                        raise _Bad(f"truncated FLASER record: expected {2 + n + 9} fields, got {len(tok)}")
                    a = flaser_angles(n)
                    pose = rest[0:3]
                    ts = rest[6]
                elif kind == "ROBOTLASER1":
                    head = _floats(tok, 2, 3, "start_angle, fov, resolution")
                    if not all(math.isfinite(x) for x in head) or head[2] == 0:
                        raise _Bad(f"ROBOTLASER1 record: start_angle, fov, resolution must be finite with a non-zero "
                                   f"resolution (got {' '.join(tok[2:5])})")
                    n = _count(tok, 8, "num_readings")
                    r = _floats(tok, 9, n, "range readings")
                    m = _count(tok, 9 + n, "num_remissions")
                    base = 10 + n + m
                    rest = _floats(tok, base, 12, "poses, velocities and ipc_timestamp")
                    if len(tok) < base + 14:
                        raise _Bad(f"truncated ROBOTLASER1 record: expected {base + 14} fields, got {len(tok)}")
                    if head[2] > 0 and n < round(head[1] / head[2]):
                        raise _Bad(f"ROBOTLASER1 record: {n} readings, fewer than the {round(head[1] / head[2])} "
                                   f"beams of its angle table (fov {head[1]} / resolution {head[2]})")
                    a = np.asarray(head[0] + np.arange(n) * head[2], dtype=np.float64)
                    pose = rest[0:3]
                    ts = rest[11]
                elif kind == "ODOM":
                    v = _floats(tok, 1, 7, "x y theta tv rv accel ipc_timestamp")
                    if len(tok) < 10:
                        raise _Bad(f"truncated ODOM record: expected 10 fields, got {len(tok)}")
                    if not all(math.isfinite(x) for x in v[:3]):
                        raise _Bad("ODOM record: non-finite pose")
                    ostamps.append(v[6])
                    oposes.append(v[:3])
                    continue
                else:
                    continue
                if not all(math.isfinite(x) for x in pose) or not math.isfinite(ts):
                    raise _Bad(f"{kind} record: non-finite pose or timestamp")
                if stamps and ts < latest:
                    msg = f"{kind} record: timestamp {ts:.6f} goes backwards (latest scan so far {latest:.6f})"
                    if cfg.backwards_stamps != "keep":
                        raise _Bad(msg)
                    backwards.append(f"{path}:{lineno}: {msg}; kept in file order")
                rv = np.asarray(r, dtype=np.float64)
                usable = np.isfinite(rv) & (rv > 0) & (rv < cfg.max_range_m)
                if not usable.any():
                    empty_scans.append(f"{path}:{lineno}: {kind} record with no usable beam ({n} readings, all NaN, "
                                       f"inf, <= 0 or >= max range {cfg.max_range_m} m): scan skipped")
                    continue
                if angles is None:
                    angles = np.asarray(a, dtype=np.float64)
                elif len(a) != len(angles) or not np.allclose(a, angles, atol=1e-6):
                    raise _Bad(f"{kind} record: {len(a)} beams / beam angles differ from the first scan's "
                               f"({len(angles)} beams)")
                bad_beams = int(np.sum(~np.isfinite(rv) | (rv < 0)))
                if bad_beams:
                    beam_lines.append(f"{path}:{lineno}: {bad_beams} NaN/inf/negative ranges read as no return")
                    invalid_count += bad_beams
            except _Bad as e:
                fail(lineno, str(e))
                continue
            stamps.append(ts)
            latest = max(latest, ts)
            ranges.append(r)
            poses.append(pose)
    except (OSError, EOFError) as e:
        what = "unreadable or truncated compressed file" if path.suffix == ".bz2" else "unreadable file"
        raise LogFormatError(f"{path}: {what} ({e})") from None

    b = 0 if angles is None else len(angles)
    rng_arr = np.asarray(ranges, dtype=np.float64).reshape(len(ranges), b)
    no_return = ~np.isfinite(rng_arr) | (rng_arr <= 0) | (rng_arr >= cfg.max_range_m)
    rng_arr = np.where(no_return, cfg.max_range_m, rng_arr)
    unknown = {k: v for k, v in counts.items() if k not in {"FLASER", "ROBOTLASER1", "ODOM"} | _KNOWN_IGNORED}
    return CarmenLog(
        path=str(path),
        stamps_s=np.asarray(stamps, dtype=np.float64),
        ranges_m=rng_arr,
        angles_rad=np.zeros(0) if angles is None else angles,
        max_range_m=cfg.max_range_m,
        poses=np.asarray(poses, dtype=np.float64).reshape(-1, 3),
        odom_stamps_s=np.asarray(ostamps, dtype=np.float64),
        odom_poses=np.asarray(oposes, dtype=np.float64).reshape(-1, 3),
        record_counts=dict(counts),
        unknown=unknown,
        invalid_beams=invalid_count,
        problems=tuple(problems + empty_scans),
        invalid_beam_lines=tuple(beam_lines),
        backwards_stamps=tuple(backwards),
    )


#: the staged Radish logs (``<data>/radish-laser-logs/<name>.clf.bz2``, relations beside them)
RADISH_LOGS = ("aces", "intel", "fr079", "mit-csail")
_ALIASES = {"intel-laser": "intel"}


def is_carmen_source(name: str) -> bool:
    """True for a Radish log name or a path ending in ``.clf`` / ``.clf.bz2``."""
    return _ALIASES.get(name, name) in RADISH_LOGS or name.endswith((".clf", ".clf.bz2"))


def resolve_carmen(name: str, data_dir: str | Path | None = None) -> Path:
    """The file of a Radish log name (under :func:`slam2d.io.datasets.data_dir`) or an existing ``.clf(.bz2)`` path."""
    from slam2d.io.datasets import data_dir as default_dir

    key = _ALIASES.get(name, name)
    if key in RADISH_LOGS:
        root, why = default_dir(data_dir)
        p = root / "radish-laser-logs" / f"{key}.clf.bz2"
        if not p.exists():
            raise FileNotFoundError(f"dataset {name!r} not found at {p} (data directory from {why}; set SLAM2D_DATA "
                                    "or --data-dir)")
        return p
    p = Path(name)
    if not p.exists():
        raise FileNotFoundError(f"{name}: not a known laser log ({', '.join(RADISH_LOGS)}) nor an existing file")
    return p


def relations_beside(path: str | Path) -> Path | None:
    """``<log>.relations`` next to a ``.clf`` / ``.clf.bz2`` file, if it exists."""
    p = Path(path)
    stem = p.name[: -len(".clf.bz2")] if p.name.endswith(".clf.bz2") else p.name.removesuffix(".clf")
    r = p.with_name(stem + ".relations")
    return r if r.exists() and r != p else None
