"""Experiments over every registered estimator: ``scaling`` (time per step vs map size) and ``consistency`` (NEES).

Both take the estimators from :func:`slam2d.lab.registry.estimator_names` unless told otherwise, so a back end
appears in them as soon as it registers itself. Results are plain JSON-ready dicts (the CLI saves them and
``slam2d report`` draws them).

Scaling method. The ``grid`` scenario with ``landmarks = N`` places N landmarks 4 m apart and drives a circle of
radius 0.35 x the grid's extent; the sensor sees a roughly constant number of landmarks per step, so the number of
observations per step stays about the same while the map grows with the circle's length. Each run is long enough
for one lap plus a margin (the map is then complete), and the time per step is the median over the last third of
the steps of this process's CPU time (``time.process_time``, all its threads), so that other programs sharing the
cores do not inflate it; the wall-clock median is kept as ``wall_step_ms_median``. The fitted log-log slope of that
time against the number of landmarks *in the estimate* (mapped) is the quantity the lesson's claims are about; the
slope against N is reported too.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from slam2d.eval.consistency import chi2_band, monte_carlo_consistency
from slam2d.lab.registry import estimator_names

#: what the lesson claims for the per-step cost in the number N of mapped landmarks (M particles), as
#: (text, exponent); matched on the estimator's registered name
CLAIMS: tuple[tuple[Callable[[str], bool], str, float | None], ...] = (
    (lambda n: n == "dead-reckoning", "O(1): ignores landmarks", 0.0),
    (lambda n: n.startswith("ekf"), "O(N^2): dense covariance update", 2.0),
    (lambda n: n.startswith("fastslam"), "O(M*N): per-particle maps copied on resampling", 1.0),
    (lambda n: "graph" in n or n.startswith(("isam", "gn", "lm")), "sparse: well below O(N^2)", None),
)


def claim_for(name: str) -> tuple[str, float | None]:
    """The lesson's complexity claim for a registered estimator name (text, exponent or None)."""
    for match, text, exponent in CLAIMS:
        if match(name):
            return text, exponent
    return "no claim recorded", None


def fit_loglog_slope(x: Sequence[float], y: Sequence[float]) -> float:
    """Least-squares slope of log(y) against log(x) over the positive pairs (nan with fewer than 2 distinct x)."""
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    ok = (xa > 0) & (ya > 0) & np.isfinite(xa) & np.isfinite(ya)
    if np.unique(xa[ok]).size < 2:
        return float("nan")
    return float(np.polyfit(np.log(xa[ok]), np.log(ya[ok]), 1)[0])


def _lap_steps(landmarks: int, overrides: dict[str, Any], seed: int) -> int:
    """Steps for one lap of the grid scenario's circle (from its own layout) plus 15 %."""
    from slam2d.config import with_overrides
    from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig

    cfg = with_overrides(ScenarioConfig(name="grid"), {**overrides, "landmarks": landmarks}).resolved()
    layout = SCENARIOS["grid"].build(cfg, np.random.default_rng(seed))
    wp = np.vstack([layout.waypoints, layout.waypoints[:1]])
    perimeter = float(np.sum(np.hypot(*np.diff(wp, axis=0).T)))
    assert cfg.speed_mps is not None and cfg.dt_s is not None
    return math.ceil(1.15 * perimeter / (cfg.speed_mps * cfg.dt_s)) + 10


def scaling(
    estimators: Sequence[str] | None = None,
    landmarks: Sequence[int] = (100, 400, 1600, 6400),
    *,
    seed: int = 0,
    steps: int | None = None,
    overrides: dict[str, Any] | None = None,
    max_run_s: float = 120.0,
    blas_threads: int | None = 1,
    report: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Time per step vs number of landmarks for each estimator on the ``grid`` scenario; fitted log-log slopes.
    Back ends that need lidar scans are listed under ``skipped`` (the grid has none).

    ``steps=None`` runs one lap plus 15 % for each N. ``overrides`` go to the scenario/estimator; by default
    ``dt_s = 0.5`` (0.75 m per step, so laps of the large grids stay affordable). An estimator stops at the first N
    whose run takes longer than ``max_run_s``. Besides the least-squares slope over all N, the slope between the two
    largest maps is reported: fixed per-step costs flatten the curve at small N, so the end slope is the better
    estimate of the asymptotic exponent.
    Runs are serial on purpose: timings from parallel runs on shared cores would disturb each other. BLAS is
    limited to ``blas_threads`` threads while timing (None: leave it alone): the claims are about operation counts,
    and on a busy machine OpenBLAS's spinning worker threads multiplied the EKF's per-step CPU time by ~10 (measured:
    3.9 ms single-threaded vs 44 ms with 2 threads at 323 mapped landmarks on a loaded 2-core box).
    """
    from threadpoolctl import threadpool_limits

    from slam2d.lab.registry import get_spec, make_estimator
    from slam2d.lab.runner import run
    from slam2d.sim.simulator import simulate, spawn_streams

    say = report or (lambda msg: None)
    names = list(estimators) if estimators is not None else estimator_names()
    base = {"dt_s": 0.5, **(overrides or {})}
    rows: list[dict[str, Any]] = []
    fits: dict[str, dict[str, Any]] = {}
    skipped: dict[str, str] = {}
    for name in names:
        if get_spec(name).needs == "scans":  # the grid has no walls: it would time dead reckoning under its name
            skipped[name] = "needs lidar scans; the grid scenario has landmarks and no walls"
            say(f"scaling {name}: skipped ({skipped[name]})")
            continue
        mine: list[dict[str, Any]] = []
        for n in sorted(landmarks):
            t_steps = steps or _lap_steps(n, base, seed)
            log = simulate("grid", seed, **{**base, "landmarks": n, "steps": t_steps})
            est = make_estimator(name, None, log.metadata)
            mapped = np.zeros(t_steps, dtype=np.int64)
            cpu = np.zeros(t_steps + 1)

            def on_step(i: int, snap: Any, _m: np.ndarray = mapped, _c: np.ndarray = cpu) -> None:
                _c[i] = time.process_time()
                _m[i - 1] = len(snap.landmarks)

            t0 = time.perf_counter()
            cpu[0] = time.process_time()
            with threadpool_limits(limits=blas_threads, user_api="blas"):
                res = run(est, log, rng=spawn_streams(seed)["estimator"], on_step=on_step, progress=False)
            wall = time.perf_counter() - t0
            tail = slice(2 * t_steps // 3, None)
            step_cpu = np.diff(cpu)
            obs_per_step = np.bincount(log.obs_step, minlength=t_steps + 1)[1:]
            row = {
                "estimator": name, "landmarks": int(n), "steps": int(t_steps),
                "step_ms_median": float(np.median(step_cpu[tail]) * 1e3),
                "step_ms_mean": float(np.mean(step_cpu[tail]) * 1e3),
                "wall_step_ms_median": float(np.median(res.step_s[tail]) * 1e3),
                "mapped": float(np.mean(mapped[tail])),
                "obs_per_step": float(np.mean(obs_per_step[tail])),
                "run_s": wall, "ate_rmse_m": float(res.metrics.get("ate_rmse_m", float("nan"))),
            }
            rows.append(row)
            mine.append(row)
            say(f"scaling {name}: N={n} mapped={row['mapped']:.0f} step={row['step_ms_median']:.3f} ms "
                f"({t_steps} steps, {wall:.1f} s)")
            if wall > max_run_s:
                say(f"scaling {name}: stopping after N={n} (run took {wall:.0f} s > {max_run_s:.0f} s)")
                break
        text, exponent = claim_for(name)
        fits[name] = {
            "slope_vs_mapped": fit_loglog_slope([r["mapped"] for r in mine], [r["step_ms_median"] for r in mine]),
            "slope_vs_landmarks": fit_loglog_slope([r["landmarks"] for r in mine],
                                                   [r["step_ms_median"] for r in mine]),
            "end_slope_vs_mapped": fit_loglog_slope([r["mapped"] for r in mine[-2:]],
                                                    [r["step_ms_median"] for r in mine[-2:]]),
            "claim": text, "claim_exponent": exponent, "points": len(mine),
        }
    return {"experiment": "scaling", "scenario": "grid", "seed": seed, "overrides": base, "blas_threads": blas_threads,
            "rows": rows, "fits": fits, "skipped": skipped}


def consistency(
    estimators: Sequence[str] | None = None,
    *,
    scenario: str = "room",
    seeds: int = 20,
    steps: int | None = 200,
    overrides: dict[str, Any] | None = None,
    probability: float = 0.95,
    executor: Any = None,
    report: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Pose NEES averaged over ``seeds`` Monte-Carlo runs per step, against the two-sided chi-square band.

    Estimators whose snapshots carry no pose covariance are listed as skipped. ``executor`` (any
    ``concurrent.futures.Executor``) spreads the runs; default is serial. Landmark NEES is not computed: estimated
    landmark ids are the estimator's own under data association, so the error to the true landmark is not defined
    without a matching step that would itself bias the statistic.
    """
    from slam2d.lab.sweep import RunSpec, resolve_spec, run_job

    say = report or (lambda msg: None)
    if seeds < 2:
        raise ValueError(f"seeds must be >= 2 for a Monte-Carlo average (got {seeds})")
    names = list(estimators) if estimators is not None else estimator_names()
    ov = {**(overrides or {}), **({"steps": steps} if steps is not None else {})}
    out: dict[str, Any] = {"experiment": "consistency", "scenario": scenario, "seeds": seeds, "overrides": ov,
                           "probability": probability, "results": {}, "skipped": {}}
    for name in names:
        spec = RunSpec(name, scenario, ov)
        resolve_spec(spec)  # fail on a bad override before running anything
        args = [spec.to_dict()] * seeds, list(range(seeds))
        recs = list(executor.map(run_job, *args)) if executor is not None else [run_job(*a) for a in zip(*args,
                                                                                                           strict=True)]
        bad = [r for r in recs if r["status"] != "ok"]
        if bad:
            out["skipped"][name] = f"{len(bad)} runs failed; first: {bad[0]['error']}"
            continue
        series = [r["metrics"].get("pose_nees") for r in recs]
        if any(s is None for s in series):
            out["skipped"][name] = "no pose covariance in its estimates"
            say(f"consistency {name}: skipped (no pose covariance)")
            continue
        vals = np.array([[np.nan if v is None else v for v in s] for s in series], dtype=np.float64)
        summ = monte_carlo_consistency(vals, dof=3, probability=probability)
        band = chi2_band(3, seeds, probability)
        out["results"][name] = {
            "mean_nees": [None if not np.isfinite(v) else float(v) for v in summ.mean],
            "band": [band.low, band.high], "fraction_inside": summ.fraction_inside,
            "overall_mean": summ.overall_mean,
            "ate_rmse_m_mean": float(np.mean([r["metrics"]["ate_rmse_m"] for r in recs])),
        }
        say(f"consistency {name}: mean NEES {summ.overall_mean:.2f} (band {band.low:.2f}..{band.high:.2f} per "
            f"step), {100 * summ.fraction_inside:.0f} % of steps inside")
    return out
