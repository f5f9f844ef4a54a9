"""CMU Plaza range-only loader (Djugash, Hamner, Roth, JFR 2009): Plaza1 / Plaza2 in GTSAM's text layout.

Files ``<name>_DR.txt`` (time, delta_distance, delta_heading), ``<name>_TD.txt`` (time, sender_id, node_id, range),
``<name>_GT.txt`` (time, x, y, heading; GPS ground truth) and ``<name>_TL.txt`` (node_id, x, y; surveyed radio
nodes); ``#`` comment lines are skipped.

Steps: one per DR row (step t ends at DR row t-1's time); pose 0 is at the first GT time when GT starts earlier
(as in the staged files, where GT row t+1 has DR row t's time), else one median DR period before the first DR row.
Odometry per step is the chord of a constant-curvature arc, ``[d cos(dh/2), d sin(dh/2), dh]``; of the three usual
readings (move then turn, turn then move, move along the mid heading) the mid-heading one reproduces the
dataset's own dead-reckoned path Plaza2_DRp within 5 cm over the whole run (the others drift by 0.4-0.5 m).
Range measurements are attached to the nearest step (>= 1; a step is ~0.1-0.2 s, a range within ~0.1 s of
its time); ranges more than one DR period outside the run are dropped. Measurements are range-only: ``obs_range_m``
holds the range, ``obs_bearing_rad`` is NaN, ``metadata['measurement'] == 'range-only'``. Node ids map to landmark
ids 0..N-1 in increasing node order (``metadata['node_ids'][i]`` is the node of landmark id i).

Ground truth: GT poses are interpolated at the step times (exact at the staged files' shared times). Plaza2's GT
heading column points backwards (opposite to the direction of travel); the loader detects this (median travel
direction vs heading more than pi/2 off on moving steps) and adds pi, recording ``gt_heading_flipped``. Plaza1's
GT heading equals the dead-reckoned heading (it is not independent truth); only GT positions are GPS.
The ranges carry a positive bias of ~2.8 m against the GT geometry; ``metadata['noise_estimate']`` records it and
``sensor.range_std_m`` is the zero-mean spread (bias folded in), see :func:`robust_std`. Plaza1's DRp file (the
dataset's own dead reckoning) is not reproduced by integrating its DR rows (its travel direction differs from its
heading by ~0.27 rad); Plaza2's is (within 5 cm).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slam2d.geometry.angles import angle_diff, wrap_angle
from slam2d.io.datasets._common import (
    DatasetFormatError,
    cap_log,
    check_integer,
    check_nondecreasing,
    content_errors,
    fit_motion_noise,
    interpolate_poses,
    nearest_step,
    read_table,
    require_file,
    robust_std,
)
from slam2d.log import Log

NAMES = ("Plaza1", "Plaza2")

#: rotation part of the Plaza2 motion-noise fit (``load_plaza(path, "Plaza2").metadata['motion']``: alpha_rot_rot
#: 1.02e-4, alpha_rot_trans 1.05e-5, min_rot_std_rad 1.56e-3 per 0.1 s step), rescaled to Plaza1's 0.2 s steps so the
#: variance per metre, radian and second is unchanged (alphas / 2, floor * sqrt(2)); used for Plaza1 only
PLAZA2_ROTATION_NOISE: dict[str, float] = {"alpha_rot_rot": 5.1e-5, "alpha_rot_trans": 5.2e-6,
                                           "min_rot_std_rad": 2.2e-3}


@content_errors("Plaza")
def load_plaza(path: str | Path, name: str = "Plaza1", *, max_steps: int | None = None,
               max_time_s: float | None = None, noise_window_s: float = 2.0) -> Log:
    """Load ``name`` (``Plaza1`` or ``Plaza2``) from the folder ``path`` as a range-only :class:`Log`.

    See the module docstring for the conventions. Motion noise is fitted against GT positions and headings over
    windows of ``noise_window_s`` (:func:`fit_motion_noise`; for Plaza1 the rotation part is meaningless because
    its GT heading is the odometry heading, so the Plaza2 rotation values are used whenever GT heading increments
    equal the odometry's; see ``noise_estimate``).
    Shapes: stamps (T+1,), odometry (T,3), obs (K,) ranges with NaN bearings, true_poses (T+1,3),
    true_landmarks (N,2).
    """
    folder = Path(path)
    if name not in NAMES:
        raise ValueError(f"name must be one of {NAMES} (got {name!r})")
    if not folder.is_dir():
        raise DatasetFormatError(f"{folder}: Plaza dataset folder not found")
    dr = read_table(require_file(folder / f"{name}_DR.txt", f"{name} odometry"),
                    ("time", "delta_distance", "delta_heading"), min_rows=2)
    check_nondecreasing(dr, 0, "time")
    td = read_table(require_file(folder / f"{name}_TD.txt", f"{name} ranges"),
                    ("time", "sender_id", "node_id", "range"), min_rows=0)
    tl = read_table(require_file(folder / f"{name}_TL.txt", f"{name} node positions"), ("node_id", "x", "y"))
    gt_path = folder / f"{name}_GT.txt"
    gt = read_table(gt_path, ("time", "x", "y", "heading"), min_rows=2) if gt_path.is_file() else None
    if gt is not None:
        check_nondecreasing(gt, 0, "time")

    nodes = check_integer(tl, 0, "node_id")
    order = np.argsort(nodes, kind="stable")
    nodes, node_xy = nodes[order], tl.data[order, 1:3]
    if np.any(np.diff(nodes) == 0):
        raise DatasetFormatError(f"{tl.path}: node_id {nodes[np.flatnonzero(np.diff(nodes) == 0)[0]]} listed twice")
    td_node = check_integer(td, 2, "node_id")
    check_integer(td, 1, "sender_id")
    pos = np.searchsorted(nodes, td_node)
    unknown = np.flatnonzero((pos >= nodes.size) | (nodes[np.minimum(pos, nodes.size - 1)] != td_node))
    if unknown.size:
        i = int(unknown[0])
        raise DatasetFormatError(f"{td.where(i)}: node_id {td_node[i]} is not in {tl.path.name} "
                                 f"(nodes {nodes.tolist()})")
    if np.any(td.data[:, 3] <= 0):
        i = int(np.flatnonzero(td.data[:, 3] <= 0)[0])
        raise DatasetFormatError(f"{td.where(i)}: range must be > 0, got {td.data[i, 3]!r}")

    t_dr = dr.data[:, 0]
    period = float(np.median(np.diff(t_dr)))
    if gt is not None and gt.data[0, 0] < t_dr[0]:
        t_first = float(gt.data[0, 0])
    else:
        t_first = float(t_dr[0] - period)
    stamps = np.concatenate([[t_first], t_dr])
    t = stamps.size - 1
    d, dh = dr.data[:, 1], dr.data[:, 2]
    odometry = np.column_stack([d * np.cos(dh / 2), d * np.sin(dh / 2), wrap_angle(dh)])

    t_td = td.data[:, 0]
    inside = (t_td >= stamps[0] - period) & (t_td <= stamps[-1] + period)
    order_td = np.argsort(t_td[inside], kind="stable")
    sel = np.flatnonzero(inside)[order_td]
    obs_step = np.maximum(nearest_step(stamps, t_td[sel]), 1)
    srt = np.argsort(obs_step, kind="stable")
    sel, obs_step = sel[srt], obs_step[srt]
    obs_id = pos[sel].astype(np.int64)

    true_poses = None
    initial = np.zeros(3)
    motion: dict[str, Any] = {}
    sensor: dict[str, Any] = {"max_range_m": float(np.ceil(td.data[:, 3].max())), "fov_rad": float(2 * np.pi),
                              "bearing_std_rad": float(np.pi)}
    estimate: dict[str, Any] = {}
    flipped = False
    if gt is not None:
        if gt.data[-1, 0] < stamps[-1] or gt.data[0, 0] > stamps[0]:
            raise DatasetFormatError(f"{gt.path}: ground truth spans {gt.data[0, 0]!r}..{gt.data[-1, 0]!r}, "
                                     f"not the run {stamps[0]!r}..{stamps[-1]!r}")
        g = gt.data[:, 1:4].copy()
        step = np.diff(g[:, :2], axis=0)
        moving = np.hypot(step[:, 0], step[:, 1]) > 0.05
        if moving.any():
            travel = np.arctan2(step[moving, 1], step[moving, 0])
            if np.median(np.abs(angle_diff(travel, g[:-1][moving, 2]))) > np.pi / 2:
                g[:, 2] = wrap_angle(g[:, 2] + np.pi)
                flipped = True
        true_poses = interpolate_poses(gt.data[:, 0], g, stamps)
        initial = true_poses[0].copy()
        n_win = max(1, round(noise_window_s / period))
        if t >= 4 * n_win:
            motion = fit_motion_noise(odometry, true_poses, n_win)
            estimate["motion_window_steps"] = n_win
            # Plaza1's GT heading is the integrated odometry heading: a rotation fit against it is ~0 (overconfident)
            heading_from_odometry = bool(np.max(np.abs(angle_diff(np.diff(true_poses[:, 2]), odometry[:, 2]))) < 1e-9)
            estimate["gt_heading_from_odometry"] = heading_from_odometry
            if heading_from_odometry:
                motion.update(PLAZA2_ROTATION_NOISE)
                estimate["rotation_noise"] = "Plaza2 fit (GT heading here is the odometry heading)"
        pred = np.hypot(*(node_xy[obs_id] - true_poses[obs_step, :2]).T)
        r_res = robust_std(td.data[sel, 3] - pred)
        sensor["range_std_m"] = r_res["std"]
        estimate["range_residual"] = r_res
        estimate["range_bias_m"] = r_res["median"]

    # per-step probability that a given node's range is reported (all nodes are always "in view": omnidirectional)
    sensor["detection_prob"] = float(min(1.0, max(sel.size / (t * nodes.size), 1e-3)))
    metadata = {
        "source": "dataset",
        "dataset": name.lower(),
        "dataset_path": str(folder.resolve()),
        "measurement": "range-only",
        "step_convention": "one step per DR row; ranges attached to the nearest step",
        "node_ids": [int(n) for n in nodes],
        "gt_heading_flipped": flipped,
        "counts": {"dr_rows": int(dr.data.shape[0]), "td_rows": int(td.data.shape[0]), "ranges_kept": int(sel.size)},
        "motion": motion,
        "sensor": sensor,
        "noise_estimate": estimate,
        "units": {"length": "m", "angle": "rad", "time": "s (vehicle clock)"},
    }
    log = Log(
        stamps_s=stamps,
        odometry=odometry,
        obs_step=obs_step.astype(np.int64),
        obs_range_m=td.data[sel, 3].copy(),
        obs_bearing_rad=np.full(sel.size, np.nan),
        obs_id=obs_id,
        initial_pose=initial,
        true_poses=true_poses,
        true_landmarks=node_xy.copy(),
        true_landmark_ids=np.arange(nodes.size, dtype=np.int64),
        metadata=metadata,
    )
    return cap_log(log, max_steps, max_time_s)
