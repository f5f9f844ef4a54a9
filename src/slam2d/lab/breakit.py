"""The "break-it" experiments: damage one ingredient of SLAM and watch what fails.

Each damage is a transformation of the recorded :class:`Log` (what the estimator is given) or of the estimator's
config, so every back end is broken in exactly the same way:

* ``no-loop-closure``: the estimator's ``loop_closure`` switch off (only back ends that have one);
* ``wrong-association``: half of the landmark ids reported with the observations are replaced by a wrong landmark's
  id (run with ``known`` association, the estimator trusts them: this is what a bad association layer does);
* ``few-landmarks``: only one landmark in five ever reports observations.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from slam2d.log import Log


def corrupt_association(log: Log, fraction: float, rng: np.random.Generator) -> Log:
    """A copy of ``log`` where ``fraction`` of the landmark observations carry a wrong (but valid) landmark id."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1] (got {fraction})")
    ids = log.obs_id.copy()
    real = np.flatnonzero(ids >= 0)
    known = np.unique(ids[real])
    if len(known) < 2 or len(real) == 0:
        return log
    pick = real[rng.random(len(real)) < fraction]
    # shift each picked id to a different landmark id (never the true one)
    offset = rng.integers(1, len(known), size=len(pick))
    pos = np.searchsorted(known, ids[pick])
    ids[pick] = known[(pos + offset) % len(known)]
    return dataclasses.replace(log, obs_id=ids, metadata={**log.metadata, "breakit": f"wrong-association:{fraction}"})


def thin_landmarks(log: Log, keep_fraction: float, rng: np.random.Generator) -> Log:
    """A copy of ``log`` in which only a random ``keep_fraction`` of the landmarks are ever observed."""
    if not 0.0 < keep_fraction <= 1.0:
        raise ValueError(f"keep_fraction must be in (0, 1] (got {keep_fraction})")
    ids = np.unique(log.obs_id[log.obs_id >= 0])
    n_keep = max(1, round(keep_fraction * len(ids)))
    kept = rng.choice(ids, size=n_keep, replace=False) if len(ids) else ids
    mask = np.isin(log.obs_id, kept) | (log.obs_id < 0)
    return dataclasses.replace(
        log,
        obs_step=log.obs_step[mask],
        obs_range_m=log.obs_range_m[mask],
        obs_bearing_rad=log.obs_bearing_rad[mask],
        obs_id=log.obs_id[mask],
        obs_descriptor=None if log.obs_descriptor is None else log.obs_descriptor[mask],
        metadata={**log.metadata, "breakit": f"few-landmarks:{keep_fraction}"},
    )


def forget_revisits(log: Log, gap_steps: int) -> Log:
    """A copy of ``log`` where a landmark re-seen after more than ``gap_steps`` steps carries a new id.

    With known association this is exactly "no loop closure": the robot never recognises a place it comes back to,
    so every back end maps the old landmarks a second time instead of correcting its drift.
    """
    if gap_steps < 1:
        raise ValueError(f"gap_steps must be >= 1 (got {gap_steps})")
    ids = log.obs_id.copy()
    real = np.flatnonzero(ids >= 0)
    if real.size == 0:
        return log
    span = int(ids[real].max()) + 1
    order = real[np.lexsort((log.obs_step[real], ids[real]))]  # grouped by id, then by time
    same = np.r_[False, ids[order][1:] == ids[order][:-1]]
    gap = np.r_[0, np.diff(log.obs_step[order])]
    new_visit = same & (gap > gap_steps)
    # visit number within each id: cumulative count of new visits, restarted at every id change
    visit = np.cumsum(new_visit)
    first = np.flatnonzero(~same)
    visit = visit - np.repeat(visit[first], np.diff(np.r_[first, order.size]))
    ids[order] = ids[order] + span * visit
    return dataclasses.replace(log, obs_id=ids, metadata={**log.metadata, "breakit": f"no-loop-closure:{gap_steps}"})


CONDITIONS = ("baseline", "no-loop-closure", "wrong-association", "few-landmarks")


def breakit_experiment(
    estimators: tuple[str, ...] = ("ekf", "fastslam", "graph"),
    seeds: tuple[int, ...] = tuple(range(10)),
    scenario: str = "loop",
    steps: int | None = None,
) -> list[dict[str, object]]:
    """ATE and map error of each estimator under each damage in :data:`CONDITIONS`, over ``seeds``.

    Every run uses ``known`` association, so the damage is the only difference. Returns one row per
    (estimator, condition) with means and standard deviations over the seeds.
    """
    import dataclasses as dc

    from slam2d.eval.mapping import map_error
    from slam2d.eval.trajectory import ate
    from slam2d.lab.registry import get_spec, make_config
    from slam2d.lab.runner import run
    from slam2d.sim.simulator import simulate, spawn_streams

    rows: list[dict[str, object]] = []
    for name in estimators:
        spec = get_spec(name)
        fields = {f.name for f in dc.fields(spec.config_cls)}
        per: dict[str, list[tuple[float, float]]] = {c: [] for c in CONDITIONS}
        for seed in seeds:
            base = simulate(scenario, seed, **({"steps": steps} if steps else {}))
            assert base.true_poses is not None and base.true_landmarks is not None
            damage = np.random.default_rng(np.random.SeedSequence([seed, 0xB4EA]))
            for cond in CONDITIONS:
                # known ids, trusted blindly: the damage must reach the back end, not be gated away
                over: dict[str, object] = ({"association.method": "known", "association.known_outlier_gate": False}
                                           if "association" in fields else {})
                log = base
                if cond == "no-loop-closure":
                    log = forget_revisits(base, 60)
                    if "loop_closure" in fields:
                        over["loop_closure"] = False
                elif cond == "wrong-association":
                    log = corrupt_association(base, 0.5, damage)
                elif cond == "few-landmarks":
                    log = thin_landmarks(base, 0.2, damage)
                est = spec.factory(make_config(name, over, log.metadata))
                res = run(est, log, rng=spawn_streams(seed)["estimator"])
                a = ate(res.trajectory, base.true_poses)
                m = map_error(res.final.landmarks, base.true_landmarks, alignment=a.alignment)
                per[cond].append((a.rmse_m, m.rmse_m))
        for cond, vals in per.items():
            arr = np.array(vals, dtype=np.float64)
            rows.append({
                "estimator": name, "condition": cond, "runs": len(vals),
                "ate_mean_m": float(np.mean(arr[:, 0])), "ate_std_m": float(np.std(arr[:, 0])),
                "map_rmse_mean_m": float(np.nanmean(arr[:, 1])) if np.any(np.isfinite(arr[:, 1])) else float("nan"),
            })
    return rows
