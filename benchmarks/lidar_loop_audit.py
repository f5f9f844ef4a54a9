"""Audit of the lidar back end's loop decisions on warehouse seeds: every candidate that passed the scan gates, with
its error against the truth and the values every gate saw.

    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_loop_audit.py --seeds 0-4
    OPENBLAS_NUM_THREADS=1 python benchmarks/lidar_loop_audit.py --seeds 2 --set loop_static_radius_m=0   # old rule

Per seed (the benchmark's 1200-step drive): accepted / false loops (the runner's rule: truly > 16 m apart or > 1 m
off the truth), then one line per verified candidate: old and new step, accepted or not, error of the measured
relative pose against the truth along and across the old pose's heading, the error of the estimate's guess, and
the gate values (correlative score and ambiguity, ICP fitness, residual, sigma, chi-square, weakest-direction
support). A false loop whose along-heading error is large and across-heading error small slid along an aisle.
"""

from __future__ import annotations

import argparse
from collections.abc import Generator
from typing import Any

import numpy as np

from slam2d.geometry import se2
from slam2d.graph.lidar import LidarSLAM
from slam2d.graph.lidar_loops import LoopCheck
from slam2d.lab.registry import make_config
from slam2d.lab.runner import LOOP_TRUE_DISTANCE_M, LOOP_TRUE_ERROR_M, run
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import simulate, spawn_streams


class _Audited(LidarSLAM):
    """The lidar estimator, keeping every verified candidate's check and guess."""

    def reset(self, initial_pose: Any, *, rng: np.random.Generator) -> None:
        super().reset(initial_pose, rng=rng)
        self.verified: list[tuple[int, int, LoopCheck, Any]] = []

    def _check_stages(self, c: int, k: int, poses: Any, *args: Any, **kwargs: Any) -> Generator[str, None, LoopCheck]:
        chk = yield from super()._check_stages(c, k, poses, *args, **kwargs)
        if chk.ok:
            self.verified.append((self._kf_step[c], self._kf_step[k], chk, se2.between(poses[c], poses[k])))
        return chk


def audit(seed: int, overrides: dict[str, Any]) -> tuple[int, int]:
    log = simulate(ScenarioConfig(name="warehouse", steps=1200), seed)
    est = _Audited(make_config("lidar", overrides, log.metadata, has_ids=False))
    res = run(est, log, rng=spawn_streams(seed)["estimator"], progress=False)
    true = log.true_poses
    assert true is not None
    accepted = {(lp.a, lp.b) for lp in res.loops if lp.accepted}
    false = sum(float(np.hypot(*(true[a, :2] - true[b, :2]))) > LOOP_TRUE_DISTANCE_M
                or float(np.hypot(*se2.local(se2.between(true[a], true[b]), lp.T_a_b)[:2])) > LOOP_TRUE_ERROR_M
                for lp in res.loops if lp.accepted for a, b in [(lp.a, lp.b)])
    print(f"seed {seed}: {len(accepted)} accepted, {false} false", flush=True)
    for a, b, chk, guess in est.verified:
        t = se2.between(true[a], true[b])
        e, eg = se2.local(t, chk.transform), se2.local(t, guess)
        print(f"  {a:5d} -> {b:5d} {'accepted' if (a, b) in accepted else 'pending '} error along {e[0]:+.2f} across "
              f"{e[1]:+.2f} m (guess {eg[0]:+.2f} {eg[1]:+.2f}) | score {chk.score:.3f} ambiguity {chk.ambiguity:.3f} "
              f"fitness {chk.fitness:.3f} rmse {chk.rmse_m:.3f} sigma {chk.sigma_m:.3f} chi2 {chk.chi2:.2f} "
              f"support {chk.support:.0f}", flush=True)
    return len(accepted), int(false)


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    if not out:
        raise ValueError(text)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=_seeds, default="0-9", help="warehouse seeds, e.g. 0-4 or 2,3 (default 0-9)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a LidarSLAMConfig field (float values), e.g. loop_static_radius_m=0")
    args = ap.parse_args()
    try:
        overrides = {k: float(v) for k, _, v in (s.partition("=") for s in args.set)}
        make_config("lidar", overrides)  # an unknown field fails here, not after the first seeds
    except ValueError as e:
        ap.error(f"--set FIELD=VALUE (float values): {e}")
    tot = np.zeros(2, dtype=int)
    for seed in args.seeds:
        tot += audit(seed, overrides)
    print(f"total: {tot[0]} accepted, {tot[1]} false")


if __name__ == "__main__":
    main()
