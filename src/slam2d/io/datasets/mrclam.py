"""UTIAS MRCLAM loader (Leung, Halpern, Barfoot, Liu, IJRR 2011): any ``MRCLAM_DatasetN`` folder, any robot 1..5.

Files (whitespace separated, ``#`` comment lines): ``Barcodes.dat`` (subject, barcode), ``Landmark_Groundtruth.dat``
(subject, x, y, x_std, y_std), ``RobotK_Odometry.dat`` (time, v, omega), ``RobotK_Measurement.dat`` (time, BARCODE,
range, bearing), ``RobotK_Groundtruth.dat`` (time, x, y, theta).

Step convention: pose 0 is at the first odometry time ``t0`` (or the first ground-truth time if that is later);
steps are a regular grid of ``dt_s`` (default 0.1 s) merged with every distinct measurement time (grid points
closer than ``dt_s / 4`` to a measurement time are dropped, so steps are at most 1.5 ``dt_s`` apart), so each
measurement sits exactly on its step. Odometry per step is the exact integral of the (v, omega) commands held
piecewise constant (zero-order hold from each record to the next) between the two step times, as
``[dx, dy, dtheta]`` in the frame of the earlier pose. The run ends at the last odometry or ground-truth time,
whichever is first. Ground truth is the motion-capture pose linearly interpolated (unwrapped heading) at each step.
Measurements at or before ``t0`` are dropped (pose 0 is never updated by an estimator).

Timing: the logged times are shifted onto the motion-capture clock by the measured latencies (see
:data:`ODOMETRY_DELAY_S`, :data:`CAMERA_DELAY_S`): odometry commands by ``+odometry_delay_s`` (when the robot
executes them), measurements by ``-camera_delay_s`` (when the image was taken); all times above are shifted times.

Ids: landmark subjects (from Landmark_Groundtruth, 6..20 in the published sets) map to landmark ids 0..N-1 in
increasing subject order; ``metadata['landmark_subjects'][i]`` is the subject of id i. Observations of other robots
(subjects in Barcodes.dat without a landmark ground truth, i.e. 1..5) and of barcodes not in Barcodes.dat are
dropped by default; with ``others="keep"`` robots are kept as id -2 (moving object) and unknown barcodes as -1.
A few landmark measurements are misread barcodes (several metres / radians off the landmark they name); they are
kept, since an estimator must gate them, and listed in ``metadata['noise_estimate']['gross_outliers']``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.geometry.angles import angle_diff
from slam2d.io.datasets._common import (
    DatasetFormatError,
    Table,
    cap_log,
    check_integer,
    check_nondecreasing,
    content_errors,
    fit_motion_noise,
    increments,
    integrate_velocity,
    interpolate_poses,
    read_table,
    require_file,
    robust_std,
    step_grid,
)
from slam2d.log import CLUTTER_ID, DYNAMIC_ID, Log
from slam2d.models.sensors import range_bearing
from slam2d.multi_log import MultiRobotLog, RobotSightings

ROBOTS = (1, 2, 3, 4, 5)

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: longest range a measurement line may hold (m): ten times the arena's diagonal, far beyond the camera's reach (~5 m)
MAX_RANGE_M = 170.0

#: residual (in fitted standard deviations, range and bearing combined) beyond which a landmark measurement is listed
#: as a gross outlier (a misread barcode) in ``metadata['noise_estimate']['gross_outliers']``
GROSS_SIGMA = 10.0

#: latency of the robots' motion: a (v, omega) command logged at t is executed at about t + 0.2 s. Measured on
#: MRCLAM 7: the cross-correlation of the commanded and the motion-capture turn rate (0.01 s grid) peaks at a lag
#: of 0.20 s for each of the five robots (correlation 0.77-0.88); without the shift the filter's pose leads the
#: truth by 0.2 s, i.e. by ~0.1 rad while the robot turns at 0.5 rad/s.
ODOMETRY_DELAY_S = 0.2
#: latency of the camera: a measurement logged at t shows the scene at about t - 0.04 s. Measured on MRCLAM 7: the
#: spread of the bearing residuals against motion-capture truth shifted by -0.1..0 s (0.01 s steps) is smallest at
#: -0.04 s for each of the five robots (robot 5: 0.0101 rad unshifted, 0.0077 rad at -0.04 s).
CAMERA_DELAY_S = 0.04


@content_errors("MRCLAM")
def load_mrclam(path: str | Path, robot: int = 1, *, dt_s: float = 0.1, max_steps: int | None = None,
                max_time_s: float | None = None, others: str = "drop", ground_truth: bool = True,
                noise_window_s: float = 1.0, odometry_delay_s: float = ODOMETRY_DELAY_S,
                camera_delay_s: float = CAMERA_DELAY_S, sensor_fit: str = "rms") -> Log:
    """Load robot ``robot`` of the MRCLAM dataset folder ``path`` as a :class:`Log` (see the module docstring).

    ``max_steps`` / ``max_time_s`` cut the run (for fast tests; noise is still fitted on the whole run).
    ``ground_truth=False`` skips reading the motion capture file (then nothing is fitted and estimators keep their
    default noise). Noise parameters in ``metadata['motion']`` / ``metadata['sensor']`` are fitted against ground
    truth of the whole run: motion by :func:`fit_motion_noise` over windows of ``noise_window_s``, sensor as the
    zero-mean spread of the landmark measurement residuals (predicted from interpolated ground truth and surveyed
    landmarks): ``sensor_fit="rms"`` (default) is the root mean square of the residuals without the gross outliers
    (beyond ``GROSS_SIGMA`` robust standard deviations), the second moment a Kalman filter needs; ``"mad"`` the
    robust (median/MAD) spread of the Gaussian core only. The residuals are heavy-tailed (range noise grows with
    range, a few landmarks carry biases of 0.2-0.4 m): with the MAD spread 13-17 % of the measurements of robots 1, 3
    and 5 fall outside the 99 % chi-square gate of their TRUE landmark at the TRUE pose, so an estimator with unknown
    association takes correct sightings for new landmarks; the RMS is 1.1-1.6 x larger.
    ``odometry_delay_s`` / ``camera_delay_s``: latencies taken out of the logged times (module docstring).
    Shapes: the Log's (T+1,) stamps and (T,3) odometry, observations sorted by step.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise DatasetFormatError(f"{folder}: MRCLAM dataset folder not found")
    if robot not in ROBOTS:
        raise ValueError(f"robot must be one of {ROBOTS} (got {robot})")
    if not dt_s > 0:
        raise ValueError(f"dt_s must be > 0 (got {dt_s})")
    if sensor_fit not in ("rms", "mad"):
        raise ValueError(f"sensor_fit must be 'rms' or 'mad' (got {sensor_fit!r})")
    if others not in ("drop", "keep"):
        raise ValueError(f"others must be 'drop' or 'keep' (got {others!r})")

    common = _read_common(folder)
    rf = _read_robot(folder, robot, ground_truth, odometry_delay_s, camera_delay_s, common)
    t0, t1 = _span(rf)
    keep = rf.in_run(t0, t1) & ((rf.ids >= 0) | (others == "keep"))
    stamps = step_grid(t0, t1, dt_s, rf.t_meas[keep], dt_s / 4)
    log = _assemble(rf, common, keep, stamps, t1, dt_s=dt_s, others=others, noise_window_s=noise_window_s,
                    sensor_fit=sensor_fit)
    return cap_log(log, max_steps, max_time_s)


def load_mrclam_all(path: str | Path, robots: tuple[int, ...] = ROBOTS, *, dt_s: float = 0.1,
                    max_steps: int | None = None, max_time_s: float | None = None, others: str = "drop",
                    ground_truth: bool = True, noise_window_s: float = 1.0,
                    odometry_delay_s: float = ODOMETRY_DELAY_S, camera_delay_s: float = CAMERA_DELAY_S,
                    sensor_fit: str = "rms") -> MultiRobotLog:
    """Load several robots of one MRCLAM folder onto ONE clock, with their sightings of each other.

    The shared run is where every selected robot has odometry (and ground truth): from the latest start to the
    earliest end; pose 0 of every robot is at that common ``t0``. The step grid is the ``dt_s`` grid merged with the
    measurement times of ALL robots (same rule as :func:`load_mrclam`), so every landmark measurement and every
    robot-robot sighting sits exactly on a step of both robots. Each robot's :class:`Log` keeps its landmark
    observations (and unknown barcodes as clutter with ``others="keep"``), its own fitted noise and its ground
    truth; a measurement whose barcode is one of the selected robots (subjects 1..5 are the robots) becomes a row of
    :attr:`MultiRobotLog.sightings` (observer, observed, range, bearing, step). Sightings of robots that are not
    selected are dropped and counted. Options as in :func:`load_mrclam`; the cut applies to all robots alike.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise DatasetFormatError(f"{folder}: MRCLAM dataset folder not found")
    robots = tuple(int(r) for r in robots)
    if not robots or len(set(robots)) != len(robots) or any(r not in ROBOTS for r in robots):
        raise ValueError(f"robots must be distinct values of {ROBOTS} (got {robots})")
    if not dt_s > 0:
        raise ValueError(f"dt_s must be > 0 (got {dt_s})")
    if sensor_fit not in ("rms", "mad"):
        raise ValueError(f"sensor_fit must be 'rms' or 'mad' (got {sensor_fit!r})")
    if others not in ("drop", "keep"):
        raise ValueError(f"others must be 'drop' or 'keep' (got {others!r})")
    common = _read_common(folder)
    files = [_read_robot(folder, r, ground_truth, odometry_delay_s, camera_delay_s, common) for r in robots]
    spans = np.array([_span(rf) for rf in files])
    t0, t1 = float(spans[:, 0].max()), float(spans[:, 1].min())
    if t1 <= t0:
        raise DatasetFormatError(f"{folder}: the runs of robots {robots} do not overlap in time")
    keep_lm, keep_rr = [], []
    for rf in files:
        run = rf.in_run(t0, t1)
        keep_lm.append(run & ((rf.ids >= 0) | ((others == "keep") & (rf.ids == CLUTTER_ID))))
        keep_rr.append(run & (rf.ids == DYNAMIC_ID) & np.isin(rf.subj, robots))
    events = np.concatenate([rf.t_meas[a | b] for rf, a, b in zip(files, keep_lm, keep_rr, strict=True)])
    stamps = step_grid(t0, t1, dt_s, events, dt_s / 4)
    logs = tuple(_assemble(rf, common, k, stamps, t1, dt_s=dt_s, others=others, noise_window_s=noise_window_s,
                           sensor_fit=sensor_fit) for rf, k in zip(files, keep_lm, strict=True))
    parts = [(np.searchsorted(stamps, rf.t_meas[k]), np.full(int(k.sum()), rf.robot), rf.subj[k],
              rf.meas.data[k, 2], rf.meas.data[k, 3]) for rf, k in zip(files, keep_rr, strict=True)]
    cols = [np.concatenate([p[i] for p in parts]) for i in range(5)]
    order = np.argsort(cols[0], kind="stable")
    sightings = RobotSightings(cols[0][order].astype(np.int64), cols[1][order].astype(np.int64),
                               cols[2][order].astype(np.int64), cols[3][order].astype(np.float64),
                               cols[4][order].astype(np.float64))
    pairs: dict[str, int] = {}
    for a, b in zip(sightings.observer.tolist(), sightings.observed.tolist(), strict=True):
        pairs[f"{a}->{b}"] = pairs.get(f"{a}->{b}", 0) + 1
    metadata = {
        "source": "dataset", "dataset": "mrclam", "dataset_path": str(folder.resolve()), "robots": list(robots),
        "measurement": "range-bearing", "dt_s": float(dt_s), "t0_unix_s": t0, "others": others,
        "landmark_subjects": [int(s) for s in common.lm_subj],
        "counts": {"steps": int(stamps.size - 1), "sightings": len(sightings), "sightings_by_pair": pairs,
                   "sightings_of_unselected_robots": int(sum(
                       np.sum(rf.in_run(t0, t1) & (rf.ids == DYNAMIC_ID) & ~np.isin(rf.subj, robots))
                       for rf in files))},
        "units": {"length": "m", "angle": "rad", "time": "s (relative to t0_unix_s)"},
    }
    if ground_truth and len(sightings):
        metadata["sighting_noise"] = _fit_sighting_noise(logs, robots, sightings)
    multi = MultiRobotLog(robots, logs, sightings, metadata)
    steps = cap_log(logs[0], max_steps, max_time_s).num_steps
    if steps == multi.num_steps:
        return multi
    cut = multi.head(steps)
    meta = {**metadata, "cut": {"steps": steps, "of": multi.num_steps, "max_steps": max_steps,
                                "max_time_s": max_time_s}}
    return MultiRobotLog(cut.robots, cut.logs, cut.sightings, meta)


# ---------------------------------------------------------------------------------------------------- pieces
@dataclass(frozen=True)
class _Common:
    """What every robot of one dataset folder shares: barcode -> subject, landmark subjects (sorted) and positions."""

    bar_to_subj: dict[int, int]
    lm_subj: IntArray
    lm_xy: Array


@dataclass(frozen=True)
class _RobotFiles:
    """One robot's files, read and classified. Times are shifted by the latencies (module docstring)."""

    robot: int
    odo: Table
    meas: Table
    gt: Table | None
    t_odo: Array
    t_meas: Array
    subj: IntArray
    """subject of each measurement (-1: barcode not in Barcodes.dat)."""
    ids: IntArray
    """landmark id of each measurement, DYNAMIC_ID for robots, CLUTTER_ID for unknown barcodes."""

    def in_run(self, t0: float, t1: float) -> NDArray[np.bool_]:
        return (self.t_meas > t0) & (self.t_meas <= t1)


def _read_common(folder: Path) -> _Common:
    bc = read_table(require_file(folder / "Barcodes.dat", "Barcodes.dat"), ("subject", "barcode"))
    subjects, barcodes = check_integer(bc, 0, "subject"), check_integer(bc, 1, "barcode")
    dup = np.flatnonzero(np.diff(np.sort(barcodes)) == 0)
    if dup.size:
        b = np.sort(barcodes)[dup[0]]
        raise DatasetFormatError(f"{bc.where(int(np.flatnonzero(barcodes == b)[1]))}: barcode {b} listed twice")
    lm = read_table(require_file(folder / "Landmark_Groundtruth.dat", "Landmark_Groundtruth.dat"),
                    ("subject", "x", "y", "x_std", "y_std"))
    lm_subj = check_integer(lm, 0, "subject")
    order = np.argsort(lm_subj, kind="stable")
    lm_subj, lm_xy = lm_subj[order], lm.data[order, 1:3]
    if np.any(np.diff(lm_subj) == 0):
        raise DatasetFormatError(f"{lm.path}: landmark subject {lm_subj[np.flatnonzero(np.diff(lm_subj) == 0)[0]]} "
                                 "listed twice")
    return _Common(dict(zip(barcodes.tolist(), subjects.tolist(), strict=True)), lm_subj, lm_xy)


def _read_robot(folder: Path, robot: int, ground_truth: bool, odometry_delay_s: float, camera_delay_s: float,
                common: _Common) -> _RobotFiles:
    odo = read_table(require_file(folder / f"Robot{robot}_Odometry.dat", f"odometry of robot {robot}"),
                     ("time", "v", "omega"), min_rows=2)
    check_nondecreasing(odo, 0, "time")
    meas = read_table(require_file(folder / f"Robot{robot}_Measurement.dat", f"measurements of robot {robot}"),
                      ("time", "barcode", "range", "bearing"), min_rows=0)
    check_nondecreasing(meas, 0, "time")
    m_bar = check_integer(meas, 1, "barcode")
    # a range or bearing no camera in the 15 x 8 m arena can report is a corrupted line: taken in, it would become the
    # fitted sensor's max range or field of view (a range of 1e9 m did)
    bad = (meas.data[:, 2] <= 0) | (meas.data[:, 2] > MAX_RANGE_M) | (np.abs(meas.data[:, 3]) > np.pi)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise DatasetFormatError(f"{meas.where(i)}: range must be in (0, {MAX_RANGE_M:g}] m and bearing in "
                                 f"[-pi, pi] rad, got {float(meas.data[i, 2])} m, {float(meas.data[i, 3])} rad")
    gt = None
    if ground_truth:
        gt = read_table(require_file(folder / f"Robot{robot}_Groundtruth.dat", f"ground truth of robot {robot}"),
                        ("time", "x", "y", "theta"), min_rows=2)
        check_nondecreasing(gt, 0, "time")
    # barcode -> subject -> landmark id (or robot / unknown)
    subj_to_lm = {int(s): i for i, s in enumerate(common.lm_subj)}
    subj = np.array([common.bar_to_subj.get(int(b), -1) for b in m_bar], dtype=np.int64)
    ids = np.array([subj_to_lm.get(int(s), DYNAMIC_ID if s >= 0 else CLUTTER_ID) for s in subj], dtype=np.int64)
    # commands: when the robot executes them; measurements: when each image was taken
    return _RobotFiles(robot, odo, meas, gt, odo.data[:, 0] + odometry_delay_s, meas.data[:, 0] - camera_delay_s,
                       subj, ids)


def _span(rf: _RobotFiles) -> tuple[float, float]:
    """(t0, t1) of one robot's run: where both odometry and ground truth exist (GT starts ~6-9 s earlier)."""
    t0, t1 = float(rf.t_odo[0]), float(rf.t_odo[-1])
    if rf.gt is not None:
        t0 = max(t0, float(rf.gt.data[0, 0]))
        t1 = min(t1, float(rf.gt.data[-1, 0]))
        if t1 <= t0:
            raise DatasetFormatError(f"{rf.gt.path}: ground truth ({rf.gt.data[0, 0]!r}..{rf.gt.data[-1, 0]!r}) does "
                                     f"not overlap the odometry ({rf.t_odo[0]!r}..{rf.t_odo[-1]!r}) of {rf.odo.path}")
    return t0, t1


def _assemble(rf: _RobotFiles, common: _Common, keep: NDArray[np.bool_], stamps: Array, t1: float, *, dt_s: float,
              others: str, noise_window_s: float, sensor_fit: str) -> Log:
    """The robot's :class:`Log` on ``stamps`` (absolute, shifted times; ``stamps[0]`` is pose 0, the run ends at
    ``t1``) with the measurements selected by ``keep`` (each exactly on a stamp), noise fitted against truth."""
    meas, ids, lm_xy, lm_subj, gt = rf.meas, rf.ids, common.lm_xy, common.lm_subj, rf.gt
    t0 = float(stamps[0])
    counts = {"measurement_rows": int(meas.data.shape[0]), "of_landmarks": int(np.sum(ids >= 0)),
              "of_robots": int(np.sum(ids == DYNAMIC_ID)), "unknown_barcode": int(np.sum(ids == CLUTTER_ID)),
              "outside_run": int(np.sum(~rf.in_run(t0, t1)))}
    obs_step = np.searchsorted(stamps, rf.t_meas[keep]).astype(np.int64)  # exact hits by construction

    dr = integrate_velocity(rf.t_odo, rf.odo.data[:, 1], rf.odo.data[:, 2], stamps)
    odometry = increments(dr)
    true_poses = initial = None
    motion: dict[str, Any] = {}
    sensor: dict[str, Any] = {}
    estimate: dict[str, Any] = {}
    if gt is not None:
        true_poses = interpolate_poses(gt.data[:, 0], gt.data[:, 1:4], stamps)
        initial = true_poses[0].copy()
        n_win = max(1, round(noise_window_s / float(np.median(np.diff(stamps)))))
        if odometry.shape[0] >= 4 * n_win:
            motion = fit_motion_noise(odometry, true_poses, n_win)
            estimate["motion_window_steps"] = n_win
        lm_mask = ids[keep] >= 0
        if lm_mask.any():
            pred = range_bearing(true_poses[obs_step[lm_mask]], lm_xy[ids[keep][lm_mask]])
            r_res = robust_std(meas.data[keep, 2][lm_mask] - pred[:, 0])
            b_res = robust_std(angle_diff(meas.data[keep, 3][lm_mask], pred[:, 1]))
            estimate["range_residual"] = r_res
            estimate["bearing_residual"] = b_res
            # misread barcodes: a landmark id whose measurement is far from that landmark (robot 5 of MRCLAM 7 has
            # four at 618-619 s, 6 m / 2.2 rad off). Kept (estimators must gate them); steps are of the whole run.
            e_r = meas.data[keep, 2][lm_mask] - pred[:, 0]
            e_b = angle_diff(meas.data[keep, 3][lm_mask], pred[:, 1])
            z = np.hypot(e_r / r_res["std"], e_b / b_res["std"])
            gross = np.flatnonzero(z > GROSS_SIGMA)
            ok = z <= GROSS_SIGMA
            if sensor_fit == "rms":
                sensor = {"range_std_m": float(np.sqrt(np.mean(e_r[ok] ** 2))),
                          "bearing_std_rad": float(np.sqrt(np.mean(e_b[ok] ** 2)))}
            else:
                sensor = {"range_std_m": r_res["std"], "bearing_std_rad": b_res["std"]}
            estimate["gross_outliers"] = {
                "threshold_sigma": GROSS_SIGMA, "count": int(gross.size),
                "steps": obs_step[lm_mask][gross].tolist(), "landmark_ids": ids[keep][lm_mask][gross].tolist()}
    if keep.any():
        sensor["max_range_m"] = float(np.ceil(meas.data[keep, 2].max() * 10) / 10)
        sensor["fov_rad"] = float(min(2 * np.pi, np.ceil(2 * np.abs(meas.data[keep, 3]).max() * 100) / 100))
        if true_poses is not None and lm_xy.shape[0]:
            # per-STEP detection probability of a landmark inside that range and field of view (truth geometry):
            # the camera reports a visible landmark in only ~10 % of the 0.1 s steps, which matters to filters that
            # count misses (negative information)
            z = range_bearing(true_poses[1:, None, :], lm_xy[None, :, :])
            in_view = (z[..., 0] <= sensor["max_range_m"]) & (np.abs(z[..., 1]) <= 0.5 * sensor["fov_rad"])
            seen = np.zeros_like(in_view)
            lm_obs = ids[keep] >= 0
            seen[obs_step[lm_obs] - 1, ids[keep][lm_obs]] = True
            if in_view.any():
                sensor["detection_prob"] = float(max(np.sum(seen & in_view) / np.sum(in_view), 1e-3))

    metadata = {
        "source": "dataset",
        "dataset": "mrclam",
        "dataset_path": str(meas.path.parent.resolve()),
        "robot": int(rf.robot),
        "measurement": "range-bearing",
        "step_convention": f"pose 0 at the first odometry time; {dt_s} s grid merged with measurement times",
        "dt_s": float(dt_s),
        "t0_unix_s": t0,
        "others": others,
        "landmark_subjects": [int(s) for s in lm_subj],
        "counts": counts,
        "motion": motion,
        "sensor": sensor,
        "noise_estimate": estimate,
        "units": {"length": "m", "angle": "rad", "time": "s (relative to t0_unix_s)"},
    }
    log = Log(
        stamps_s=stamps - t0,
        odometry=odometry,
        obs_step=obs_step,
        obs_range_m=meas.data[keep, 2].copy(),
        obs_bearing_rad=meas.data[keep, 3].copy(),
        obs_id=ids[keep],
        initial_pose=initial if initial is not None else np.zeros(3),
        true_poses=true_poses,
        true_landmarks=lm_xy.copy(),
        true_landmark_ids=np.arange(lm_subj.size, dtype=np.int64),
        metadata=metadata,
    )
    return log


def _fit_sighting_noise(logs: tuple[Log, ...], robots: tuple[int, ...], s: RobotSightings) -> dict[str, Any]:
    """Spread of the robot-robot sightings about the truth (root mean square without the gross outliers beyond
    ``GROSS_SIGMA`` robust standard deviations, as the landmark fit): the sensor model of a robot-robot factor."""
    truth = np.stack([np.asarray(log.true_poses) for log in logs])  # (R, T+1, 3)
    row = {r: i for i, r in enumerate(robots)}
    a = np.array([row[int(r)] for r in s.observer])
    b = np.array([row[int(r)] for r in s.observed])
    pred = range_bearing(truth[a, s.step], truth[b, s.step, :2])
    e_r = s.range_m - pred[:, 0]
    e_b = angle_diff(s.bearing_rad, pred[:, 1])
    z = np.hypot(e_r / robust_std(e_r)["std"], e_b / robust_std(e_b)["std"])
    ok = z <= GROSS_SIGMA
    return {"range_std_m": float(np.sqrt(np.mean(e_r[ok] ** 2))),
            "bearing_std_rad": float(np.sqrt(np.mean(e_b[ok] ** 2))), "range_bias_m": float(np.median(e_r)),
            "gross_outliers": int(np.sum(~ok))}

