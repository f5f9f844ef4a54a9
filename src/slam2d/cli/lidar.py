"""Laser-log glue for ``slam2d run`` (CARMEN logs as ``Log``s, ``--trajectory``, ``--map``, relation errors) and
``slam2d lidar``, a thin alias of ``slam2d run --estimator lidar``."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from slam2d.cli.common import add_force_argument, dataset_options
from slam2d.io.atomic import atomic_path, atomic_write
from slam2d.log import Log

if TYPE_CHECKING:
    from slam2d.eval.relations import Relations
    from slam2d.io.carmen import CarmenConfig


def register(sub: Any) -> None:
    p = sub.add_parser("lidar", help="2D lidar SLAM on a CARMEN log (alias of 'run --estimator lidar')",
                       description="Lidar SLAM (the 'lidar' estimator) over a CARMEN .clf log or a Radish log name; "
                                   "writes the occupancy map as PNG, optionally the TUM trajectory and, when a "
                                   "<log>.relations file sits next to the log, the Kümmerle et al. relation errors.")
    p.add_argument("--dataset", required=True,
                   help="aces, intel, fr079, mit-csail (under the data directory's radish-laser-logs) or a path to "
                        "a .clf/.clf.bz2 file")
    p.add_argument("--out", default=None, help="occupancy map PNG (default <log>_map.png)")
    p.add_argument("--trajectory", default=None, metavar="OUT.txt", help="TUM trajectory with the log's stamps")
    p.add_argument("--resolution", type=float, default=0.05, help="map cell size in m (default 0.05)")
    p.add_argument("--no-loops", action="store_true", help="scan-matching odometry only (no loop closure)")
    p.add_argument("--relations", default=None, help="relations file (default: <log>.relations if present)")
    p.add_argument("--path", action="store_true", help="draw the estimated trajectory on the map")
    p.add_argument("--data-dir", default=None, help="directory holding the dataset folders (overrides SLAM2D_DATA)")
    p.add_argument("--dataset-opt", action="append", default=[], metavar="KEY=VALUE",
                   help="a CARMEN reader option (repeatable): max_range_m=30, on_error=skip, backwards_stamps=skip, "
                        "max_lines=N")
    p.add_argument("--json", default=None, metavar="OUT", help="write the result record as JSON")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a LidarSLAMConfig field (repeatable), e.g. --set keyframe_distance_m=0.2")
    add_force_argument(p)
    p.set_defaults(func=cmd)


def carmen_config(options: Mapping[str, Any] | None = None) -> CarmenConfig:
    """A :class:`CarmenConfig` from loader options (``--dataset-opt KEY=VALUE``: max_range_m=30, on_error=skip,
    backwards_stamps=skip, max_lines=N); an unknown key or a value of the wrong kind is a ValueError naming it."""
    from slam2d.config import from_dict
    from slam2d.io.carmen import CarmenConfig

    return from_dict(CarmenConfig, dict(options or {}))


def load_laser_log(name: str, data_dir: str | None = None, max_steps: int | None = None,
                   max_time_s: float | None = None, options: Mapping[str, Any] | None = None) -> Log:
    """A CARMEN log (Radish name or path) as a ``Log``; its metadata keep the file path and original stamps.

    ``options`` set :class:`CarmenConfig` fields (see :func:`carmen_config`). A cut (``max_steps``, ``max_time_s``
    seconds after the first scan) that leaves no step is a ValueError, never the whole log."""
    from slam2d.io.carmen import read_carmen, resolve_carmen

    log = read_carmen(resolve_carmen(name, data_dir), carmen_config(options)).to_log()
    steps = log.num_steps
    if max_time_s is not None:
        steps = min(steps, int(np.searchsorted(log.stamps_s, max_time_s, side="right")) - 1)
    if max_steps is not None:
        steps = min(steps, int(max_steps))
    if steps < 1:
        raise ValueError(f"{log.metadata['path']}: the requested cut (max_steps={max_steps}, max_time_s={max_time_s}) "
                         f"leaves no step: the second scan is {log.stamps_s[1]:.6g} s after the first")
    return log.head(steps) if steps < log.num_steps else log


def find_relations(log_path: str | Path | None, relations: str | Path | None = None) -> Path | None:
    """The relations file to score against: ``relations`` if given, else ``<log>.relations`` beside the log."""
    from slam2d.io.carmen import relations_beside

    if relations:
        return Path(relations)
    return relations_beside(log_path) if log_path is not None else None


def load_relations(log: Log, relations: str | Path | None = None) -> Relations | None:
    """The relations of :func:`find_relations`, read now: a missing or malformed file fails before the (minutes of)
    SLAM, not after them."""
    from slam2d.eval.relations import read_relations

    path = find_relations(log.metadata.get("path"), relations)
    return read_relations(path) if path is not None else None


@contextlib.contextmanager
def _naming(option: str, path: str | Path) -> Iterator[None]:
    """An OSError without a file name (ENOSPC writing /dev/full) names the option and path."""
    try:
        yield
    except OSError as e:
        if e.filename is None and e.errno is not None:
            raise type(e)(e.errno, e.strerror or str(e), f"{option} {path}") from e
        raise


#: what each counted problem of a CARMEN log means, for the note the commands print
_LOG_PROBLEMS = (("skipped_lines", "lines skipped (malformed, or a scan with no usable beam)"),
                 ("invalid_beams", "NaN/inf/negative ranges read as no return"),
                 ("backwards_stamps", "scans whose timestamp goes backwards, kept in file order"))


def report_log_problems(log: Log) -> dict[str, Any]:
    """Print one note per kind of problem the CARMEN reader counted (with its first file:line), and one for record
    types it does not use, to stderr; returns the counts for the result record: a skip is counted and named, never
    silent."""
    examples = log.metadata.get("problem_examples", {})
    counts: dict[str, Any] = {}
    for key, what in _LOG_PROBLEMS:
        counts[f"log_{key}"] = n = int(log.metadata.get(key, 0))
        if n:
            first = examples.get(key) or [""]
            print(f"slam2d: note: {what}: {n}; first: {first[0]}", file=sys.stderr)
    counts["log_unknown_records"] = unknown = dict(log.metadata.get("unknown_records", {}))
    if unknown:
        kinds = ", ".join(f"{k} x{v}" for k, v in sorted(unknown.items()))
        print(f"slam2d: note: record types this reader does not use, ignored: {kinds}", file=sys.stderr)
    return counts


def original_stamps(log: Log) -> np.ndarray:
    """The stamps of poses 0..T as the source wrote them (CARMEN ipc timestamps), else the log's own."""
    st = log.metadata.get("stamps_original_s")
    return np.asarray(st[: log.num_steps + 1] if st is not None else log.stamps_s, dtype=np.float64)


def write_tum_stamped(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """A TUM file whose stamps are written as the shortest text that reads back as the same float (so a CARMEN
    stamp ``976052896.784509`` stays ``976052896.784509`` and matches the relations files by string too); written
    crash-safely (a temporary file, then a rename)."""
    from slam2d.io.tum import poses_to_tum

    rows = poses_to_tum(stamps, poses)
    with atomic_write(path) as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        f.writelines(f"{float(r[0])!r} " + " ".join(f"{v:.9g}" for v in r[1:]) + "\n" for r in rows)


def laser_outputs(log: Log, trajectory: np.ndarray, record: dict[str, Any], *, trajectory_out: str | None = None,
                  map_out: str | None = None, resolution_m: float = 0.05, relations: str | Relations | None = None,
                  draw_path: bool = False) -> None:
    """Write the TUM trajectory / occupancy map PNG and add relation errors (mean +- std, trans and rot) of the
    estimate and of the logged odometry to ``record`` when a relations file (or :func:`load_relations`'s result) is
    given or sits beside the log. The map is built before anything is written: a map that cannot be built leaves
    no trajectory file behind."""
    from slam2d.eval.relations import Relations, relation_errors
    from slam2d.geometry import se2

    stamps = original_stamps(log)
    grid = None
    if map_out:
        if log.scan_ranges_m is None or log.scan_angles_rad is None or log.scan_step is None:
            raise ValueError("--map needs a log with lidar scans")
        from slam2d.maps.occupancy import grid_from_scans

        grid = grid_from_scans(trajectory[log.scan_step], log.scan_ranges_m, log.scan_angles_rad,
                               log.scan_max_range_m, resolution_m=resolution_m)
    rel = relations if isinstance(relations, Relations) else load_relations(log, relations)
    if trajectory_out:
        with _naming("--trajectory", trajectory_out):
            write_tum_stamped(trajectory_out, stamps, trajectory)
        record["trajectory_file"] = str(trajectory_out)
    if map_out and grid is not None:
        from slam2d.viz.maps import save_occupancy_png

        with _naming("--map", map_out), atomic_path(map_out) as tmp:
            save_occupancy_png(grid, tmp, trajectory if draw_path else None)
        record["map"] = str(map_out)
        record["map_cells"] = f"{grid.shape[1]}x{grid.shape[0]}"
    if rel is None:
        return
    odo = se2.compose_chain(log.initial_pose, log.odometry)
    for label, poses in (("rel", trajectory), ("odometry_rel", odo)):
        errors = relation_errors(stamps, poses, rel, on_missing="skip")
        skipped, e = errors.skipped, errors.summary()
        record.update({f"{label}_{k}": v for k, v in e.items() if k in ("trans_mean_m", "trans_std_m",
                                                                       "rot_mean_deg", "rot_std_deg")})
    record["relations"] = len(rel)
    record["relations_used"] = int(len(rel) - e["missing"])
    record["relations_file"] = rel.path
    if e["missing"]:  # a prefix of the log (--max-steps), or a relations file of another log
        print(f"slam2d: note: {int(e['missing'])} of {len(rel)} relations name stamps the estimate has no pose "
              f"for, left out; first: {skipped[0]}", file=sys.stderr)


def cmd(args: argparse.Namespace) -> int:
    from slam2d.cli.common import check_number, check_outputs, overrides_from, print_table, write_json
    from slam2d.io.carmen import resolve_carmen
    from slam2d.lab.runner import run_named

    # everything that can be checked is checked before the (minutes of) SLAM
    check_number("--resolution", args.resolution, low=0.01, high=100.0)
    source = resolve_carmen(args.dataset, args.data_dir)
    if Path(source).is_dir():
        raise IsADirectoryError(21, "is a directory, not a CARMEN log", str(source))
    if not Path(source).is_file():  # /dev/zero, a FIFO: never read line by line without end
        raise ValueError(f"{source}: not a regular file (a CARMEN log is a .clf or .clf.bz2 file)")
    out = args.out or f"{Path(source).name.split('.')[0]}_map.png"
    check_outputs(args, [source, find_relations(source, args.relations)],
                  [("--out", out), ("--json", args.json), ("--trajectory", args.trajectory)])
    log = load_laser_log(args.dataset, args.data_dir, options=dataset_options(args.dataset_opt))
    relations = load_relations(log, args.relations)
    problems = report_log_problems(log)
    overrides = {f"estimator.{k}": v for k, v in overrides_from(args).items()}
    if args.no_loops:
        overrides["estimator.loop_closure"] = "false"
    result, record = run_named("lidar", None, overrides=overrides, log=log, progress=None)
    record.update(problems)
    laser_outputs(log, result.trajectory, record, trajectory_out=args.trajectory, map_out=out,
                  resolution_m=args.resolution, relations=relations,
                  draw_path=args.path)
    cols = ["scenario", "steps", "rel_trans_mean_m", "rel_trans_std_m", "rel_rot_mean_deg", "rel_rot_std_deg",
            "odometry_rel_trans_mean_m", "step_ms_mean", "step_ms_p99", "map"]
    print_table([record], [c for c in cols if c in record])
    if args.json:
        write_json(args.json, record)
    return 0
