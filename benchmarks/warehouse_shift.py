"""A simulated shift in the challenge warehouse with the lidar estimator in lifelong mode.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/warehouse_shift.py --hours 1 --report-min 10 \
        | tee warehouse_shift_1h.txt

World: ``warehouse-challenge`` (100 x 100 m, 14 identical aisles, 600 pallets, 20 forklifts), the drone flying its
lawnmower route over and over at 1.2 m/s. The simulator runs at 10 Hz (dt 0.1 s) with a scan every step, and every
scan is processed (10 Hz). It streams (``Simulator(record=False)``): no Log is ever materialised, so an 8 h shift
needs no more memory than a minute.

The drone takes its first scan at its dock, whose pose is the map's origin (the estimator is handed that scan with
zero odometry before the flight starts); without it the map's frame would be the pose after the first noisy
odometry step, a few mrad of heading off, and every "unaligned" error far from the dock would measure that.

Printed every ``--report-min`` simulated minutes: online (unaligned, the pose ``estimate()`` returns at each step)
position and heading error p99 so far, resident memory, keyframes, static cells, the estimator's per-scan latency
(``step`` + ``estimate``, process time) p50/p99, its CPU per simulated second, and the static cells inside the
forklifts' true boxes now / ghost static cells (see below). At the end: the whole-run
numbers, static-layer cells inside the forklifts' true boxes (now), on the forklifts' tracks (within 0.7 m of their
routes, where no structure stands: every forklift trace the map ever kept), farther than 0.2 m from any true static
structure (ghosts, and the map's own drift), and loops (the lifelong mode closes none: a revisit is localised
against the map).

``--markers surveyed`` puts the challenge's floor markers down (every 10 m along each aisle and road, and at every
crossing; read by the downward camera within 1 m) and hands the estimator their positions as a survey would give
them: the true positions plus a normal error of ``--survey-sigma`` (1 cm) per axis, drawn once. That the warehouse
surveyed its markers is an assumption of this mode. ``--markers mapped`` puts the same markers down without a
survey: each is mapped on its first sighting and corrects later passes (it carries that pass's drift).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from slam2d.config import with_overrides
from slam2d.graph.lidar import LidarSLAM, LidarSLAMConfig
from slam2d.log import Observations, Scan, Step
from slam2d.maps.layers import LayersConfig
from slam2d.maps.occupancy import rasterize_segments
from slam2d.sim import ScenarioConfig, Simulator
from slam2d.sim.raycast import simulate_scan_culled


def rss_mib() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def dock_step(sim: Simulator) -> Step:
    """A scan at the dock (the true initial pose), with zero odometry: the map's anchor."""
    lidar = sim.config.lidar
    near = sim.world.segments_near(0.0, sim.pose[:2], lidar.max_range_m)
    ranges = simulate_scan_culled(sim.pose, near, lidar, sim.rng["lidar"])
    empty = Observations(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    return Step(0, 0.0, 0.0, np.zeros(3), empty, scan=Scan(ranges, lidar.angles(), lidar.max_range_m))


def layer_truth(est: LidarSLAM, sim: Simulator) -> tuple[int, int, int]:
    """Static cells: inside a forklift's true box now; within 0.7 m of a forklift's route (its tracks: a forklift is
    1 m wide and drives on the route, while racks and walls are >= 2 m from every route); > 0.2 m from every true
    static segment (ghosts, or the map's own drift where it is off by more than 0.2 m)."""
    from scipy.ndimage import binary_dilation

    lay = est.map_layers()
    grid = lay.static_grid()
    world = sim.world
    structure = rasterize_segments(grid, world.walls)
    near_structure = binary_dilation(structure, np.ones((5, 5), bool))  # 2 cells = 0.2 m at 0.1 m
    boxes = world.segments_at(sim.time_s)[len(world.walls):]
    forklift = binary_dilation(rasterize_segments(grid, boxes), np.ones((3, 3), bool))
    routes = np.vstack([np.hstack([m.path, np.roll(m.path, -1, axis=0)]) for m in world.moving])
    tracks = binary_dilation(rasterize_segments(grid, routes), np.ones((15, 15), bool))  # +-0.7 m
    static = lay.static
    return (int(np.count_nonzero(static & forklift & ~near_structure)), int(np.count_nonzero(static & tracks)),
            int(np.count_nonzero(static & ~near_structure)))


def aligned_errors(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(T,) position errors after the one rotation + translation that best fits ``est`` (T,2) to ``truth``
    (least squares, Kabsch): what is left once the map frame's own offset is taken out (shape, not anchoring)."""
    me, mt = est.mean(axis=0), truth.mean(axis=0)
    u, _, vt = np.linalg.svd((est - me).T @ (truth - mt))
    d = np.sign(np.linalg.det(u @ vt))
    rot = (u @ np.diag([1.0, d]) @ vt).T
    return np.asarray(np.hypot(*((est - me) @ rot.T + mt - truth).T))


def survey(sim: Simulator, sigma_m: float, seed: int) -> tuple[tuple[int, float, float], ...]:
    """The survey drawn from its own generator (the simulator's streams are untouched)."""
    return sim.world.marker_survey(sigma_m, np.random.default_rng([seed, 17]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hours", type=float, default=1.0, help="simulated hours (default 1)")
    ap.add_argument("--report-min", type=float, default=60.0, help="report every this many simulated minutes")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--markers", choices=("off", "surveyed", "mapped"), default="off",
                    help="floor markers: off, on with surveyed positions, or on and mapped on first sighting "
                         "(default off)")
    ap.add_argument("--survey-sigma", type=float, default=0.01,
                    help="with --markers surveyed: the survey's error per axis, drawn once per marker (m)")
    ap.add_argument("--json", default=None, help="write the final numbers as JSON")
    args = ap.parse_args()
    if args.hours <= 0:
        ap.error(f"--hours must be > 0 (got {args.hours})")
    if args.report_min <= 0:
        ap.error(f"--report-min must be > 0 (got {args.report_min})")
    if args.json:  # refused now, not after the (hours of) shift
        from slam2d.io.atomic import check_output

        try:
            check_output(args.json, "--json")
        except OSError as e:
            ap.error(f"{e.filename}: {e.strerror}")

    over = {"dt_s": 0.1} if args.markers == "off" else {"dt_s": 0.1, "warehouse.floor_markers": True}
    cfg = with_overrides(ScenarioConfig(name="warehouse-challenge"), over)
    sim = Simulator(cfg, seed=args.seed, record=False)
    driver = sim.driver()
    dt = float(sim.config.dt_s or 0.1)
    steps = round(args.hours * 3600 / dt)
    every = max(1, round(args.report_min * 60 / dt))
    est = LidarSLAM(LidarSLAMConfig(layers=LayersConfig(), loop_closure=False,
                                    surveyed_markers=survey(sim, args.survey_sigma, args.seed)
                                    if args.markers == "surveyed" else (),
                                    map_unsurveyed_markers=args.markers == "mapped",
                                    survey_sigma_m=max(args.survey_sigma, 1e-3)))
    est.reset(sim.pose, rng=np.random.default_rng(args.seed))
    est.step(dock_step(sim))
    pos_err = np.zeros(steps, np.float32)
    head_err = np.zeros(steps, np.float32)
    lat_ms = np.zeros(steps, np.float32)
    est_xy = np.zeros((steps, 2), np.float32)
    true_xy = np.zeros((steps, 2), np.float32)
    mk = {"off": "off", "mapped": f"{len(sim.world.floor_markers)} unsurveyed, mapped on first sighting",
          "surveyed": f"{len(sim.world.floor_markers)} surveyed (survey error {100 * args.survey_sigma:g} cm per "
                      "axis)"}[args.markers]
    print(f"floor markers: {mk}", flush=True)
    print(f"warehouse-challenge seed {args.seed}: {len(sim.world.moving)} forklifts, lidar "
          f"{sim.config.lidar.beams} beams / {sim.config.lidar.max_range_m} m at {1 / dt:.0f} Hz, every scan "
          f"processed; {steps} steps = {args.hours:g} h simulated", flush=True)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i in range(steps):
        st = sim.step(*driver.command(sim.pose, None))
        t0 = time.process_time()
        est.step(st)
        e = est.estimate()
        lat_ms[i] = 1e3 * (time.process_time() - t0)
        pos_err[i] = np.hypot(e.pose[0] - sim.pose[0], e.pose[1] - sim.pose[1])
        est_xy[i], true_xy[i] = e.pose[:2], sim.pose[:2]
        head_err[i] = abs(np.arctan2(np.sin(e.pose[2] - sim.pose[2]), np.cos(e.pose[2] - sim.pose[2])))
        if (i + 1) % every == 0 or i + 1 == steps:
            n = i + 1
            s = est.layer_stats()
            print(f"t {n * dt / 60:6.1f} min | pos p99 {100 * np.percentile(pos_err[:n], 99):5.1f} cm "
                  f"(now {100 * pos_err[i]:4.1f}) | head p99 {np.degrees(np.percentile(head_err[:n], 99)):5.2f} deg "
                  f"| RSS {rss_mib():6.1f} MiB | keyframes {s.keyframes} | static cells {s.static_cells} | "
                  f"scan p50 {np.percentile(lat_ms[:n], 50):5.2f} p99 {np.percentile(lat_ms[:n], 99):5.2f} ms | "
                  f"CPU {lat_ms[:n].sum() / 1e3 / (n * dt):.3f} core | failures {s.tracking_failures} | "
                  f"marker fixes {s.marker_fixes} (mapped {s.markers_mapped}) | "
                  f"static cells in forklifts / on tracks / > 0.2 m off {'/'.join(map(str, layer_truth(est, sim)))} | "
                  f"wall {time.perf_counter() - wall0:6.0f} s", flush=True)
    est.finalize()
    aligned = aligned_errors(est_xy.astype(float), true_xy.astype(float))
    in_forklifts, on_tracks, ghosts = layer_truth(est, sim)
    s = est.layer_stats()
    rec = {
        "seed": args.seed, "hours": args.hours, "markers": args.markers,  "scans_processed": steps, "rate_hz": 1 / dt,
        "pos_err_p99_cm": float(100 * np.percentile(pos_err, 99)),
        "aligned_pos_err_p99_cm": float(100 * np.percentile(aligned, 99)), "pos_err_max_cm": float(100 * pos_err.max()),
        "head_err_p99_deg": float(np.degrees(np.percentile(head_err, 99))),
        "head_err_max_deg": float(np.degrees(head_err.max())),
        "scan_ms_p50": float(np.percentile(lat_ms, 50)), "scan_ms_p99": float(np.percentile(lat_ms, 99)),
        "scan_ms_max": float(lat_ms.max()),
        "estimator_cpu_per_sim_s": float(lat_ms.sum() / 1e3 / (steps * dt)),
        "process_cpu_per_sim_s": float((time.process_time() - cpu0) / (steps * dt)),
        "rss_mib_end": rss_mib(), "keyframes": s.keyframes, "static_cells": s.static_cells,
        "static_cells_in_forklifts": in_forklifts, "static_cells_on_forklift_tracks": on_tracks,
        "static_cells_off_structure": ghosts, "loops_accepted": 0,
        "false_loops": 0, "tracking_failures": s.tracking_failures,
        "marker_fixes": s.marker_fixes, "markers_mapped": s.markers_mapped,
        "dynamic_points_total": s.dynamic_points_total,
    }
    print(f"whole run: pos p99 {rec['pos_err_p99_cm']:.1f} cm (max {rec['pos_err_max_cm']:.1f}; after one rigid "
          f"alignment of the whole run to the truth: p99 {rec['aligned_pos_err_p99_cm']:.1f} cm), head p99 "
          f"{rec['head_err_p99_deg']:.2f} deg (max {rec['head_err_max_deg']:.2f}); scan p50 {rec['scan_ms_p50']:.2f} "
          f"p99 {rec['scan_ms_p99']:.2f} max {rec['scan_ms_max']:.1f} ms; estimator CPU "
          f"{rec['estimator_cpu_per_sim_s']:.3f} core per simulated second (whole process, simulator included: "
          f"{rec['process_cpu_per_sim_s']:.3f}); static cells inside forklifts now {in_forklifts}, on forklift "
          f"tracks {on_tracks}, > 0.2 m from any true structure {ghosts}; loops 0 accepted, 0 false (lifelong mode "
          f"closes none); {s.keyframes} keyframes; {s.dynamic_points_total} points labelled dynamic", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rec, fh, indent=2)


if __name__ == "__main__":
    main()
