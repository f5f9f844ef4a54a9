"""FastSLAM 2.0 pose NEES: the particle covariance against the linearised one, and what each does to the estimate.

Monte-Carlo over simulated runs with known ids (the set-up of tests/consistency/test_pose_nees.py): per scenario and
reported covariance (``FastSLAMConfig.pose_cov``), the share of steps whose mean pose NEES lies in the two-sided 95 %
chi-square band, the mean NEES, the same with the assumed motion noise x0.1 (must fail), the RMS position error
of the estimate at every step and the mean ATE (SE(2)-aligned). The estimate (hence ATE) must not depend on
``pose_cov``: the option changes only the reported covariance. Also prints the decomposition behind the linearised
covariance: E[d d^T] for d = FastSLAM's mean pose minus EKF-SLAM's against E[P_ekf - C] (C: particle covariance).

    python benchmarks/fastslam_nees.py                      # 30 seeds x 200 steps, room and loop (~15 min, 2 cores)
    python benchmarks/fastslam_nees.py --seeds 10 --steps 100
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from slam2d.eval.consistency import monte_carlo_consistency, pose_error
from slam2d.eval.trajectory import ate
from slam2d.lab.registry import make_estimator
from slam2d.log import Log
from slam2d.sim.simulator import simulate


def run(name: str, logs: list[Log], overrides: dict[str, Any], steps: int) -> dict[str, np.ndarray]:
    """Per run and step: the pose error (R,T,3), the reported covariance (R,T,3,3) and the ATE per run (R,)."""
    err = np.zeros((len(logs), steps, 3))
    cov = np.zeros((len(logs), steps, 3, 3))
    ates = np.zeros(len(logs))
    for r, log in enumerate(logs):
        est = make_estimator(name, overrides, log.metadata)
        est.reset(log.initial_pose, rng=np.random.default_rng(1000 + r))
        poses = np.zeros((steps, 3))
        for t, step in enumerate(log.head(steps)):
            est.step(step)
            snap = est.estimate()
            assert snap.pose_cov is not None
            poses[t] = snap.pose
            err[r, t] = pose_error(snap.pose, log.true_poses[t + 1])
            cov[r, t] = snap.pose_cov
        ates[r] = ate(poses, log.true_poses[1:steps + 1]).rmse_m
    return {"err": err, "cov": cov, "ate": ates}


def summary(res: dict[str, np.ndarray]) -> str:
    e, c = res["err"], res["cov"]
    values = np.einsum("...i,...i->...", e, np.linalg.solve(c, e[..., None])[..., 0])
    s = monte_carlo_consistency(values, dof=3)
    rms = float(np.sqrt(np.mean(np.sum(e[..., :2] ** 2, axis=-1))))
    return (f"in band {s.fraction_inside:4.0%}  mean NEES {s.overall_mean:8.2f}  RMS pos err {rms:.4f} m  "
            f"mean ATE {float(np.mean(res['ate'])):.4f} m")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--scenarios", nargs="+", default=["room", "loop"])
    args = ap.parse_args()
    if args.seeds < 1 or args.steps < 1:
        ap.error(f"--seeds and --steps must be >= 1 (got {args.seeds}, {args.steps})")
    from slam2d.sim.scenarios import SCENARIOS

    bad = [s for s in args.scenarios if s not in SCENARIOS]
    if bad:
        ap.error(f"--scenarios: unknown {', '.join(bad)}; scenarios: {', '.join(sorted(SCENARIOS))}")
    for scenario in args.scenarios:
        logs = [simulate(scenario, seed, steps=args.steps) for seed in range(args.seeds)]
        print(f"== {scenario}: {args.seeds} seeds x {args.steps} steps, FastSLAM 2.0, 100 particles", flush=True)
        runs = {}
        for label, overrides in [("particles", {}), ("linearised", {"pose_cov": "linearised"}),
                                 ("particles x0.1", {"motion_noise_scale": 0.1}),
                                 ("linearised x0.1", {"pose_cov": "linearised", "motion_noise_scale": 0.1})]:
            t0 = time.process_time()
            runs[label] = run("fastslam2", logs, overrides, args.steps)
            print(f"  {label:16s} {summary(runs[label])}  ({time.process_time() - t0:.0f} s CPU)", flush=True)
        same = np.array_equal(runs["particles"]["err"], runs["linearised"]["err"])
        print(f"  estimates identical with either pose_cov: {same}")
        ekf = run("ekf", logs, {}, args.steps)
        print(f"  {'EKF-SLAM':16s} {summary(ekf)}")
        d = runs["particles"]["err"] - ekf["err"]
        for q, sl in enumerate(np.array_split(np.arange(args.steps), 4)):
            ddt = np.einsum("rti,rtj->ij", d[:, sl], d[:, sl]) / (d.shape[0] * sl.size)
            gap = (ekf["cov"][:, sl] - runs["particles"]["cov"][:, sl]).mean(axis=(0, 1))
            print(f"  quarter {q + 1}: diag E[d d^T] {np.diag(ddt)}  diag E[P_ekf - C] {np.diag(gap)}")


if __name__ == "__main__":
    main()
