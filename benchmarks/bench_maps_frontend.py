"""Speed of the maps/front-end kernels: vectorised grid update vs a per-beam loop, and ICP scaling with points.

Prints ratios and fitted log-log exponents (time ~ n^k). Run: .venv/bin/python benchmarks/bench_maps_frontend.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from slam2d.frontend.icp import icp
from slam2d.geometry import se2
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid
from slam2d.models.lidar import cast_rays
from slam2d.sim.world import box_walls

WALLS = np.vstack([box_walls(0, 0, 20, 14), box_walls(9, 6, 11, 8)])


def per_beam_update(grid: OccupancyGrid, pose: np.ndarray, r: np.ndarray, ang: np.ndarray, max_range: float) -> None:
    """The obvious Python loop over beams (and samples) for comparison; same model as OccupancyGrid.update."""
    cfg = grid.config
    step = cfg.sample_step_cells * grid.resolution
    flat = grid.logodds.reshape(-1)
    hits: set[int] = set()
    free: set[int] = set()
    for rr, a in zip(r, ang, strict=True):
        th = pose[2] + a
        is_hit = rr < max_range
        length = rr - 0.5 * step if is_hit else min(max_range, cfg.free_range_cap_m)
        for d in np.arange(0.0, length + 1e-12, step):
            f, ok = grid.cell_index(np.array([[pose[0] + d * np.cos(th), pose[1] + d * np.sin(th)]]))
            if ok[0]:
                free.add(int(f[0]))
        if is_hit:
            f, ok = grid.cell_index(np.array([[pose[0] + rr * np.cos(th), pose[1] + rr * np.sin(th)]]))
            if ok[0]:
                hits.add(int(f[0]))
    for c in free - hits:
        flat[c] = max(flat[c] + cfg.logodds_free, cfg.logodds_min)
    for c in hits:
        flat[c] = min(flat[c] + cfg.logodds_occupied, cfg.logodds_max)


def timeit(fn, repeat: int = 3) -> float:  # type: ignore[no-untyped-def]
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return float(best)


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    pose = np.array([4.0, 3.0, 0.3])
    cfg = OccupancyConfig(resolution_m=0.1)
    print("occupancy update: vectorised vs per-beam loop (one scan, room)")
    beams = [45, 90, 181, 361, 721]
    tv = []
    for b in beams:
        ang = np.linspace(-np.pi / 2, np.pi / 2, b)
        r = cast_rays(pose, ang, WALLS, 12.0)
        g = OccupancyGrid((-1, -1, 21, 15), cfg)
        t_vec = timeit(lambda g=g, r=r, ang=ang: g.update(pose, r, ang, 12.0), 5)
        tv.append(t_vec)
        if b <= 181:
            t_loop = timeit(lambda r=r, ang=ang: per_beam_update(OccupancyGrid((-1, -1, 21, 15), cfg), pose, r, ang,
                                                                  12.0), 1)
            print(f"  beams={b:4d}  vectorised {1e3 * t_vec:7.2f} ms   loop {1e3 * t_loop:8.1f} ms   "
                  f"ratio {t_loop / t_vec:6.0f}x")
        else:
            print(f"  beams={b:4d}  vectorised {1e3 * t_vec:7.2f} ms")
    k = np.polyfit(np.log(beams), np.log(tv), 1)[0]
    print(f"  fitted exponent time ~ beams^{k:.2f} (the samples grow linearly with beams; cache effects add a little)")

    print("ICP (point-to-line) time vs points")
    rng = np.random.default_rng(0)
    ns = [90, 180, 360, 720, 1440]
    ti = []
    for n in ns:
        ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
        r = cast_rays(np.array([6.0, 5.0, 0.2]), ang, WALLS, 30.0)
        tgt = np.c_[r * np.cos(ang), r * np.sin(ang)]
        src = se2.inverse_transform_points([0.2, -0.1, 0.1], tgt) + rng.normal(0, 0.01, tgt.shape)
        t = timeit(lambda src=src, tgt=tgt: icp(src, tgt), 3)
        ti.append(t)
        print(f"  points={n:5d}  {1e3 * t:7.2f} ms")
    k = np.polyfit(np.log(ns), np.log(ti), 1)[0]
    print(f"  fitted exponent time ~ points^{k:.2f} (KD-tree matching: expected ~1, n log n)")


if __name__ == "__main__":
    main()
