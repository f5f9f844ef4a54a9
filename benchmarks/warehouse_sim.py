"""Cost of simulating the challenge warehouse, and of saving/loading maps.

Prints: segment counts; per-scan cost of the dense caster (every beam x every segment), the dense caster on the
range-culled segments, and the culled caster (pairs in each segment's arc) that the simulator uses; the full
simulator step (30 Hz lidar, 20 forklifts, landmarks, floor markers); and map save/load times and file size.

Run: OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/warehouse_sim.py
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slam2d.config import with_overrides
from slam2d.maps.store import MapStore, snapshot_from_truth
from slam2d.models.lidar import cast_rays
from slam2d.sim import ScenarioConfig, Simulator, simulate
from slam2d.sim.raycast import cast_rays_culled


def per_call_ms(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """Median and 95th percentile of ``repeat`` calls, in ms."""
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    a = np.array(t) * 1e3
    return float(np.median(a)), float(np.percentile(a, 95))


def current_rss_mib() -> float:
    """Resident set size now (Linux /proc; the peak from getrusage would hide a flat curve after a big step)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    cfg = with_overrides(ScenarioConfig(name="warehouse-challenge"), {"floor_markers": "true"})
    sim = Simulator(cfg, seed=0)
    lidar = sim.config.lidar
    angles = lidar.angles()
    world = sim.world
    rng = np.random.default_rng(0)
    print(f"warehouse-challenge: {len(world.walls)} static segments (walls, panels, uprights, pallets), "
          f"{len(world.moving)} forklifts, {len(world.landmarks)} uprights, {len(world.floor_markers)} floor markers; "
          f"lidar {lidar.beams} beams, {lidar.max_range_m} m, dt {sim.config.dt_s:.4f} s")
    poses = [np.array([rng.uniform(2, 98), rng.choice(sim.config.warehouse.road_centres_y()),
                       rng.uniform(-np.pi, np.pi)]) for _ in range(40)]
    it = iter(range(10**9))

    def pose() -> np.ndarray:
        return poses[next(it) % len(poses)]

    all_segs = world.segments_at(5.0)
    near_counts = [len(world.segments_near(5.0, p[:2], lidar.max_range_m)) for p in poses]
    print(f"segments within {lidar.max_range_m} m of the lidar: median {int(np.median(near_counts))} "
          f"of {len(all_segs)}")
    rows = [
        ("dense, all segments", lambda: cast_rays(pose(), angles, all_segs, lidar.max_range_m), 10),
        ("dense, range-culled", lambda: (lambda p: cast_rays(p, angles, world.segments_near(5.0, p[:2], 30.0),
                                                             30.0))(pose()), 20),
        ("culled caster, range-culled (used)", lambda: (lambda p: cast_rays_culled(
            p, angles, world.segments_near(5.0, p[:2], 30.0), 30.0))(pose()), 200),
    ]
    for name, fn, rep in rows:
        med, p95 = per_call_ms(fn, rep)
        print(f"  per scan: {name:38s} median {med:7.2f} ms  p95 {p95:7.2f} ms")
    med, p95 = per_call_ms(lambda: world.segments_at(5.0), 200)
    print(f"  placing 20 forklifts (segments_at): median {med:.3f} ms")

    steps = 900
    t0 = time.perf_counter()
    log = simulate(with_overrides(cfg, {"steps": steps}), seed=0)
    dt = time.perf_counter() - t0
    print(f"simulate {steps} steps (30 s at 30 Hz, lidar every step, markers on): {dt:.2f} s = "
          f"{1e3 * dt / steps:.2f} ms per step ({steps * float(sim.config.dt_s) / dt:.1f}x real time)")

    # streaming (record=False), as a long shift would run: resident memory must not grow with the steps
    live = Simulator(cfg, seed=1, record=False)
    driver = live.driver()
    rss = []
    t0 = time.perf_counter()
    for i in range(1, 6001):
        live.step(*driver.command(live.pose, None))
        if i % 1500 == 0:
            rss.append(current_rss_mib())
    dt = time.perf_counter() - t0
    print(f"streaming 6000 steps (200 s simulated): {1e3 * dt / 6000:.2f} ms per step; RSS after each 1500 "
          f"steps: {', '.join(f'{r:.0f}' for r in rss)} MiB")

    small = simulate("warehouse", seed=0)
    t0 = time.perf_counter()
    snap = snapshot_from_truth(small)
    build = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "w.db"
        med_w, _ = per_call_ms(lambda: MapStore.write(path, snap), 5)
        med_r, _ = per_call_ms(lambda: MapStore.read(path), 5)
        size = os.path.getsize(path)
        big = snapshot_from_truth(log)
        bpath = Path(d) / "big.db"
        med_bw, _ = per_call_ms(lambda: MapStore.write(bpath, big), 3)
        med_br, _ = per_call_ms(lambda: MapStore.read(bpath), 3)
        bsize = os.path.getsize(bpath)
    c, bc = snap.counts(), big.counts()
    print(f"map of 'warehouse' (600 steps): {c['keyframes']} keyframes x {c['beams']} beams, "
          f"{c['occupancy_cells']} cells; build {build:.2f} s, write {med_w:.1f} ms, read {med_r:.1f} ms, "
          f"{size / 1024:.0f} KiB")
    print(f"map of 'warehouse-challenge' (900 steps): {bc['keyframes']} keyframes x {bc['beams']} beams, "
          f"{bc['occupancy_cells']} cells; write {med_bw:.1f} ms, read {med_br:.1f} ms, {bsize / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
