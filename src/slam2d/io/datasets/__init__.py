"""Dataset loaders: real logs turned into the same :class:`slam2d.log.Log` the simulator produces.

``load_dataset(name, path=None, robot=1, **opts)`` is the one entry point used by the CLI and the lab; ``DATASETS``
lists what is known, ``data_dir()`` says where the staged copies are looked for (``$SLAM2D_DATA``, else
``../shared/datasets`` next to the current directory or the repository), ``dataset_status`` what is present.

Conventions shared by every loader: odometry is the relative pose ``[dx, dy, dtheta]`` from pose t-1 to pose t in
the frame of pose t-1; pose 0 is the start (no measurements are attached to it); observations are sorted by step;
``metadata`` has ``source='dataset'``, ``dataset``, ``measurement`` and ``motion`` / ``sensor`` dicts named like
:class:`~slam2d.models.motion.MotionNoise` / :class:`~slam2d.models.sensors.SensorConfig` fields (fitted against
ground truth where there is one; how is recorded in ``metadata['noise_estimate']``).
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, overload

from slam2d.io.datasets._common import DatasetFormatError
from slam2d.io.datasets.mrclam import load_mrclam, load_mrclam_all
from slam2d.io.datasets.plaza import load_plaza
from slam2d.io.datasets.victoria import load_victoria
from slam2d.log import Log
from slam2d.multi_log import MultiRobotLog

__all__ = ["DATASETS", "DatasetFormatError", "DatasetInfo", "data_dir", "dataset_status", "load_dataset",
           "load_mrclam", "load_mrclam_all", "load_plaza", "load_victoria", "loader_options"]


@dataclass(frozen=True)
class DatasetInfo:
    """A known dataset: its folder name under the data directory, the files a loader needs, and its loader."""

    name: str
    folder: str
    description: str
    files: tuple[str, ...]
    loader: Callable[..., Log]
    has_robots: bool = False


def _mrclam(path: Path, robot: int, **opts: Any) -> Log:
    return load_mrclam(path, robot, **opts)


def _plaza(name: str) -> Callable[..., Log]:
    def load(path: Path, robot: int, **opts: Any) -> Log:
        return load_plaza(path, name, **opts)

    return load


def _victoria(path: Path, robot: int, **opts: Any) -> Log:
    return load_victoria(path, **opts)


_MRCLAM_FILES = ("Barcodes.dat", "Landmark_Groundtruth.dat",
                 *(f"Robot{k}_{kind}.dat" for k in range(1, 6) for kind in ("Odometry", "Measurement", "Groundtruth")))

DATASETS: dict[str, DatasetInfo] = {
    "mrclam": DatasetInfo(
        "mrclam", "utias-mrclam-7",
        "UTIAS MRCLAM (indoor, 5 robots, 15 barcoded landmarks, range-bearing, motion-capture truth)",
        _MRCLAM_FILES, _mrclam, has_robots=True),
    "victoria-park": DatasetInfo(
        "victoria-park", "victoria-park",
        "Victoria Park raw (outdoor car, Ackermann odometry, tree detections, unknown association, GPS)",
        ("raw/odometry_aa3_dr.csv", "raw/tree_detections.csv", "raw/laser_scan_times.csv", "raw/gps_aa3_gpsx.csv"),
        _victoria),
    "plaza1": DatasetInfo(
        "plaza1", "plaza-range-only", "CMU Plaza1 range-only (4 UWB beacons, GPS truth, 1933 s)",
        ("Plaza1_DR.txt", "Plaza1_TD.txt", "Plaza1_TL.txt", "Plaza1_GT.txt"), _plaza("Plaza1")),
    "plaza2": DatasetInfo(
        "plaza2", "plaza-range-only", "CMU Plaza2 range-only (4 UWB beacons, GPS truth, 410 s)",
        ("Plaza2_DR.txt", "Plaza2_TD.txt", "Plaza2_TL.txt", "Plaza2_GT.txt"), _plaza("Plaza2")),
}

_ALIASES = {"victoria": "victoria-park", "utias": "mrclam", "mrclam7": "mrclam"}

_REPO_ROOT = Path(__file__).resolve().parents[4]


def data_dir(override: str | Path | None = None) -> tuple[Path, str]:
    """Where datasets are looked for, and why: ``override``, else ``$SLAM2D_DATA``, else the first existing of
    ``./../shared/datasets`` and ``<repo>/../shared/datasets`` (the repository layout), else the latter."""
    if override is not None:
        return Path(override), "--data-dir"
    env = os.environ.get("SLAM2D_DATA")
    if env:
        return Path(env), "SLAM2D_DATA"
    candidates = [Path.cwd().parent / "shared" / "datasets", _REPO_ROOT.parent / "shared" / "datasets"]
    for c in candidates:
        if c.is_dir():
            return c, "default"
    return candidates[-1], "default (absent)"


def resolve_name(name: str) -> DatasetInfo:
    """The :class:`DatasetInfo` for ``name`` (case-insensitive, a few aliases); ValueError listing the valid ones."""
    key = _ALIASES.get(name.lower(), name.lower())
    if key not in DATASETS:
        raise ValueError(f"unknown dataset {name!r}; valid datasets: {sorted(DATASETS)}")
    return DATASETS[key]


def dataset_status(name: str, root: str | Path | None = None) -> tuple[Path, list[str]]:
    """(folder, missing files) of dataset ``name`` under the data directory ``root`` (default :func:`data_dir`)."""
    info = resolve_name(name)
    folder = (Path(root) if root is not None else data_dir()[0]) / info.folder
    return folder, [f for f in info.files if not (folder / f).is_file()]


def loader_options(name: str) -> list[str]:
    """Keyword options the loader of dataset ``name`` accepts (``max_steps``, ``max_time_s``, ...)."""
    loaders: dict[str, Callable[..., Log]] = {"mrclam": load_mrclam, "victoria-park": load_victoria,
                                              "plaza1": load_plaza, "plaza2": load_plaza}
    fn = loaders[resolve_name(name).name]
    return [p.name for p in inspect.signature(fn).parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY]


@overload
def load_dataset(name: str, path: str | Path | None = None, robot: int = 1, *,
                 data_dir_override: str | Path | None = None, **opts: Any) -> Log: ...


@overload
def load_dataset(name: str, path: str | Path | None = None, *, robot: Literal["all"],
                 data_dir_override: str | Path | None = None, **opts: Any) -> MultiRobotLog: ...


def load_dataset(name: str, path: str | Path | None = None, robot: int | str = 1, *,
                 data_dir_override: str | Path | None = None, **opts: Any) -> Log | MultiRobotLog:
    """Load dataset ``name`` as a :class:`Log` (or, with ``robot="all"``, a :class:`MultiRobotLog`).

    ``path`` points the loader at any folder in that dataset's format (e.g. another ``MRCLAM_DatasetN``); by default
    the staged copy under :func:`data_dir` is used. ``robot`` selects the MRCLAM robot (1..5, or ``"all"`` for every
    robot on one clock with their sightings of each other, :func:`load_mrclam_all`; other datasets have one vehicle
    and reject robot != 1). ``opts`` go to the loader (see :func:`loader_options`), e.g. ``max_steps``,
    ``max_time_s``; an unknown option raises ValueError listing the valid ones.
    """
    info = resolve_name(name)
    valid = loader_options(info.name)
    bad = sorted(set(opts) - set(valid))
    if bad:
        raise ValueError(f"unknown option(s) {bad} for dataset {info.name!r}; valid options: {valid}")
    if isinstance(robot, str) and robot != "all":
        raise ValueError(f"robot must be an integer or 'all' (got {robot!r})")
    if not info.has_robots and robot != 1:
        raise ValueError(f"dataset {info.name!r} has a single vehicle; --robot/robot applies to mrclam only")
    folder = Path(path) if path is not None else data_dir(data_dir_override)[0] / info.folder
    if not folder.is_dir():
        raise DatasetFormatError(f"{folder}: dataset folder for {info.name!r} not found (set SLAM2D_DATA, "
                                 "--data-dir or --dataset-path)")
    if robot == "all":
        return load_mrclam_all(folder, **opts)
    return info.loader(folder, int(robot), **opts)
