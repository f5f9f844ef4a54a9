"""Sweeps: configurations x seeds, run through any ``concurrent.futures.Executor``, stored one record per run.

A sweep file (TOML) names the estimators, scenarios and seeds, fixed overrides (``[set]``), a grid of overrides
(``[grid]``: every key a list; the cartesian product is taken) and/or a list of override tables (``[[configs]]``)::

    estimators = ["dead-reckoning"]        # or "all": every registered estimator
    scenarios = ["grid"]
    seeds = 10                             # 0..9; or a list [0, 4, 7]; or {start = 100, count = 10}
    [set]
    steps = 50
    [grid]
    landmarks = [25, 50, 100]
    "sensor.range_std_m" = [0.05, 0.2]

Every expanded run config is validated by constructing its scenario and estimator configs *before* any run starts;
an unknown key or invalid value raises ValueError naming the key and the table it came from.

The result store is ``DIR/results.jsonl``: one JSON record per (config hash, seed), each appended with a single
``write`` on an ``O_APPEND`` descriptor and ``fsync``-ed before the next, and carrying a checksum of its own content.
On (re)start every line is checked; a corrupt or partial line is reported, moved to ``DIR/quarantine.jsonl`` (never
silently dropped) and its run is done again. Finished runs are skipped, so an interrupted sweep resumes where it
stopped. Only the submitting process writes the store, so it is safe with any executor, including Dask.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import hashlib
import itertools
import json
import math
import os
import signal
import socket
import sys
import time
import tomllib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam2d.config import split_overrides, to_dict, with_overrides
from slam2d.io.atomic import exclusive, write_text_atomic
from slam2d.io.json_text import json_ready
from slam2d.lab.registry import estimator_names, get_spec, make_config
from slam2d.lab.store import QUARANTINE_FILE as QUARANTINE_FILE
from slam2d.lab.store import STORE_FILE as STORE_FILE
from slam2d.lab.store import ResultStore as ResultStore
from slam2d.lab.store import StoreProblem as StoreProblem
from slam2d.sim.scenarios import ScenarioConfig

PLAN_FILE = "plan.json"
LOCK_FILE = ".lock"
MAX_SWEEP_FILE_BYTES = 16 * 2**20
#: a sweep's size: seeds, configurations (estimators x scenarios x configs x grid) and runs (their product) at most;
#: a typo such as ``seeds = 1000000000`` is refused at once instead of hanging while the plan is expanded
MAX_SWEEP_SEEDS, MAX_SWEEP_CONFIGS, MAX_SWEEP_RUNS = 100_000, 10_000, 1_000_000

TOP_KEYS = {
    "name": "a label for the sweep (string)",
    "description": "free text",
    "estimators": 'list of estimator names, or "all"',
    "scenarios": "list of scenario names",
    "seeds": "number of seeds, a list of seeds, or {start, count}",
    "set": "table of overrides applied to every run",
    "grid": "table of override -> list of values (cartesian product)",
    "configs": "array of override tables (each one is a configuration)",
}


# ----------------------------------------------------------------------------------------------- configurations
@dataclass(frozen=True)
class RunSpec:
    """One configuration of a sweep: estimator, scenario, overrides (JSON-able). The seed is separate."""

    estimator: str
    scenario: str
    overrides: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"estimator": self.estimator, "scenario": self.scenario, "overrides": dict(self.overrides)}

    @property
    def key(self) -> str:
        """Stable content hash of the configuration (16 hex digits)."""
        blob = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def label(self) -> str:
        ov = ", ".join(f"{k}={v}" for k, v in sorted(self.overrides.items()))
        return f"{self.estimator} on {self.scenario}" + (f" ({ov})" if ov else "")


@dataclass(frozen=True)
class SweepPlan:
    """An expanded sweep: every configuration and the seeds each runs with."""

    name: str
    specs: tuple[RunSpec, ...]
    seeds: tuple[int, ...]

    def jobs(self) -> list[tuple[RunSpec, int]]:
        return [(s, seed) for s in self.specs for seed in self.seeds]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "seeds": list(self.seeds),
                "configs": [{"key": s.key, **s.to_dict()} for s in self.specs]}


def resolve_spec(spec: RunSpec) -> tuple[ScenarioConfig, dict[str, Any], Any]:
    """Build a run's scenario config, its estimator-only overrides and the estimator config (validates all).

    Keys route as in :func:`slam2d.lab.runner.run_named`: a key the scenario knows goes to the scenario (and the
    estimator inherits it through the log's metadata); ``estimator.KEY`` sets only the estimator's copy;
    ``scenario.KEY`` only the scenario's.
    """
    est_spec = get_spec(spec.estimator)
    est_only = {k.split(".", 1)[1]: v for k, v in spec.overrides.items() if k.startswith("estimator.")}
    rest = {k.split(".", 1)[1] if k.startswith("scenario.") else k: v for k, v in spec.overrides.items()
            if not k.startswith("estimator.")}
    if "name" in rest:
        raise ValueError("override 'name' is not allowed: choose scenarios with the 'scenarios' list")
    scen_over, est_over = split_overrides(rest, ScenarioConfig, est_spec.config_cls)
    scen = with_overrides(ScenarioConfig(name=spec.scenario), scen_over)
    est_all = {**est_over, **est_only}
    meta = {"motion": to_dict(scen.motion), "sensor": to_dict(scen.sensor)}
    est_cfg = make_config(spec.estimator, est_all, meta)
    return scen, est_all, est_cfg


def _flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"sensor": {"range_std_m": 1}}`` -> ``{"sensor.range_std_m": 1}`` (TOML sub-tables become dotted keys)."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _check_value(where: str, v: Any) -> None:
    if isinstance(v, bool | int | float | str):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{where}: value must be finite (got {v!r})")
        return
    raise ValueError(f"{where}: value must be a number, string or boolean (got {type(v).__name__} {v!r})")


def _parse_seeds(v: Any, source: str) -> tuple[int, ...]:
    if isinstance(v, bool):
        raise ValueError(f"{source}: 'seeds' must be a count, a list of integers or {{start, count}} (got {v!r})")
    if isinstance(v, int):
        if not 1 <= v <= MAX_SWEEP_SEEDS:
            raise ValueError(f"{source}: 'seeds' count must be in 1..{MAX_SWEEP_SEEDS} (got {v})")
        return tuple(range(v))
    if isinstance(v, list):
        if not v or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in v):
            raise ValueError(f"{source}: 'seeds' list must be non-empty non-negative integers (got {v!r})")
        if len(set(v)) != len(v):
            raise ValueError(f"{source}: 'seeds' list has duplicates: {v!r}")
        if len(v) > MAX_SWEEP_SEEDS or max(v) > 2**63 - 1:
            raise ValueError(f"{source}: 'seeds' list must hold at most {MAX_SWEEP_SEEDS} seeds below 2**63")
        return tuple(v)
    if isinstance(v, Mapping):
        unknown = sorted(set(v) - {"start", "count"})
        if unknown:
            raise ValueError(f"{source}: unknown key(s) {unknown} in 'seeds'; valid keys: ['count', 'start']")
        start, count = v.get("start", 0), v.get("count", 0)
        for n, x in (("seeds.start", start), ("seeds.count", count)):
            if not isinstance(x, int) or isinstance(x, bool) or x < (1 if n == "seeds.count" else 0):
                raise ValueError(f"{source}: '{n}' must be an integer >= {1 if n == 'seeds.count' else 0} (got {x!r})")
        if count > MAX_SWEEP_SEEDS:
            raise ValueError(f"{source}: 'seeds.count' must be <= {MAX_SWEEP_SEEDS} (got {count})")
        if start + count > 2**63:
            raise ValueError(f"{source}: 'seeds.start' + 'seeds.count' must be <= 2**63 (seeds are 64-bit)")
        return tuple(range(start, start + count))
    raise ValueError(f"{source}: 'seeds' must be a count, a list of integers or {{start, count}} (got {v!r})")


def _parse_names(data: Mapping[str, Any], key: str, valid: Sequence[str], source: str,
                 default: list[str] | None = None) -> list[str]:
    v = data.get(key, default)
    if v is None:
        raise ValueError(f"{source}: missing required key '{key}' ({TOP_KEYS[key]})")
    if v == "all":
        return list(valid)
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, list) or not v or not all(isinstance(s, str) for s in v):
        raise ValueError(f"{source}: '{key}' must be a non-empty list of names (got {v!r})")
    bad = [s for s in v if s not in valid]
    if bad:
        raise ValueError(f"{source}: '{key}' has unknown name(s) {bad}; valid: {sorted(valid)}")
    if len(set(v)) != len(v):
        raise ValueError(f"{source}: '{key}' has duplicates: {v!r}")
    return list(v)


def parse_sweep(data: Mapping[str, Any], source: str = "sweep") -> SweepPlan:
    """Expand and validate a sweep description (the parsed TOML). Raises ValueError naming the offending key."""
    from slam2d.sim.scenarios import SCENARIOS

    unknown = sorted(set(data) - set(TOP_KEYS))
    if unknown:
        raise ValueError(f"{source}: unknown key(s) {unknown}; valid keys: {sorted(TOP_KEYS)}")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise ValueError(f"{source}: 'name' must be a string (got {name!r})")
    estimators = _parse_names(data, "estimators", estimator_names(), source)
    scenarios = _parse_names(data, "scenarios", sorted(SCENARIOS), source, default=["room"])
    seeds = _parse_seeds(data.get("seeds", 1), source)

    # origin of each override key, so that errors can name the table it came from
    fixed_raw = data.get("set", {})
    if not isinstance(fixed_raw, Mapping):
        raise ValueError(f"{source}: 'set' must be a table of overrides (got {fixed_raw!r})")
    fixed = _flatten(fixed_raw)
    for k, v in fixed.items():
        _check_value(f"{source}: set.{k}", v)
    grid_raw = data.get("grid", {})
    if not isinstance(grid_raw, Mapping):
        raise ValueError(f"{source}: 'grid' must be a table of override -> list of values (got {grid_raw!r})")
    grid = _flatten(grid_raw)
    for k, vals in grid.items():
        if not isinstance(vals, list) or not vals:
            raise ValueError(f"{source}: grid.{k} must be a non-empty list of values (got {vals!r})")
        for v in vals:
            _check_value(f"{source}: grid.{k}", v)
        if len({json.dumps(v) for v in vals}) != len(vals):
            raise ValueError(f"{source}: grid.{k} has duplicate values: {vals!r}")
    cfg_list_raw = data.get("configs", [{}])
    if not isinstance(cfg_list_raw, list) or not cfg_list_raw or not all(isinstance(c, Mapping) for c in cfg_list_raw):
        raise ValueError(f"{source}: 'configs' must be a non-empty array of tables ([[configs]])")
    cfg_list = [_flatten(c) for c in cfg_list_raw]
    for i, c in enumerate(cfg_list):
        for k, v in c.items():
            _check_value(f"{source}: configs[{i}].{k}", v)
            if k in grid:
                raise ValueError(f"{source}: key '{k}' is in both grid and configs[{i}]; give it in one place")

    grid_keys = sorted(grid)
    configs = len(estimators) * len(scenarios) * len(cfg_list) * math.prod(len(grid[k]) for k in grid_keys)
    if configs > MAX_SWEEP_CONFIGS or configs * len(seeds) > MAX_SWEEP_RUNS:
        raise ValueError(f"{source}: {configs} configurations x {len(seeds)} seeds is more than a sweep may hold "
                         f"(at most {MAX_SWEEP_CONFIGS} configurations and {MAX_SWEEP_RUNS} runs); split it")
    specs: list[RunSpec] = []
    seen: set[str] = set()
    for est in estimators:
        for scen in scenarios:
            for ci, c in enumerate(cfg_list):
                for values in itertools.product(*(grid[k] for k in grid_keys)):
                    origin = {k: f"set.{k}" for k in fixed}
                    origin.update({k: f"configs[{ci}].{k}" for k in c})
                    origin.update({k: f"grid.{k}" for k in grid_keys})
                    ov = {**fixed, **c, **dict(zip(grid_keys, values, strict=True))}
                    spec = RunSpec(est, scen, ov)
                    _validate(spec, origin, source)
                    if spec.key not in seen:
                        seen.add(spec.key)
                        specs.append(spec)
    return SweepPlan(name, tuple(specs), seeds)


def _validate(spec: RunSpec, origin: Mapping[str, str], source: str) -> None:
    """Construct the run's configs; on failure find the key responsible and name it with its table."""
    try:
        resolve_spec(spec)
        return
    except ValueError as e:
        whole = str(e)
    for k, v in spec.overrides.items():
        try:
            resolve_spec(RunSpec(spec.estimator, spec.scenario, {k: v}))
        except ValueError as e:
            raise ValueError(f"{source}: {origin.get(k, k)} = {v!r} (for {spec.estimator} on {spec.scenario}): {e}"
                             ) from None
    raise ValueError(f"{source}: invalid configuration {spec.label()}: {whole}")


def load_sweep(path: str | Path) -> SweepPlan:
    """Read and validate a sweep TOML file (see the module docstring for the schema)."""
    p = Path(path)
    if p.exists() and not p.is_file():
        raise ValueError(f"{p}: not a sweep file (a directory or a special file)")
    with p.open("rb") as f:
        raw = f.read(MAX_SWEEP_FILE_BYTES + 1)
    if len(raw) > MAX_SWEEP_FILE_BYTES:
        raise ValueError(f"{p}: larger than {MAX_SWEEP_FILE_BYTES // 2**20} MB; not a sweep file")
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ValueError(f"{p}: not valid TOML (not UTF-8 text at byte {e.start})") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{p}: not valid TOML: {e}") from None
    except RecursionError:
        raise ValueError(f"{p}: not valid TOML (nested too deeply)") from None
    return parse_sweep(data, str(p))


# ------------------------------------------------------------------------------------------------- the job
def evaluate_extra(result: Any, log: Any) -> dict[str, Any]:
    """Consistency and map metrics of one run beyond the runner's: per-step pose NEES and the map error.

    Pose NEES is left out (nan) for steps whose pose covariance is not positive definite (e.g. the start).
    """
    from slam2d.eval.consistency import pose_nees
    from slam2d.eval.mapping import map_error
    from slam2d.eval.trajectory import align_se2

    out: dict[str, Any] = {}
    if log.true_poses is not None and result.pose_covs is not None:
        covs = result.pose_covs[1:]
        series = np.full(covs.shape[0], np.nan)
        ok = np.all(np.linalg.eigvalsh(0.5 * (covs + covs.transpose(0, 2, 1))) > 0, axis=-1)
        if ok.any():
            series[ok] = pose_nees(result.poses[1:][ok], covs[ok], log.true_poses[1:][ok])
        out["pose_nees"] = [float(f"{v:.5g}") if np.isfinite(v) else None for v in series]
        out["pose_nees_mean"] = float(np.nanmean(series)) if ok.any() else None
    if log.true_landmarks is not None and len(result.final.landmarks):
        align = align_se2(result.trajectory, log.true_poses) if log.true_poses is not None else None
        me = map_error(result.final.landmarks, log.true_landmarks, max_distance_m=2.0, alignment=align)
        out.update(map_rmse_m=me.rmse_m, map_matched=me.matched, map_spurious=me.spurious, map_missed=me.missed)
    return out


def run_job(spec: Mapping[str, Any], seed: int) -> dict[str, Any]:
    """Run one (configuration, seed); never raises for a failing run (the record says ``status: error``).

    Top level of an installed module so that process pools and Dask workers can import it.
    """
    from slam2d.lab.runner import run_named
    from slam2d.sim.simulator import simulate

    t0 = time.perf_counter()
    rs = RunSpec(str(spec["estimator"]), str(spec["scenario"]), dict(spec.get("overrides", {})))
    rec: dict[str, Any] = {"key": rs.key, "seed": int(seed), "config": rs.to_dict(),
                           "host": socket.gethostname(), "pid": os.getpid()}
    try:
        scen, est_over, _ = resolve_spec(rs)
        log = simulate(scen, int(seed))
        result, record = run_named(rs.estimator, log=log, seed=int(seed),
                                   overrides={f"estimator.{k}": v for k, v in est_over.items()})
        record.update(evaluate_extra(result, log))
        rec.update(status="ok", metrics=record)
    except Exception as e:  # a failing run is a result too; the sweep goes on
        rec.update(status="error", error=f"{type(e).__name__}: {e}")
    rec["elapsed_s"] = time.perf_counter() - t0
    return json_ready(rec)  # type: ignore[no-any-return]


# ------------------------------------------------------------------------------------------------- running
def _worker_init() -> None:
    # Ctrl-C goes to the whole process group; only the parent should react (cancel, keep what is stored).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # and a worker never outlives the forkserver that forked it (which never outlives the sweep)
    from slam2d.lab._die_with_parent import die_with_parent

    die_with_parent()


@contextlib.contextmanager
def make_executor(workers: int | None = None, scheduler: str | None = None) -> Iterator[cf.Executor]:
    """A local process pool, or a Dask executor when a scheduler address is given (or ``DASK_SCHEDULER_ADDRESS``).

    Dask needs the ``cluster`` extra (``pip install slam2d[cluster]``) and workers that can import slam2d.
    """
    address = scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS") or None
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be >= 1 (got {workers})")
    if address:
        try:
            from dask.distributed import Client
        except ImportError:
            raise ValueError("a Dask scheduler was given but dask.distributed is not installed; "
                             "install the cluster extra: pip install 'slam2d[cluster]'") from None
        client = Client(address, timeout=30)
        try:
            yield client.get_executor(pure=False)
        finally:
            client.close()
        return
    import multiprocessing

    # forkserver: no fork() of a process that already runs threads (tqdm's monitor); the preload makes the
    # workers start with slam2d imported.
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["slam2d.lab._die_with_parent", "slam2d.lab.sweep"])
    ex = cf.ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1, mp_context=ctx,
                                initializer=_worker_init)
    try:
        yield ex
    finally:
        ex.shutdown(wait=True, cancel_futures=True)


@dataclass
class SweepSummary:
    """What a call to :func:`run_sweep` did."""

    total: int
    already_done: int
    ran: int = 0
    errors: int = 0
    failed: list[str] = field(default_factory=list)
    problems: list[StoreProblem] = field(default_factory=list)
    interrupted: bool = False

    @property
    def complete(self) -> bool:
        return not self.failed and not self.interrupted and self.already_done + self.ran == self.total


def run_sweep(
    plan: SweepPlan,
    out_dir: str | Path,
    executor: cf.Executor,
    *,
    progress: bool | None = None,
    max_in_flight: int | None = None,
    report: Callable[[str], None] | None = None,
    on_record: Callable[[dict[str, Any]], None] | None = None,
) -> SweepSummary:
    """Run every (config, seed) of ``plan`` not yet in the store at ``out_dir``; store each record as it arrives.

    ``progress=None`` shows a bar (with ETA) when stderr is a terminal. At most ``max_in_flight`` runs are submitted
    at a time (default 64), so an interrupt cancels quickly. On KeyboardInterrupt the pending runs are cancelled,
    what is stored stays stored, and the summary says ``interrupted`` (the caller decides the exit code).
    """
    say = report or (lambda msg: print(msg, file=sys.stderr))
    store = ResultStore(out_dir)
    store.directory.mkdir(parents=True, exist_ok=True)
    with exclusive(store.directory / LOCK_FILE, f"another sweep is writing to {store.directory}"):
        return _run_locked(plan, store, executor, say, progress, max_in_flight, on_record)


def _run_locked(plan: SweepPlan, store: ResultStore, executor: cf.Executor, say: Callable[[str], None],
                progress: bool | None, max_in_flight: int | None,
                on_record: Callable[[dict[str, Any]], None] | None) -> SweepSummary:
    done, problems = store.scan()
    for p in problems:
        say(f"store {store.path}: line {p.line}: {p.reason}; moved to {QUARANTINE_FILE}, its run will be redone")
    store.quarantine(problems)
    _write_plan(store.directory / PLAN_FILE, plan)
    jobs = plan.jobs()
    pending = [(s, seed) for s, seed in jobs if (s.key, seed) not in done]
    summary = SweepSummary(total=len(jobs), already_done=len(jobs) - len(pending), problems=problems)
    say(f"sweep {plan.name}: {len(jobs)} runs ({len(plan.specs)} configs x {len(plan.seeds)} seeds); "
        f"{summary.already_done} already stored, {len(pending)} to run")
    if not pending:
        return summary
    bar = _bar(len(jobs), summary.already_done, progress)
    window = max_in_flight or 64
    queue = iter(pending)
    in_flight: dict[cf.Future[dict[str, Any]], tuple[RunSpec, int]] = {}
    store.open()
    try:
        while True:
            for s, seed in itertools.islice(queue, max(0, window - len(in_flight))):
                in_flight[executor.submit(run_job, s.to_dict(), seed)] = (s, seed)
            if not in_flight:
                break
            finished, _ = cf.wait(list(in_flight), return_when=cf.FIRST_COMPLETED)
            for fut in finished:
                s, seed = in_flight.pop(fut)
                try:
                    rec = fut.result()
                except Exception as e:  # infrastructure failure (worker lost for good, pool broken): not stored
                    summary.failed.append(f"{s.label()} seed {seed}: {type(e).__name__}: {e}")
                    continue
                store.append(rec)
                summary.ran += 1
                summary.errors += rec.get("status") != "ok"
                if bar is not None:
                    bar.update(1)
                if on_record is not None:
                    on_record(rec)
    except KeyboardInterrupt:
        summary.interrupted = True
        for fut in in_flight:
            fut.cancel()
        say(f"interrupted: {summary.already_done + summary.ran} of {len(jobs)} runs stored in {store.path}; "
            "run the same command again to finish the rest")
    finally:
        store.close()
        if bar is not None:
            bar.close()
    if summary.failed:
        say(f"{len(summary.failed)} runs did not complete (not stored; re-run to retry); first: {summary.failed[0]}")
    return summary


def _bar(total: int, initial: int, enabled: bool | None) -> Any:
    show = sys.stderr.isatty() if enabled is None else enabled
    if not show:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="run", file=sys.stderr, smoothing=0.1)


def _write_plan(path: Path, plan: SweepPlan) -> None:
    write_text_atomic(path, json.dumps(plan.to_dict(), indent=1, sort_keys=True) + "\n")
