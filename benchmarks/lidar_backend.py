"""Lidar back end benchmark: accuracy and speed on the Radish logs, ATE and false loops in simulation.

    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_backend.py --json lidar_backend.json
    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_backend.py --logs intel --sim-seeds 0   # one log only
    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_backend.py --logs aces --sim-seeds 0 --set loop_queue=12
    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_backend.py --sim-seeds 0 --repeat 3   # timing: median of 3 runs

Per log (one process each, so that peak RSS is the log's own): Kümmerle relation errors (mean +- std, trans and
rot) of the default ``lidar`` estimator, per-scan latency p50/p99/max (one ``step`` + ``estimate``), the whole-log
real-time factor (log duration / processing time, finalize included) and peak RSS; also the translation error over
the relations less than 1 s apart alone (local accuracy; ``lidar_relations_check.py`` scores the same relations
with a raw-scan ICP and with odometry). ``--repeat N`` runs the logs N times, taking turns (a shared machine's speed
drifts within minutes, so each log's runs meet different moments): the timing columns are the medians, their range
is printed, and every other column must be identical between the runs (the results are deterministic; the benchmark
stops when they are not). ``--set FIELD=VALUE`` (repeatable) overrides a ``LidarSLAMConfig`` field on the logs and the
simulated drives, to measure how much a harmless change moves the relation error.
Latency and real-time factor are given twice: wall clock, and CPU time of the thread (what they are on a core of
their own; on a shared machine the wall clock also counts the waits for a core). Simulation: ATE of the lidar
estimator vs dead reckoning on room and warehouse, and accepted / false loops over ``--sim-seeds`` warehouse
seeds (identical aisles, a 1200-step drive that revisits them; the runner counts a loop false when its two poses
are truly > 16 m apart or its measurement is off the truth by > 1 m); and the drift along one aisle: the largest
error of the floor markers' estimated positions after a 150-step drive down an aisle with markers (warehouse
seed 3, ``tests/unit/test_lidar_markers.py``'s drive), where the aisle's walls say nothing along it.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import time
from typing import Any

import numpy as np

LOGS = ("aces", "intel", "fr079", "mit-csail")


def one_log(name: str, overrides: dict[str, str]) -> dict[str, Any]:
    from slam2d.cli.lidar import laser_outputs, load_laser_log
    from slam2d.lab.registry import make_estimator
    from slam2d.lab.runner import run

    log = load_laser_log(name)
    est = make_estimator("lidar", overrides)
    cpu: list[float] = []  # CPU time of each step + estimate: what the scan costs on a core of its own
    step, estimate = est.step, est.estimate

    def timed_step(s: Any) -> None:
        t = time.thread_time()
        step(s)
        cpu.append(time.thread_time() - t)

    def timed_estimate() -> Any:
        t = time.thread_time()
        out = estimate()
        if cpu:
            cpu[-1] += time.thread_time() - t
        return out

    est.step, est.estimate = timed_step, timed_estimate  # type: ignore[method-assign]
    t0, c0 = time.perf_counter(), time.thread_time()
    res = run(est, log, rng=np.random.default_rng(0), progress=False)
    total, total_cpu = time.perf_counter() - t0, time.thread_time() - c0
    cms = np.asarray(cpu) * 1e3
    rec: dict[str, Any] = {"log": name, "scans": log.num_steps + 1}
    laser_outputs(log, res.trajectory, rec)
    short = short_relation_error(log, res.trajectory)
    if short is not None:
        rec["rel_trans_short_mean_m"] = short
    ms = res.step_s * 1e3
    duration = float(log.stamps_s[-1] - log.stamps_s[0])
    d = res.final.diagnostics
    rec.update(latency_ms_p50=float(np.percentile(ms, 50)), latency_ms_p99=float(np.percentile(ms, 99)),
               latency_ms_max=float(ms.max()), processing_s=total, duration_s=duration,
               real_time_factor=duration / total, cpu_ms_p50=float(np.percentile(cms, 50)),
               cpu_ms_p99=float(np.percentile(cms, 99)), cpu_ms_max=float(cms.max()), processing_cpu_s=total_cpu,
               real_time_factor_cpu=duration / total_cpu,
               peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
               loops_accepted=d.loops_accepted, loops_rejected=d.loops_rejected,
               tracking_failures=d.dropped_observations)
    return rec


def short_relation_error(log: Any, trajectory: np.ndarray, span_s: float = 1.0) -> float | None:
    """Mean translational relation error over the relations less than ``span_s`` apart (the local accuracy, where
    loops hardly matter), or None when no relations file sits beside the log."""
    from dataclasses import replace

    from slam2d.cli.lidar import original_stamps
    from slam2d.eval.relations import read_relations, relation_errors
    from slam2d.io.carmen import relations_beside

    path = relations_beside(str(log.metadata["path"])) if "path" in log.metadata else None
    if path is None:
        return None
    rel = read_relations(path)
    m = np.abs(rel.stamps[:, 1] - rel.stamps[:, 0]) < span_s
    sub = replace(rel, stamps=rel.stamps[m], rel=rel.rel[m], lines=rel.lines[m])
    e = relation_errors(original_stamps(log), trajectory, sub, on_missing="skip").trans_m
    return float(np.mean(e)) if len(e) else None


#: the default warehouse drive (600 steps) never comes back to a place; at 1200 steps it revisits aisles from step
#: ~830 on, so loop candidates -- right and wrong ones among identical aisles -- are actually verified
SIM_STEPS = {"room": 450, "warehouse": 1200}


def sim(scenario: str, seed: int, overrides: dict[str, str]) -> dict[str, Any]:
    """Dead reckoning and the lidar estimator (with ``overrides``) on one simulated drive."""
    from slam2d.lab.runner import run_named

    out: dict[str, Any] = {"scenario": scenario, "seed": seed, "steps": SIM_STEPS[scenario]}
    for est in ("dead-reckoning", "lidar"):
        extra = overrides if est == "lidar" else {}
        _, rec = run_named(est, scenario, seed=seed, overrides={**extra, "steps": SIM_STEPS[scenario]},
                           progress=False)
        out[f"{est}_ate_m"] = rec["ate_rmse_m"]
        if est == "lidar":
            d = rec["estimator_config"]
            out.update(loops_accepted=rec.get("loops_accepted"), loops_false=rec.get("loops_false"),
                       step_ms_p99=rec["step_ms_p99"], loop_closure=d["loop_closure"])
    return out


def aisle_drift(overrides: dict[str, str]) -> float:
    """The largest error (m) of the floor markers' estimated positions after the 150-step aisle drive."""
    from slam2d.config import with_overrides
    from slam2d.graph.lidar import LidarSLAM, LidarSLAMConfig
    from slam2d.lab.runner import run
    from slam2d.sim.scenarios import ScenarioConfig
    from slam2d.sim.simulator import simulate
    from slam2d.sim.warehouse import WarehouseConfig

    log = simulate(ScenarioConfig(name="warehouse", steps=150, warehouse=WarehouseConfig(floor_markers=True)), seed=3)
    est = LidarSLAM(with_overrides(LidarSLAMConfig(), overrides))
    run(est, log, rng=np.random.default_rng(0), progress=False)
    assert est.graph is not None and log.true_markers is not None
    truth = log.true_markers[np.asarray(est.graph.marker_ids)]
    return float(np.abs(est.graph.markers - truth).max())


def machine_reference(calls: int = 100) -> dict[str, Any]:
    """The machine's speed on the back end's hot call, so that timings from different machines can be compared: the
    median CPU time of a fixed point-to-line ICP (180 points on a 1000-point room outline, exactly 10 iterations,
    one SciPy KD-tree query each) and of one such query alone."""
    import platform

    from slam2d.frontend.icp import ICPConfig, icp, prepare_target
    from slam2d.geometry import se2

    rng = np.random.default_rng(7)
    u = rng.uniform(0.0, 36.0, 1000)  # a 10 x 8 m rectangle's perimeter, unrolled
    outline = np.where((u < 10)[:, None], np.c_[u, 0 * u], np.where((u < 18)[:, None], np.c_[10 + 0 * u, u - 10],
                       np.where((u < 28)[:, None], np.c_[28 - u, 8 + 0 * u], np.c_[0 * u, 36 - u])))
    target = outline + rng.normal(0.0, 0.01, outline.shape)
    source = se2.transform_points(se2.inverse(np.array([0.1, -0.05, 0.03])), target[::5][:180])
    cfg = ICPConfig(max_iterations=10, tolerance=1e-100)  # no early stop: exactly 10 iterations
    prep = prepare_target(target, cfg)
    assert icp(source, prep, config=cfg).iterations == 10

    def cpu_ms(fn: Any) -> float:
        times = []
        for _ in range(calls):
            t = time.thread_time()
            fn()
            times.append(time.thread_time() - t)
        return float(np.median(times) * 1e3)

    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), model)
    except OSError:
        pass  # not Linux: platform's answer stands
    return {"cpu": model, "icp_10_iterations_ms": cpu_ms(lambda: icp(source, prep, config=cfg)),
            "kdtree_query_ms": cpu_ms(lambda: prep.tree.query(source, distance_upper_bound=1.0))}


#: the columns that measure the machine, not the estimator
TIMING = ("latency_ms_p50", "latency_ms_p99", "latency_ms_max", "processing_s", "real_time_factor", "cpu_ms_p50",
          "cpu_ms_p99", "cpu_ms_max", "processing_cpu_s", "real_time_factor_cpu", "peak_rss_mb")


def combine(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One record from repeated runs of a log: the timing columns' medians (each run's kept under ``timing_runs``);
    every other column must be the same in every run."""
    first = runs[0]
    for r in runs[1:]:
        for k in first.keys() | r.keys():
            if k not in TIMING and first.get(k) != r.get(k):
                raise SystemExit(f"{first['log']}: {k} differs between runs ({first.get(k)} vs {r.get(k)}): "
                                 "the estimator is not deterministic")
    out = dict(first)
    out.update({k: float(np.median([r[k] for r in runs])) for k in TIMING})
    out["runs"] = len(runs)
    out["timing_runs"] = [{k: r[k] for k in TIMING} for r in runs]
    return out


def _isolated(fn: Any, *args: Any) -> Any:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", default=",".join(LOGS), help="comma-separated Radish logs (default all four)")
    ap.add_argument("--sim-seeds", type=int, default=10, help="warehouse seeds for the false-loop count (default 10)")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each log, taking turns; timing = medians")
    ap.add_argument("--json", default=None, help="write all records as JSON")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a LidarSLAMConfig field on the logs and the simulated drives (repeatable), "
                         "e.g. loop_queue=12")
    args = ap.parse_args()
    from slam2d.config import parse_set_args
    from slam2d.lab.registry import make_config

    try:
        overrides = parse_set_args(args.set)
        make_config("lidar", overrides)  # an unknown field or bad value fails here, not in the first log's process
    except ValueError as e:
        ap.error(str(e))
    records: dict[str, Any] = {"logs": [], "sim": []}
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    if args.sim_seeds < 0:
        ap.error(f"--sim-seeds must be >= 0 (got {args.sim_seeds})")
    names = [n for n in args.logs.split(",") if n]
    # checked before the first log's minutes of work: every log is there, the JSON file can be written
    from slam2d.io.carmen import resolve_carmen

    for n in names:
        try:
            resolve_carmen(n)
        except FileNotFoundError as e:
            ap.error(f"--logs: {e}")
    if args.json:
        from slam2d.io.atomic import check_output

        try:
            check_output(args.json, "--json")
        except OSError as e:
            ap.error(f"{e.filename}: {e.strerror}")
    records["machine"] = ref = machine_reference()
    print(f"machine: {ref['cpu']}; reference ICP (10 iterations, 180 points on 1000) {ref['icp_10_iterations_ms']:.2f}"
          f" ms CPU, one KD-tree query of those points {ref['kdtree_query_ms']:.3f} ms", flush=True)
    per_log: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    for _ in range(args.repeat):  # taking turns: each log's runs meet different moments of the machine
        for name in names:
            per_log[name].append(_isolated(one_log, name, overrides))
    for name in names:
        r = combine(per_log[name])
        records["logs"].append(r)
        print(f"{name:10s} rel {r['rel_trans_mean_m']:.4f} +- {r['rel_trans_std_m']:.4f} m  "
              f"{r['rel_rot_mean_deg']:.3f} +- {r['rel_rot_std_deg']:.3f} deg (under 1 s apart "
              f"{r.get('rel_trans_short_mean_m', float('nan')):.4f} m) | latency p50 {r['latency_ms_p50']:.1f} "
              f"p99 {r['latency_ms_p99']:.1f} max {r['latency_ms_max']:.0f} ms (CPU p50 {r['cpu_ms_p50']:.1f} "
              f"p99 {r['cpu_ms_p99']:.1f} max {r['cpu_ms_max']:.0f}) | RTF {r['real_time_factor']:.1f}x "
              f"(CPU {r['real_time_factor_cpu']:.1f}x) | "
              f"RSS {r['peak_rss_mb']:.0f} MB | loops {r['loops_accepted']}/{r['loops_rejected']} rejected"
              + _spread(r), flush=True)
    runs = [("room", 0)] + [("warehouse", s) for s in range(args.sim_seeds)]
    for scen, seed in runs:
        r = sim(scen, seed, overrides)
        records["sim"].append(r)
        print(f"{scen:10s} seed {seed}: ATE lidar {r['lidar_ate_m']:.3f} m vs dead reckoning "
              f"{r['dead-reckoning_ate_m']:.3f} m, loops {r['loops_accepted']} (false {r['loops_false']})", flush=True)
    wh = [r for r in records["sim"] if r["scenario"] == "warehouse"]
    if wh:
        print(f"warehouse: {sum(r['loops_false'] or 0 for r in wh)} false loops in "
              f"{sum(r['loops_accepted'] or 0 for r in wh)} accepted over {len(wh)} seeds, mean ATE "
              f"{np.mean([r['lidar_ate_m'] for r in wh]):.3f} m")
    records["aisle_drift_m"] = aisle_drift(overrides)
    print(f"aisle with floor markers (seed 3, 150 steps): largest marker error {records['aisle_drift_m']:.3f} m")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=2, default=float)


def _spread(r: dict[str, Any]) -> str:
    """The range of the repeated runs' CPU p99 and real-time factor ("" for one run)."""
    t = r.get("timing_runs", [])
    if len(t) < 2:
        return ""
    p99, rtf = [x["cpu_ms_p99"] for x in t], [x["real_time_factor_cpu"] for x in t]
    return (f" | medians of {len(t)} runs: CPU p99 {min(p99):.1f}-{max(p99):.1f} ms, "
            f"RTF {min(rtf):.1f}-{max(rtf):.1f}x")


if __name__ == "__main__":
    main()
