"""Victoria Park (ACFR, Guivant & Nebot) raw loader: Ackermann odometry, pre-extracted tree detections, GPS.

Files (in ``raw/`` of the staged folder, or the folder itself): ``odometry_aa3_dr.csv`` (time_ms, speed_mps,
steering_rad), ``tree_detections.csv`` (scan_index, time_s, range_m, bearing_rad, diameter_m), ``laser_scan_times.csv``
(scan_index, time_s, n_detections), ``gps_aa3_gpsx.csv`` (time_ms, Lo_m, La_m); comment lines start with ``#``.

Kinematics (Guivant & Nebot): the speed is measured at the rear-left wheel, offset H = 0.76 m from the
rear-axle centre, so the rear-axle centre moves at ``vc = v / (1 - tan(s) H / L)`` and turns at
``omega = vc tan(s) / L`` (wheel base L = 2.83 m, steering s). The rear axle follows exact arcs for
piecewise-constant (v, s) held from each record to the next. The laser sits at (a, b) = (3.78, 0.5) m in the
vehicle frame (forward, left: the sign used by the published model ``x' = vc cos(phi) - vc/L tan(s)
(a sin(phi) + b cos(phi))``); the log's pose is the LASER pose ``rear (+) [a, b, 0]``, so detections are
range-bearing from the pose itself.

Calibration (both values are loader options; neither uses GPS). The dataset's info.txt gives a = 0.95 m and no
steering offset; with those, dead reckoning ends 93 m (ATE vs GPS) off and no filter can hold a map. The published
a = 3.78 m and a steering offset of +0.006 rad fit the data better: trees detected 1 s, 5 s and 20 s apart and placed
through dead reckoning land 0.20 / 0.66 / 0.60 m apart (median nearest-neighbour gap) with info.txt's model, and
0.10 / 0.21 / 0.32 m with the calibrated one; whole-run dead reckoning falls to 44 m ATE. The offset was chosen as
the minimiser of those gaps over a 0.001 rad grid (:func:`reobservation_gaps_m` measures them).

Steps: one per laser scan (pose t at the time of scan t-1 counted from the first scan after the first odometry
record); pose 0 is at the first odometry time and scans before it are dropped.
Bearings are the laser beam angle minus pi/2 (0 = straight ahead, positive to the left). The detector's tree
diameter is kept as a 1-D descriptor. Association is unknown: every ``obs_id`` is -1, so the ``known`` association
method cannot run on this dataset.

GPS fixes (own frame, metres) are attached to the nearest step when within half a scan period (one per step, the
closest) in ``gps_step`` / ``gps_xy`` for evaluation (:func:`slam2d.eval.gps.gps_ate`); there is no ``true_poses``.
``metadata['gps_role'] == 'evaluation'`` says estimators should not fuse them (the registry's ``make_config``, used
by ``run_named``, the CLI and sweeps, turns ``use_gps`` off for such logs unless an override sets it).
Noise parameters in the metadata are hand-set, not fitted (there is no full ground truth), except the detection
probability 0.5: of the mapped trees predicted in view (< 28 m) along an EKF run, 56 % had a detection within 1.5 m
in a scan. For scale (numbers measured with the info.txt model): trees
re-observed one scan later, predicted through the loaded odometry, differ by a robust (MAD) std of 0.061 m in range
and 0.0042 rad in bearing (so at most ~0.043 m / 0.003 rad per detection); 5 scans (~1 s) later 0.136 m / 0.010 rad,
25 scans later 0.35 m / 0.033 rad (odometry drift). Shifting the scan times against the odometry by -0.3..+0.3 s
makes those residuals smallest near 0 to -0.05 s, so no clock offset is applied. The hand-set sensor noise
(0.5 m, 0.02 rad) is deliberately several times the re-observation spread: tree centres move with the viewpoint
and the detector reports clutter.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry import se2
from slam2d.io.datasets._common import (
    DatasetFormatError,
    cap_log,
    check_integer,
    check_nondecreasing,
    content_errors,
    increments,
    integrate_velocity,
    nearest_step,
    read_table,
    require_file,
)
from slam2d.log import CLUTTER_ID, Log

IntArray = NDArray[np.int64]

#: vehicle geometry (metres): b, H, L from the dataset's info.txt / car.bmp. The laser's forward offset ``a`` is the
#: 3.78 m of Guivant & Nebot's published model (laser at the front bumper), not info.txt's 0.95 m: re-observed trees
#: agree better with 3.78 m (module docstring, "Calibration").
CAR_A_M = 3.78
CAR_B_M = 0.5
CAR_H_M = 0.76
CAR_L_M = 2.83
#: steering-encoder offset (rad) added to every steering reading, calibrated from the data alone (module docstring,
#: "Calibration"). Uncorrected, it is a constant turn of ~0.1 deg/m that bends the whole path.
STEERING_OFFSET_RAD = 0.006

#: hand-set noise (not fitted: no full ground truth). Per step (one laser scan, ~0.2 s, up to ~1 m of travel).
MOTION = {"alpha_rot_rot": 0.01, "alpha_rot_trans": 0.0004, "alpha_trans_trans": 0.0025, "alpha_trans_rot": 0.0001,
          "min_trans_std_m": 0.01, "min_rot_std_rad": 0.002}
SENSOR = {"range_std_m": 0.5, "bearing_std_rad": 0.02, "max_range_m": 80.0, "fov_rad": float(np.pi),
          "detection_prob": 0.5, "descriptor_dim": 1, "descriptor_std": 0.1}
#: detections farther than this are dropped by default: they are few, and a far trunk's centre is poorly defined
DEFAULT_MAX_RANGE_M = 30.0


def raw_folder(path: str | Path) -> Path:
    """The folder holding the raw csv files: ``path/raw`` when present, else ``path``."""
    p = Path(path)
    return p / "raw" if (p / "raw" / "odometry_aa3_dr.csv").is_file() else p


@content_errors("Victoria Park")
def load_victoria(path: str | Path, *, max_steps: int | None = None, max_time_s: float | None = None,
                  descriptors: bool = True, max_range_m: float | None = DEFAULT_MAX_RANGE_M,
                  laser_forward_m: float = CAR_A_M, steering_offset_rad: float = STEERING_OFFSET_RAD) -> Log:
    """Load the raw Victoria Park run in ``path`` (the staged folder or its ``raw/``) as a :class:`Log`.

    See the module docstring for the conventions. ``max_steps`` / ``max_time_s`` cut the run. ``max_range_m`` drops
    detections farther than that (and becomes the sensor's ``max_range_m`` in the metadata); default 30 m, None keeps
    all (up to 75 m).
    ``laser_forward_m`` (the model's ``a``) and ``steering_offset_rad`` default to the calibrated values above
    (``laser_forward_m=0.95, steering_offset_rad=0`` reproduces the uncalibrated info.txt model).
    Shapes: stamps (T+1,), odometry (T,3), obs (K,) with obs_descriptor (K,1) tree diameter (m) when ``descriptors``.
    """
    folder = raw_folder(path)
    if not folder.is_dir():
        raise DatasetFormatError(f"{folder}: Victoria Park folder not found")
    odo = read_table(require_file(folder / "odometry_aa3_dr.csv", "Victoria Park odometry"),
                     ("time_ms", "speed_mps", "steering_rad"), delimiter=",", min_rows=2)
    check_nondecreasing(odo, 0, "time_ms")
    scans = read_table(require_file(folder / "laser_scan_times.csv", "Victoria Park laser scan times"),
                       ("scan_index", "time_s", "n_detections"), delimiter=",")
    scan_idx = check_integer(scans, 0, "scan_index")
    bad = np.flatnonzero(scan_idx != np.arange(scan_idx.size))
    if bad.size:
        raise DatasetFormatError(f"{scans.where(int(bad[0]))}: scan_index {scan_idx[bad[0]]} out of sequence "
                                 f"(expected {int(bad[0])})")
    check_nondecreasing(scans, 1, "time_s")
    n_det = check_integer(scans, 2, "n_detections")
    det = read_table(require_file(folder / "tree_detections.csv", "Victoria Park tree detections"),
                     ("scan_index", "time_s", "range_m", "bearing_rad", "diameter_m"), delimiter=",", min_rows=0)
    d_scan = check_integer(det, 0, "scan_index")
    out = np.flatnonzero((d_scan < 0) | (d_scan >= scan_idx.size))
    if out.size:
        raise DatasetFormatError(f"{det.where(int(out[0]))}: scan_index {d_scan[out[0]]} not in laser_scan_times.csv "
                                 f"(0..{scan_idx.size - 1})")
    back = np.flatnonzero(np.diff(d_scan) < 0)
    if back.size:
        raise DatasetFormatError(f"{det.where(int(back[0]) + 1)}: scan_index goes backwards")
    mism = np.flatnonzero(det.data[:, 1] != scans.data[d_scan, 1])
    if mism.size:
        i = int(mism[0])
        raise DatasetFormatError(f"{det.where(i)}: time_s {det.data[i, 1]!r} differs from scan {d_scan[i]}'s time "
                                 f"{scans.data[d_scan[i], 1]!r} in {scans.where(int(d_scan[i]))}")
    per_scan = np.bincount(d_scan, minlength=scan_idx.size)
    wrong = np.flatnonzero(per_scan != n_det)
    if wrong.size:
        j = int(wrong[0])
        raise DatasetFormatError(f"{scans.where(j)}: n_detections {n_det[j]} but tree_detections.csv has "
                                 f"{per_scan[j]} rows for scan {j}")
    if np.any(det.data[:, 2] <= 0):
        i = int(np.flatnonzero(det.data[:, 2] <= 0)[0])
        raise DatasetFormatError(f"{det.where(i)}: range_m must be > 0, got {det.data[i, 2]!r}")
    gps_path = folder / "gps_aa3_gpsx.csv"
    gps = read_table(gps_path, ("time_ms", "Lo_m", "La_m"), delimiter=",", min_rows=0) if gps_path.is_file() else None

    t_odo = odo.data[:, 0] / 1000.0
    t0 = float(t_odo[0])
    t_scan = scans.data[:, 1]
    first = int(np.searchsorted(t_scan, t0, side="right"))  # first scan strictly after pose 0
    stamps = np.concatenate([[t0], t_scan[first:]])
    keep = d_scan >= first  # scans first.. are steps 1..T
    if max_range_m is not None:
        if not max_range_m > 0:
            raise ValueError(f"max_range_m must be > 0 (got {max_range_m})")
        keep &= det.data[:, 2] <= max_range_m
    obs_step = (d_scan[keep] - first + 1).astype(np.int64)

    speed, steer = odo.data[:, 1], odo.data[:, 2] + steering_offset_rad
    vc = speed / (1.0 - np.tan(steer) * CAR_H_M / CAR_L_M)
    rear = integrate_velocity(t_odo, vc, vc * np.tan(steer) / CAR_L_M, stamps)
    laser = se2.compose(rear, np.array([laser_forward_m, CAR_B_M, 0.0]))
    odometry = increments(laser)

    gps_step = gps_xy = None
    gps_counts = {"gps_rows": 0, "gps_attached": 0}
    if gps is not None and gps.data.shape[0]:
        check_nondecreasing(gps, 0, "time_ms")
        t_gps = gps.data[:, 0] / 1000.0
        half = 0.5 * float(np.median(np.diff(stamps)))
        s = nearest_step(stamps, t_gps)
        err = np.abs(stamps[s] - t_gps)
        ok = err <= half
        # one fix per step: the closest one
        order = np.lexsort((err[ok], s[ok]))
        s_ok, xy_ok = s[ok][order], gps.data[ok][order, 1:3]
        first_of = np.concatenate([[True], np.diff(s_ok) > 0]) if s_ok.size else np.zeros(0, dtype=bool)
        gps_step, gps_xy = s_ok[first_of].astype(np.int64), xy_ok[first_of].copy()
        gps_counts = {"gps_rows": int(gps.data.shape[0]), "gps_attached": int(gps_step.size)}

    sensor = dict(SENSOR) if descriptors else {k: v for k, v in SENSOR.items() if "descriptor" not in k}
    if max_range_m is not None:
        sensor["max_range_m"] = float(max_range_m)
    metadata = {
        "source": "dataset",
        "dataset": "victoria-park",
        "dataset_path": str(folder.resolve()),
        "measurement": "range-bearing",
        "association": "unknown (all obs_id = -1)",
        "gps_role": "evaluation",
        "step_convention": "pose 0 at the first odometry time; one step per later laser scan; pose = laser pose",
        "t0_s": t0,
        "vehicle": {"a_m": laser_forward_m, "b_m": CAR_B_M, "H_m": CAR_H_M, "L_m": CAR_L_M,
                    "steering_offset_rad": steering_offset_rad},
        "counts": {"detections": int(d_scan.size), "detections_kept": int(keep.sum()),
                   "scans": int(scan_idx.size), "scans_before_start": first, **gps_counts},
        "motion": dict(MOTION),
        "sensor": sensor,
        "noise_estimate": {"method": "hand-set (no full ground truth)"},
        "units": {"length": "m", "angle": "rad", "time": "s (dataset clock)"},
    }
    log = Log(
        stamps_s=stamps,
        odometry=odometry,
        obs_step=obs_step,
        obs_range_m=det.data[keep, 2].copy(),
        obs_bearing_rad=det.data[keep, 3] - np.pi / 2,
        obs_id=np.full(int(keep.sum()), CLUTTER_ID, dtype=np.int64),
        obs_descriptor=det.data[keep, 4:5].copy() if descriptors else None,
        gps_step=gps_step,
        gps_xy=gps_xy,
        metadata=metadata,
    )
    return cap_log(log, max_steps, max_time_s)


def reobservation_gaps_m(log: Log, lags: tuple[int, ...] = (5, 25, 100), *, every: int = 7,
                         max_gap_m: float = 3.0) -> list[float]:
    """Self-consistency of odometry + detections, without any ground truth: for scans ``k`` and ``k + lag``
    (k = 0, every, 2 every, ...), the detections are placed in the world through dead reckoning and each one of
    scan k is paired with its nearest of scan k + lag; returns the median pair distance (m) per lag, over pairs
    closer than ``max_gap_m``. A wrong laser offset or a steering bias spreads the same trunk apart as time passes.
    """
    from scipy.spatial import cKDTree

    poses = se2.compose_chain(log.initial_pose, log.odometry)
    p = poses[log.obs_step]
    world = p[:, :2] + log.obs_range_m[:, None] * np.column_stack([np.cos(p[:, 2] + log.obs_bearing_rad),
                                                                   np.sin(p[:, 2] + log.obs_bearing_rad)])
    start = np.searchsorted(log.obs_step, np.arange(log.num_steps + 2))
    out = []
    for lag in lags:
        gaps = []
        for k in range(1, log.num_steps + 1 - lag, every):
            a, b = world[start[k]:start[k + 1]], world[start[k + lag]:start[k + lag + 1]]
            if len(a) and len(b):
                d, _ = cKDTree(b).query(a)
                gaps.append(d[d < max_gap_m])
        out.append(float(np.median(np.concatenate(gaps))) if gaps else float("nan"))
    return out


def processed_pose_steps(path: str | Path, processed_poses: ArrayLike) -> IntArray:
    """The raw log's step index of each pose of the processed graph file (``victoriaPark.txt``).

    The processed file (iSAM) dead-reckons the rear-axle centre with info.txt's model, one pose per laser scan,
    dropping scans while the car stands still; its pose timestamps are not given. Its initial values (the odometry
    chain) therefore trace the same rear-axle path as ours: each processed pose is matched to the step at the same
    distance travelled along that path (on the staged file the matched distances agree to a median of 3 cm and at
    most 0.1 m in 99 % of poses). Shapes: (P, 3) -> (P,) int, into steps 0..T of ``load_victoria(path)``.
    """
    proc = np.asarray(processed_poses, dtype=np.float64).reshape(-1, 3)
    raw = load_victoria(path, laser_forward_m=0.0, steering_offset_rad=0.0)  # log pose = rear axle + (0, b)
    rear = se2.compose(se2.compose_chain(np.zeros(3), raw.odometry), se2.inverse(np.array([0.0, CAR_B_M, 0.0])))
    s_raw = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(rear[:, :2], axis=0).T))])
    s_proc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(proc[:, :2], axis=0).T))])
    j = np.searchsorted(s_raw, s_proc).clip(1, s_raw.size - 1)
    return np.where(np.abs(s_raw[j - 1] - s_proc) <= np.abs(s_raw[j] - s_proc), j - 1, j).astype(np.int64)
