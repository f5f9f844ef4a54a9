"""Statistical power of the Monte-Carlo NEES tests at the sizes the test suite uses (the numbers in the comments of
tests/consistency/test_pose_nees.py and tests/unit/test_range_only_ekf.py).

Each part runs disjoint seed sets and prints, per set, the fraction of steps whose run-averaged pose NEES lies inside
the two-sided 95 % chi-square band and the overall mean NEES:

* ``overconfident``: the back ends with OVERCONFIDENT noise over the first 40 steps (30- and 20-run sets, seeds 0-89),
  and the honest ones over the same prefixes (seeds 30-89);
* ``band``: honest and mildly overconfident back ends (motion variances x0.5 / odometry information x2) over 200 steps
  in 20- and 30-run sets (seeds 0-59);
* ``range-only``: the range-only EKF with motion variances x0.1 and x1 over 40 and 150 steps (30-run sets, seeds 0-89).

Run (about 15 min of CPU per part): PYTHONPATH=src .venv/bin/python benchmarks/nees_power.py band
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import numpy as np

from slam2d.eval.consistency import monte_carlo_consistency, online_pose_nees
from slam2d.filters.range_only_ekf import RangeOnlyEKF
from slam2d.lab.registry import make_config, make_estimator
from slam2d.log import Log
from slam2d.sim.simulator import simulate

STEPS = 200
REPORTED: dict[str, dict[str, Any]] = {"fastslam2": {"pose_cov": "linearised"}}
OVERCONFIDENT: dict[str, dict[str, Any]] = {"ekf": {"motion_noise_scale": 0.1}, "graph": {"odometry_info_scale": 10.0},
                                            "fastslam2": {"motion_noise_scale": 0.1}}
MILD: dict[str, dict[str, Any]] = {"ekf": {"motion_noise_scale": 0.5}, "graph": {"odometry_info_scale": 2.0},
                                   "fastslam2": {"motion_noise_scale": 0.5}}


def pose_nees(name: str, logs: list[Log], seeds: list[int], overrides: dict[str, Any], steps: int) -> np.ndarray:
    """(runs, steps) pose NEES of back end ``name``; run of seed s uses estimator stream 1000 + s, as the test."""
    return np.stack([online_pose_nees(make_estimator(name, overrides, log.metadata), log,
                                      np.random.default_rng(1000 + seed), steps)
                     for log, seed in zip(logs, seeds, strict=True)])


def range_only_nees(logs: list[Log], seeds: list[int], motion_scale: float, steps: int) -> np.ndarray:
    """(runs, steps) pose NEES of the range-only EKF (run of seed s seeded with s, as the test)."""
    def ekf(log: Log) -> RangeOnlyEKF:
        cfg = make_config("range-only-ekf", None, log.metadata)
        return RangeOnlyEKF(dataclasses.replace(cfg, motion=cfg.motion.scaled(motion_scale)))
    return np.stack([online_pose_nees(ekf(log), log, np.random.default_rng(seed), steps)
                     for log, seed in zip(logs, seeds, strict=True)])


def report(label: str, values: np.ndarray, runs: int, steps: int) -> None:
    sets = [monte_carlo_consistency(values[a:a + runs, :steps], 3) for a in range(0, len(values) - runs + 1, runs)]
    inside = " ".join(f"{s.fraction_inside:4.0%}" for s in sets)
    means = " ".join(f"{s.overall_mean:5.2f}" for s in sets)
    band = sets[0].band
    print(f"{label:40s} {runs:2d} runs x {steps:3d} steps: inside {inside} | mean {means} | "
          f"band [{band.low:.2f}, {band.high:.2f}]", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", choices=["overconfident", "band", "range-only"])
    part = ap.parse_args().part
    if part == "range-only":
        seeds = list(range(90))
        logs = [simulate("room", s, steps=150) for s in seeds]
        for scale, steps in ((0.1, 40), (1.0, 150)):
            v = range_only_nees(logs, seeds, scale, steps)
            for n in sorted({40, steps}):
                report(f"room range-only-ekf motion x{scale}", v, 30, n)
        return
    for scenario in ("room", "loop"):
        seeds = list(range(90 if part == "overconfident" else 60))
        logs = [simulate(scenario, s, steps=STEPS) for s in seeds]
        for name in ("ekf", "graph", "fastslam2"):
            honest = REPORTED.get(name, {})
            if part == "overconfident":
                over = pose_nees(name, logs, seeds, {**honest, **OVERCONFIDENT[name]}, 40)
                ok = pose_nees(name, logs[30:], seeds[30:], honest, 40)
                for runs in (30, 20):
                    report(f"{scenario} {name} overconfident", over, runs, 40)
                    report(f"{scenario} {name} honest (seeds 30-89)", ok, runs, 40)
            else:
                for label, ov in (("honest", honest), ("mild", {**honest, **MILD[name]})):
                    v = pose_nees(name, logs, seeds, ov, STEPS)
                    for runs in (30, 20):
                        report(f"{scenario} {name} {label}", v, runs, STEPS)


if __name__ == "__main__":
    main()
