"""FastSLAM cost per step versus particles M and map size N.

Claim checked: with every particle updated at once, a step costs ~O(M k) for k observations (known association, or
per-particle ML over the few landmarks near each particle) -- independent of N -- plus O(M N) only when resampling
copies the maps (and, for per-particle ML, one cheap O(M N) distance pass per step that picks the nearby landmarks).

Set-up: N landmarks spread uniformly over a square sized so that ~10 are within the 8 m sensor range; every particle
starts with all N landmarks in its map (noisy copies of the truth); the robot drives a circle near the centre and
sees the landmarks within range (~10) per step. Timings are medians over steps of this process's CPU time
(``time.process_time``: the machine is shared, wall-clock time would measure the neighbours). Prints a table,
µs per particle per observation (target <= 5), the cost of one resampling copy, and fitted log-log exponents.

    python benchmarks/fastslam.py            # full grid (~1-2 min on 2 cores)
    python benchmarks/fastslam.py --quick    # fewer steps
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from slam2d.association import AssociationConfig
from slam2d.filters.fastslam import FastSLAM, FastSLAMConfig, systematic_resample
from slam2d.geometry import compose
from slam2d.log import Observations, Step
from slam2d.models.motion import MotionNoise, sample_odometry
from slam2d.models.sensors import SensorConfig, sense_landmarks

SENSOR = SensorConfig()
VISIBLE = 10  # landmarks in view per step, on average


def world(n: int, rng: np.random.Generator) -> np.ndarray:
    side = math.sqrt(n * math.pi * SENSOR.max_range_m**2 / VISIBLE)
    return rng.uniform(-side / 2, side / 2, size=(n, 2))


def make_filter(m: int, lm: np.ndarray, version: int, method: str, rng: np.random.Generator) -> FastSLAM:
    cfg = FastSLAMConfig(particles=m, version=version, resample_threshold=0.0, sensor=SENSOR,
                         association=AssociationConfig(method=method))  # type: ignore[arg-type]
    est = FastSLAM(cfg)
    est.reset(np.zeros(3), rng=rng)
    n = len(lm)
    # benchmark set-up only: fill every particle's map directly instead of driving for thousands of steps
    if method == "known":
        for i in range(n):
            est._slot_for_id(i)
    p = est.particles
    p.ensure_capacity(n)
    p.lm_mean[:, :n] = lm + rng.normal(0, 0.05, size=(m, n, 2))
    p.lm_cov[:, :n] = np.diag([0.0025, 0.0025])
    p.tracks.hits[:, :n] = 10  # sighted ten times: confirmed
    p.lm_count[:] = n
    return est


def drive(steps: int, lm: np.ndarray, rng: np.random.Generator) -> list[Step]:
    noise = MotionNoise()
    u_true = np.array([0.3, 0.0, 0.1])
    pose = np.zeros(3)
    out = []
    for t in range(1, steps + 1):
        pose = compose(pose, u_true)
        z, ids, _ = sense_landmarks(pose, lm, np.arange(len(lm)), SENSOR, rng)
        out.append(Step(t, float(t), 1.0, sample_odometry(u_true, noise, rng),
                        Observations(z[:, 0], z[:, 1], ids)))
    return out


def time_steps(est: FastSLAM, steps: list[Step]) -> float:
    times = []
    for s in steps:
        t0 = time.process_time()
        est.step(s)
        times.append(time.process_time() - t0)
    return float(np.median(times[1:]))


def slope(x: list[float], y: list[float]) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps per configuration")
    args = ap.parse_args()
    n_steps = 8 if args.quick else 20
    ms, ns = [10, 100, 1000], [100, 1000]
    rows = []
    print(f"{'version':>7} {'assoc':>6} {'M':>5} {'N':>5} {'k':>5} {'ms/step':>9} {'us/(M k)':>9} "
          f"{'resample copy ms':>17}")
    for version in (1, 2):
        for method in ("known", "ml"):
            for n in ns:
                rng = np.random.default_rng(0)
                lm = world(n, rng)
                steps = drive(n_steps, lm, rng)
                k = float(np.mean([len(s.observations) for s in steps]))
                for m in ms:
                    est = make_filter(m, lm, version, "known" if method == "known" else "mahalanobis", rng)
                    dt = time_steps(est, steps)
                    # the O(M N) part: one resampling copy of every per-particle array
                    w = rng.dirichlet(np.ones(m))
                    t0 = time.process_time()
                    for _ in range(3):
                        est.particles.select(systematic_resample(w, rng))
                    copy = (time.process_time() - t0) / 3
                    rows.append((version, method, m, n, k, dt, copy))
                    print(f"{version:>7} {method:>6} {m:>5} {n:>5} {k:>5.1f} {dt * 1e3:>9.2f} "
                          f"{dt / (m * k) * 1e6:>9.2f} {copy * 1e3:>17.2f}", flush=True)

    print("\nfitted log-log exponents (time ~ M^a at fixed N, ~ N^b at fixed M; M from 100 to 1000):")
    for version in (1, 2):
        for method in ("known", "ml"):
            sel = [r for r in rows if r[0] == version and r[1] == method]
            a = [slope([100, 1000], [r[5] for r in sel if r[3] == n and r[2] in (100, 1000)]) for n in ns]
            b = [slope(ns, [r[5] for r in sel if r[2] == m]) for m in ms]
            print(f"  v{version} {method:>5}: step vs M: a = {a[0]:.2f} (N=100), {a[1]:.2f} (N=1000); "
                  f"step vs N: b = {', '.join(f'{x:.2f}' for x in b)} (M = {ms})")
    copies = [r for r in rows if r[0] == 1 and r[1] == "known"]
    a = slope([r[2] * r[3] for r in copies if r[2] >= 100], [r[6] for r in copies if r[2] >= 100])
    print(f"  resampling copy vs M*N (M >= 100): exponent {a:.2f}  (O(M N) predicts 1)")
    big = [r for r in rows if r[2] == 1000]
    print("\nµs per particle per observation at M = 1000 (target <= 5): "
          + ", ".join(f"v{r[0]} {r[1]} N={r[3]}: {r[5] / (r[2] * r[4]) * 1e6:.2f}" for r in big))


if __name__ == "__main__":
    main()
