"""Do the relations files agree with the raw laser data? A check that uses no SLAM estimate.

    python benchmarks/lidar_relations_check.py

For every relation (short ones, |t2 - t1| < 2 s, where the two scans see nearly the same scene, and long ones,
which close loops) the raw scan at t2 is moved into the frame of the scan at t1 by the relation itself, and we
measure how well the two raw scans then overlap: the fraction of t2's points within 10 cm of a t1 point
(``inliers``). A correct relation gives the overlap of two scans taken at nearly the same place; a wrong one does
not. For the short ones the same is measured with the logged odometry's relative pose instead of the relation (a
reference that drifts but is locally decent). Also counted: relations whose (x, y) equals the logged odometry's
relative translation to 5 decimals (a relation copied from odometry).

For the relations under 1 s apart, the translation error (as in the relation metric) of two estimates that use no
trajectory: the logged odometry's relative pose, and a direct point-to-line ICP of the two raw scans from that
guess (the lidar back end's tracking settings). The second says how well the file's short relations agree with
the scans themselves: a SLAM estimate scored on them is compared with it in the README.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree

from slam2d.eval.relations import match_stamps, read_relations
from slam2d.frontend.icp import icp
from slam2d.geometry import se2
from slam2d.graph.lidar_config import LidarSLAMConfig
from slam2d.io.carmen import read_carmen, relations_beside, resolve_carmen


def points(r: np.ndarray, a: np.ndarray, max_range: float = 25.0) -> np.ndarray:
    ok = np.isfinite(r) & (r > 0.05) & (r < max_range)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=-1)


def inliers(p1: np.ndarray, p2: np.ndarray, t: np.ndarray, tol: float = 0.1) -> float:
    d, _ = cKDTree(p1).query(se2.transform_points(t, p2), distance_upper_bound=tol)
    return float(np.mean(np.isfinite(d))) if len(d) else 0.0


def check(name: str) -> None:
    path = resolve_carmen(name)
    c = read_carmen(path)
    rel_path = relations_beside(path)
    if rel_path is None:
        print(f"{name}: no relations file")
        return
    rel = read_relations(rel_path)
    idx, ok = match_stamps(c.stamps_s, rel.stamps, 1e-3)
    short = ok.all(axis=1) & (np.abs(rel.stamps[:, 1] - rel.stamps[:, 0]) < 2.0)
    i1, i2 = idx[short, 0], idx[short, 1]
    odo = se2.between(c.poses[i1], c.poses[i2])
    z = rel.rel[short]
    copied = np.all(np.abs(np.round(z[:, :2], 5) - np.round(odo[:, :2], 5)) < 1.5e-5, axis=1)
    by_rel = np.array([inliers(points(c.ranges_m[a], c.angles_rad), points(c.ranges_m[b], c.angles_rad), t)
                       for a, b, t in zip(i1, i2, z, strict=True)])
    by_odo = np.array([inliers(points(c.ranges_m[a], c.angles_rad), points(c.ranges_m[b], c.angles_rad), t)
                       for a, b, t in zip(i1, i2, odo, strict=True)])
    yaw_gap = np.degrees(np.abs(np.angle(np.exp(1j * (z[:, 2] - odo[:, 2])))))
    print(f"{name:10s} short relations {short.sum():4d} | (x,y) = odometry: {copied.sum():4d} | "
          f"scan inliers under the relation: median {np.median(by_rel):.2f} (p10 {np.percentile(by_rel, 10):.2f}) | "
          f"under odometry: median {np.median(by_odo):.2f} | relation worse than odometry by > 0.2: "
          f"{int(np.sum(by_rel < by_odo - 0.2))}")
    long = ok.all(axis=1) & ~short
    by_long = np.array([inliers(points(c.ranges_m[a], c.angles_rad), points(c.ranges_m[b], c.angles_rad), t)
                        for a, b, t in zip(idx[long, 0], idx[long, 1], rel.rel[long], strict=True)])
    if len(by_long):
        print(f"{'':10s} long relations {long.sum():4d}: scan inliers under the relation median "
              f"{np.median(by_long):.2f} (p10 {np.percentile(by_long, 10):.2f}); "
              f"below 0.3: {int(np.sum(by_long < 0.3))}")
    sub = np.abs(rel.stamps[short, 1] - rel.stamps[short, 0]) < 1.0
    if sub.any():
        cfg = LidarSLAMConfig()

        def scan(i: int) -> np.ndarray:
            return points(c.ranges_m[i], c.angles_rad, cfg.max_range_m)

        pair = np.array([icp(scan(b), scan(a), initial=t, config=cfg.icp).transform
                         for a, b, t in zip(i1[sub], i2[sub], odo[sub], strict=True)])
        e_pair = np.hypot(*(pair[:, :2] - z[sub, :2]).T)  # the relation metric's translation error
        e_odo = np.hypot(*(odo[sub, :2] - z[sub, :2]).T)
        cs = copied[sub]
        split = [float(np.mean(e_pair[m])) if m.any() else float("nan") for m in (cs, ~cs)]
        print(f"{'':10s} under 1 s {sub.sum():4d}: translation error of raw-scan ICP mean {e_pair.mean():.4f} m "
              f"(median {np.median(e_pair):.4f}; the {cs.sum()} copied from odometry {split[0]:.4f}, the others "
              f"{split[1]:.4f}), of odometry mean {e_odo.mean():.4f} m (median {np.median(e_odo):.4f})")
    if copied.any():
        print(f"{'':10s} copied ones: inliers under the relation median {np.median(by_rel[copied]):.2f}, under "
              f"odometry {np.median(by_odo[copied]):.2f}; |yaw(relation) - yaw(odometry)| median "
              f"{np.median(yaw_gap[copied]):.2f} deg (others: {np.median(yaw_gap[~copied]):.2f} deg)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.parse_args()
    names = ("aces", "intel", "fr079", "mit-csail")
    for n in names:  # a missing log is said now, in one line, not as a traceback after the first logs' checks
        try:
            resolve_carmen(n)
        except FileNotFoundError as e:
            ap.error(str(e))
    for n in names:
        check(n)


if __name__ == "__main__":
    main()
