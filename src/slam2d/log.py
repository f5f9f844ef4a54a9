"""``Log``: the one contract between data sources (simulator, dataset loaders) and estimators.

A log holds T steps. Step ``t`` (1..T) is the motion from pose ``t-1`` to pose ``t`` reported by odometry, followed by
the measurements taken at pose ``t``. Pose 0 is the start (``initial_pose``). Observations are stored flat, sorted by
step, so that one step's batch is a slice.

Ground truth (``true_poses``, ``true_landmarks``, ``walls``) is optional and is never handed to an estimator: the
runner passes estimators only :class:`Step` objects, which hold no truth except ``Observations.landmark_id``, the id
the data source itself reports (simulator oracle ids, or barcodes on real data). Only the ``known`` association
method reads it; the association metrics compare against it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import tempfile
import zipfile
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Observation id values that are not static landmarks.
CLUTTER_ID = -1
DYNAMIC_ID = -2


class LogFormatError(ValueError):
    """A log file is corrupt, truncated or not a slam2d log; the message names the file and the problem."""


@dataclass(frozen=True)
class Observations:
    """A batch of range-bearing observations taken at one pose.

    Shapes: range_m (K,), bearing_rad (K,), landmark_id (K,) int (-1 clutter, -2 moving object, >=0 landmark id as
    reported by the source), descriptor (K, D) or None.
    """

    range_m: Array
    bearing_rad: Array
    landmark_id: IntArray
    descriptor: Array | None = None

    def __len__(self) -> int:
        return int(self.range_m.shape[0])

    @property
    def z(self) -> Array:
        """(K, 2) array of [range, bearing]."""
        return np.stack([self.range_m, self.bearing_rad], axis=-1)

    def subset(self, mask: NDArray[np.bool_] | IntArray) -> Observations:
        return Observations(
            self.range_m[mask],
            self.bearing_rad[mask],
            self.landmark_id[mask],
            None if self.descriptor is None else self.descriptor[mask],
        )


@dataclass(frozen=True)
class Scan:
    """One lidar scan. Shapes: ranges_m (B,), angles_rad (B,) in the robot frame; max_range_m marks no return."""

    ranges_m: Array
    angles_rad: Array
    max_range_m: float


@dataclass(frozen=True)
class MarkerReadings:
    """Floor markers read by the downward camera at one pose. Shapes: xy_m (K,2) in the robot frame, ids (K,) int."""

    xy_m: Array
    ids: IntArray

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True)
class Step:
    """Everything an estimator may see at step ``index``: odometry and the measurements at the new pose.

    ``odometry`` is the measured relative motion [dx, dy, dtheta] from pose index-1 to pose index, in the frame of
    pose index-1. ``gps`` is a measured [x, y] or None. ``scan`` is a lidar scan or None. ``markers`` holds the
    floor-marker readings of this step (possibly none) when the source has a floor camera, else None.
    """

    index: int
    time_s: float
    dt_s: float
    odometry: Array
    observations: Observations
    gps: Array | None = None
    scan: Scan | None = None
    markers: MarkerReadings | None = None


_ARRAY_FIELDS = (
    "stamps_s",
    "odometry",
    "obs_step",
    "obs_range_m",
    "obs_bearing_rad",
    "obs_id",
    "obs_descriptor",
    "true_poses",
    "true_landmarks",
    "true_landmark_ids",
    "walls",
    "gps_step",
    "gps_xy",
    "scan_step",
    "scan_ranges_m",
    "scan_angles_rad",
    "dynamic_xy",
    "marker_step",
    "marker_xy_m",
    "marker_id",
    "true_markers",
)


@dataclass(frozen=True, eq=False)
class Log:
    """A recorded run: odometry and observations per step, optional ground truth, and metadata.

    Shapes (T steps, K observations, N landmarks, W walls, G gps fixes, S scans, B beams):
    stamps_s (T+1,), odometry (T,3), obs_step (K,) int sorted, obs_range_m (K,), obs_bearing_rad (K,), obs_id (K,) int,
    obs_descriptor (K,D) or None, true_poses (T+1,3) or None, true_landmarks (N,2) or None, true_landmark_ids (N,)
    or None, walls (W,4) [x0,y0,x1,y1] or None, gps_step (G,), gps_xy (G,2), scan_step (S,), scan_ranges_m (S,B),
    scan_angles_rad (B,), dynamic_xy (T+1,M,2) true positions of moving objects or None. Floor-marker readings
    (R of them, optional together): marker_step (R,) int sorted, marker_xy_m (R,2) robot frame, marker_id (R,) int;
    true_markers (N_m,2) marker ``i`` has id ``i``.
    ``metadata`` is JSON-serialisable: seed, scenario, config, sensor parameters, units, source.
    """

    stamps_s: Array
    odometry: Array
    obs_step: IntArray
    obs_range_m: Array
    obs_bearing_rad: Array
    obs_id: IntArray
    initial_pose: Array = field(default_factory=lambda: np.zeros(3))
    obs_descriptor: Array | None = None
    true_poses: Array | None = None
    true_landmarks: Array | None = None
    true_landmark_ids: IntArray | None = None
    walls: Array | None = None
    gps_step: IntArray | None = None
    gps_xy: Array | None = None
    scan_step: IntArray | None = None
    scan_ranges_m: Array | None = None
    scan_angles_rad: Array | None = None
    scan_max_range_m: float = 0.0
    dynamic_xy: Array | None = None
    marker_step: IntArray | None = None
    marker_xy_m: Array | None = None
    marker_id: IntArray | None = None
    true_markers: Array | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        arrays = {n: getattr(self, n) for n in (*_ARRAY_FIELDS, "initial_pose") if getattr(self, n) is not None}
        for n, a in arrays.items():
            if not isinstance(a, np.ndarray):
                arrays[n] = np.asarray(a)
        if arrays["odometry"].ndim != 2 or arrays["odometry"].shape[1] != 3:
            raise ValueError(f"odometry must have shape (T, 3), got {arrays['odometry'].shape}")
        # types, shapes, finite values and cross-field consistency, as Log.load checks a file; non-finite odometry
        # is left to the runner, which names the step where it makes the pose non-finite
        problem = _check_arrays(arrays, nonfinite_ok=("odometry",))
        if problem:
            raise ValueError(f"Log: {problem}")
        for n, a in arrays.items():
            if a is not getattr(self, n):
                object.__setattr__(self, n, a)
        smr = self.scan_max_range_m
        if isinstance(smr, bool) or not isinstance(smr, int | float) or not 0 <= smr < float("inf"):
            raise ValueError(f"Log: scan_max_range_m must be a finite number >= 0, got {smr!r}")
        t = self.odometry.shape[0]
        if self.stamps_s.shape != (t + 1,):
            raise ValueError(f"stamps_s must have shape ({t + 1},), got {self.stamps_s.shape}")
        k = self.obs_step.shape[0]
        for name in ("obs_range_m", "obs_bearing_rad", "obs_id"):
            if getattr(self, name).shape != (k,):
                raise ValueError(f"{name} must have shape ({k},), got {getattr(self, name).shape}")
        if k and (np.any(np.diff(self.obs_step) < 0) or self.obs_step[0] < 0 or self.obs_step[-1] > t):
            raise ValueError("obs_step must be sorted and within [0, T]")
        if self.true_poses is not None and self.true_poses.shape != (t + 1, 3):
            raise ValueError(f"true_poses must have shape ({t + 1}, 3), got {self.true_poses.shape}")
        # offsets so that a step's observations are one slice: obs[starts[t]:starts[t+1]]
        object.__setattr__(self, "_obs_starts", np.searchsorted(self.obs_step, np.arange(t + 2)))
        if self.gps_step is not None:
            object.__setattr__(self, "_gps_index", {int(s): i for i, s in enumerate(self.gps_step)})
        if self.scan_step is not None:
            object.__setattr__(self, "_scan_index", {int(s): i for i, s in enumerate(self.scan_step)})
        m_step, m_xy, m_id = self.marker_step, self.marker_xy_m, self.marker_id
        if m_step is not None or m_xy is not None or m_id is not None:
            if m_step is None or m_xy is None or m_id is None:
                raise ValueError("marker_step, marker_xy_m and marker_id must be given together")
            r = m_step.shape[0]
            if m_xy.shape != (r, 2) or m_id.shape != (r,):
                raise ValueError(f"marker_xy_m must have shape ({r}, 2) and marker_id ({r},)")
            if r and np.any(np.diff(m_step) < 0):
                raise ValueError("marker_step must be sorted")
            object.__setattr__(self, "_marker_starts", np.searchsorted(m_step, np.arange(t + 2)))

    # ------------------------------------------------------------------ access
    @property
    def num_steps(self) -> int:
        return int(self.odometry.shape[0])

    def __len__(self) -> int:
        return self.num_steps

    def observations_at(self, index: int) -> Observations:
        """Observations taken at pose ``index`` (0..T)."""
        starts = self._obs_starts  # type: ignore[attr-defined]
        sl = slice(int(starts[index]), int(starts[index + 1]))
        return Observations(
            self.obs_range_m[sl],
            self.obs_bearing_rad[sl],
            self.obs_id[sl],
            None if self.obs_descriptor is None else self.obs_descriptor[sl],
        )

    def step(self, index: int) -> Step:
        """The estimator-facing record of step ``index`` (1..T)."""
        if not 1 <= index <= self.num_steps:
            raise IndexError(f"step index {index} out of range 1..{self.num_steps}")
        gps = None
        if self.gps_step is not None and self.gps_xy is not None:
            i = self._gps_index.get(index)  # type: ignore[attr-defined]
            gps = None if i is None else self.gps_xy[i]
        scan = None
        if self.scan_step is not None and self.scan_ranges_m is not None and self.scan_angles_rad is not None:
            i = self._scan_index.get(index)  # type: ignore[attr-defined]
            if i is not None:
                scan = Scan(self.scan_ranges_m[i], self.scan_angles_rad, self.scan_max_range_m)
        markers = None
        if self.marker_step is not None and self.marker_xy_m is not None and self.marker_id is not None:
            starts = self._marker_starts  # type: ignore[attr-defined]
            sl = slice(int(starts[index]), int(starts[index + 1]))
            markers = MarkerReadings(self.marker_xy_m[sl], self.marker_id[sl])
        return Step(
            index=index,
            time_s=float(self.stamps_s[index]),
            dt_s=float(self.stamps_s[index] - self.stamps_s[index - 1]),
            odometry=self.odometry[index - 1],
            observations=self.observations_at(index),
            gps=gps,
            scan=scan,
            markers=markers,
        )

    def __iter__(self) -> Iterator[Step]:
        for i in range(1, self.num_steps + 1):
            yield self.step(i)

    def head(self, steps: int) -> Log:
        """The first ``steps`` steps of this log (a new Log)."""
        steps = min(steps, self.num_steps)
        k = int(self._obs_starts[steps + 1])  # type: ignore[attr-defined]

        def cut(arr: Any, idx: Any, n: int) -> Any:
            return None if arr is None else arr[idx(n)]

        keep_g = None if self.gps_step is None else self.gps_step <= steps
        keep_s = None if self.scan_step is None else self.scan_step <= steps
        keep_m = None if self.marker_step is None else self.marker_step <= steps
        return dataclasses.replace(
            self,
            stamps_s=self.stamps_s[: steps + 1],
            odometry=self.odometry[:steps],
            obs_step=self.obs_step[:k],
            obs_range_m=self.obs_range_m[:k],
            obs_bearing_rad=self.obs_bearing_rad[:k],
            obs_id=self.obs_id[:k],
            obs_descriptor=cut(self.obs_descriptor, lambda n: slice(0, n), k),
            true_poses=cut(self.true_poses, lambda n: slice(0, n), steps + 1),
            gps_step=None if keep_g is None else self.gps_step[keep_g],  # type: ignore[index]
            gps_xy=None if keep_g is None or self.gps_xy is None else self.gps_xy[keep_g],
            scan_step=None if keep_s is None else self.scan_step[keep_s],  # type: ignore[index]
            scan_ranges_m=None if keep_s is None or self.scan_ranges_m is None else self.scan_ranges_m[keep_s],
            dynamic_xy=cut(self.dynamic_xy, lambda n: slice(0, n), steps + 1),
            marker_step=None if keep_m is None else self.marker_step[keep_m],  # type: ignore[index]
            marker_xy_m=None if keep_m is None else self.marker_xy_m[keep_m],  # type: ignore[index]
            marker_id=None if keep_m is None else self.marker_id[keep_m],  # type: ignore[index]
        )

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> Path:
        """Write the log as an ``.npz`` archive holding the arrays plus ``metadata.json``. Written to a temporary
        file beside ``path`` and renamed, so a failed save never leaves a truncated log. Returns the path."""
        target = Path(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                self.write_npz(fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o644)
            os.replace(tmp, target)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
        return target

    def write_npz(self, fh: IO[bytes]) -> None:
        """Write the archive into an open binary file (the CLI wraps it in ``slam2d.io.atomic.atomic_write``)."""
        arrays = {n: getattr(self, n) for n in _ARRAY_FIELDS if getattr(self, n) is not None}
        arrays["initial_pose"] = self.initial_pose
        meta = {"format": "slam2d-log", "version": 1, "scan_max_range_m": self.scan_max_range_m,
                "metadata": dict(self.metadata)}
        with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for name, arr in arrays.items():
                buf = io.BytesIO()
                np.save(buf, np.asarray(arr), allow_pickle=False)
                zf.writestr(name + ".npy", buf.getvalue())
            zf.writestr("metadata.json", json.dumps(meta, sort_keys=True))

    @classmethod
    def load(cls, path: str | Path) -> Log:
        """Read a log written by :meth:`save`; raises only :class:`LogFormatError` naming the file and the problem
        (a missing, special or oversized file, a corrupt archive, wrong array types or shapes, non-finite values)."""
        path = Path(path)
        if not path.exists():
            raise LogFormatError(f"{path}: no such file")
        if not path.is_file():
            raise LogFormatError(f"{path}: not a slam2d log (a directory or a special file)")
        limit = _max_log_bytes()
        try:
            zf = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, OSError, ValueError, EOFError, OverflowError) as e:
            raise LogFormatError(f"{path}: not a slam2d log (corrupt or truncated archive: {e})") from None
        try:
            with zf:
                infos = {i.filename: i for i in zf.infolist()}
                if sum(i.file_size for i in infos.values()) > limit:
                    raise LogFormatError(f"{path}: archive expands to more than {limit / 2**20:g} MB "
                                         f"(set {MAX_LOG_ENV} to read it)")
                if "metadata.json" not in infos:
                    raise LogFormatError(f"{path}: not a slam2d log (metadata.json missing)")
                meta = json.loads(zf.read("metadata.json"))
                if not isinstance(meta, dict) or meta.get("format") != "slam2d-log":
                    tag = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
                    raise LogFormatError(f"{path}: not a slam2d log (format tag {tag!r})")
                arrays: dict[str, Any] = {}
                for n in (*_ARRAY_FIELDS, "initial_pose"):
                    if n + ".npy" in infos:
                        arrays[n] = np.load(io.BytesIO(zf.read(n + ".npy")), allow_pickle=False)
        except LogFormatError:
            raise
        except RecursionError:
            raise LogFormatError(f"{path}: corrupt slam2d log (metadata.json nested too deeply)") from None
        except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError, TypeError, OverflowError,
                NotImplementedError, RuntimeError, zlib.error, MemoryError) as e:
            raise LogFormatError(f"{path}: corrupt slam2d log ({type(e).__name__}: {e})") from None
        missing = [n for n in ("stamps_s", "odometry", "obs_step", "obs_range_m", "obs_bearing_rad", "obs_id")
                   if n not in arrays]
        if missing:
            raise LogFormatError(f"{path}: corrupt slam2d log (missing arrays {missing})")
        problem = _check_arrays(arrays)
        if problem:
            raise LogFormatError(f"{path}: corrupt slam2d log ({problem})")
        smr = meta.get("scan_max_range_m", 0.0)
        if isinstance(smr, bool) or not isinstance(smr, int | float) or not (0 <= smr < float("inf")):
            raise LogFormatError(f"{path}: corrupt slam2d log (scan_max_range_m must be a finite number >= 0, "
                                 f"got {smr!r})")
        metadata = meta.get("metadata", {})
        if not isinstance(metadata, dict):
            raise LogFormatError(f"{path}: corrupt slam2d log (metadata must be a JSON object)")
        try:
            return cls(**arrays, scan_max_range_m=float(smr), metadata=metadata)
        except (ValueError, TypeError, IndexError, OverflowError) as e:
            raise LogFormatError(f"{path}: inconsistent slam2d log ({e})") from None

    def equals(self, other: Log) -> bool:
        """Exact (bit-identical) equality of every array and the metadata."""
        for n in (*_ARRAY_FIELDS, "initial_pose"):
            a, b = getattr(self, n), getattr(other, n)
            if (a is None) != (b is None):
                return False
            if a is not None and not (a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b)):
                return False
        return json.dumps(dict(self.metadata), sort_keys=True) == json.dumps(dict(other.metadata), sort_keys=True)


MAX_LOG_ENV = "SLAM2D_MAX_FILE_MB"


def _max_log_bytes() -> int:
    """The size cap of a log archive (uncompressed): ``SLAM2D_MAX_FILE_MB`` (default 2048 MB), as for text inputs."""
    raw = os.environ.get(MAX_LOG_ENV, "")
    try:
        mb = float(raw) if raw else 2048.0
    except ValueError:
        mb = 2048.0
    return int(mb * 2**20)


#: kind ("f" float, "i" integer) and number of dimensions of every stored array; None = any float finite check off
_ARRAY_KINDS: dict[str, tuple[str, int, bool]] = {
    "stamps_s": ("f", 1, True), "odometry": ("f", 2, True), "obs_step": ("i", 1, True),
    "obs_range_m": ("f", 1, False), "obs_bearing_rad": ("f", 1, False), "obs_id": ("i", 1, True),
    "obs_descriptor": ("f", 2, False), "true_poses": ("f", 2, True), "true_landmarks": ("f", 2, True),
    "true_landmark_ids": ("i", 1, True), "walls": ("f", 2, True), "gps_step": ("i", 1, True),
    "gps_xy": ("f", 2, True), "scan_step": ("i", 1, True), "scan_ranges_m": ("f", 2, False),
    "scan_angles_rad": ("f", 1, True), "dynamic_xy": ("f", 3, False), "initial_pose": ("f", 1, True),
    "marker_step": ("i", 1, True), "marker_xy_m": ("f", 2, True), "marker_id": ("i", 1, True),
    "true_markers": ("f", 2, True),
}


def _check_arrays(arrays: dict[str, Any], nonfinite_ok: tuple[str, ...] = ()) -> str | None:
    """What is wrong with the arrays' types, shapes and values (None when they are usable); converts them in place
    to float64 / int64 (without a copy when they already are). ``nonfinite_ok`` names arrays exempt from the finite
    check."""
    for n, a in arrays.items():
        kind, ndim, finite = _ARRAY_KINDS[n]
        if not isinstance(a, np.ndarray) or a.dtype.kind not in ("iu" if kind == "i" else "fiu"):
            return f"{n} must be {'an integer' if kind == 'i' else 'a numeric'} array, got {getattr(a, 'dtype', a)}"
        if a.ndim != ndim:
            return f"{n} must have {ndim} dimension(s), got shape {a.shape}"
        arrays[n] = a = a.astype(np.int64 if kind == "i" else np.float64, copy=False)
        if finite and kind == "f" and n not in nonfinite_ok and not np.all(np.isfinite(a)):
            return f"{n} has non-finite values"
    stamps = arrays["stamps_s"]
    if stamps.size > 1 and np.any(np.diff(stamps) < 0):
        i = int(np.flatnonzero(np.diff(stamps) < 0)[0]) + 1
        return (f"stamps_s must be non-decreasing (stamps_s[{i}] = {float(stamps[i])} < "
                f"stamps_s[{i - 1}] = {float(stamps[i - 1])})")
    for n in ("gps_step", "scan_step"):
        if n in arrays and np.unique(arrays[n]).size != arrays[n].size:
            return f"{n} has repeated steps (at most one per step)"
    t = arrays["odometry"].shape[0]
    checks = [
        ("initial_pose", lambda a: a.shape == (3,)),
        ("obs_descriptor", lambda a: a.shape[0] == arrays["obs_step"].shape[0]),
        ("true_landmarks", lambda a: a.shape[1] == 2),
        ("walls", lambda a: a.shape[1] == 4),
        ("gps_step", lambda a: a.size == 0 or (a.min() >= 0 and a.max() <= t)),
        ("gps_xy", lambda a: a.shape == (arrays.get("gps_step", np.zeros(0)).shape[0], 2)),
        ("scan_step", lambda a: a.size == 0 or (a.min() >= 0 and a.max() <= t)),
        ("scan_ranges_m", lambda a: a.shape == (arrays.get("scan_step", np.zeros(0)).shape[0],
                                               arrays.get("scan_angles_rad", np.zeros(0)).shape[0])),
        ("dynamic_xy", lambda a: a.shape[0] == t + 1 and a.shape[2] == 2),
        ("true_landmark_ids", lambda a: a.shape[0] == arrays.get("true_landmarks", np.zeros((a.shape[0], 2))).shape[0]),
        ("marker_step", lambda a: a.size == 0 or (a.min() >= 0 and a.max() <= t)),
        ("true_markers", lambda a: a.shape[1] == 2),
    ]
    for n, ok in checks:
        if n in arrays and not ok(arrays[n]):
            return f"{n} has an inconsistent shape {arrays[n].shape} or values out of range"
    if ("gps_step" in arrays) != ("gps_xy" in arrays) or ("scan_step" in arrays) != ("scan_ranges_m" in arrays):
        return "gps_step/gps_xy or scan_step/scan_ranges_m given without their partner"
    return None
