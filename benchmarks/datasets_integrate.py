"""Loader hot path: exact velocity integration (``integrate_velocity``) must scale linearly in the number of
commands; prints times, ratios and the fitted log-log exponent. Also times each staged dataset's loader once."""

from __future__ import annotations

import argparse
import time

import numpy as np

from slam2d.io.datasets import DATASETS, dataset_status, load_dataset
from slam2d.io.datasets._common import integrate_velocity


def best_of(fn, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    rng = np.random.default_rng(0)
    sizes = [40_000, 160_000, 640_000]
    secs = []
    for m in sizes:
        t = np.cumsum(rng.uniform(0.005, 0.02, m))
        v, w = rng.uniform(0, 1, m), rng.uniform(-1, 1, m)
        q = np.linspace(t[0], t[-1], m // 10)
        secs.append(best_of(lambda t=t, v=v, w=w, q=q: integrate_velocity(t, v, w, q)))
        print(f"integrate_velocity M={m:>7d}: {secs[-1] * 1e3:8.2f} ms  (ratio to previous "
              f"{secs[-1] / secs[-2] if len(secs) > 1 else float('nan'):.2f}, size ratio 4)")
    slope = np.polyfit(np.log(sizes), np.log(secs), 1)[0]
    print(f"fitted exponent (time ~ M^k): k = {slope:.2f} (linear is 1)")
    for name in DATASETS:
        _, missing = dataset_status(name)
        if missing:
            print(f"{name}: not present, skipped")
            continue
        sec = best_of(lambda name=name: load_dataset(name), repeats=1)
        print(f"load_dataset({name!r}): {sec:.2f} s")


if __name__ == "__main__":
    main()
