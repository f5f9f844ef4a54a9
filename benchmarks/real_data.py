"""Every back end on the staged real datasets: ATE (vs motion capture, or GPS for Victoria Park), map error against
surveyed landmarks where they exist, runtime; a markdown table on stdout and one figure per dataset in docs/.

Run: python benchmarks/real_data.py [--quick] [--only DATASET]
(needs ../shared/datasets; --quick: first 3000 steps of each log)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import slam2d
from slam2d.eval.gps import gps_ate
from slam2d.eval.mapping import map_error
from slam2d.io.datasets import load_dataset
from slam2d.lab.victoria_reference import compare_with_processed_graph

DOCS = Path(__file__).resolve().parents[1] / "docs"

PLAN = [
    # (dataset, robot, estimator, overrides)
    *[("mrclam", r, e, o) for r in range(1, 6) for e, o in [
        ("dead-reckoning", {}), ("ekf", {"association.method": "known"}),
        ("ekf", {"association.method": "mahalanobis"}), ("ekf", {"association.method": "jcbb"}),
        ("fastslam2", {"association.method": "known"}),
        ("fastslam", {"association.method": "mahalanobis", "particles": "300"}),
        ("fastslam2", {"association.method": "mahalanobis"}),
        ("graph", {"association.method": "known", "optimize_every": "50"}),
        ("graph", {"association.method": "mahalanobis", "optimize_every": "50"})]],
    ("victoria-park", 1, "dead-reckoning", {}),
    *[("victoria-park", 1, e, {"association.method": m}) for e, m in [
        ("ekf", "mahalanobis"), ("ekf", "jcbb"), ("fastslam", "mahalanobis"), ("fastslam2", "mahalanobis"),
        ("graph", "mahalanobis")]],
    *[(p, 1, e, {}) for p in ("plaza1", "plaza2") for e in ("dead-reckoning", "range-only-ekf", "range-only-graph")],
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="first 3000 steps of each log")
    ap.add_argument("--only", metavar="DATASET", help="run one dataset (mrclam, victoria-park, plaza1, plaza2)")
    args = ap.parse_args()
    names = list(dict.fromkeys(name for name, *_ in PLAN))
    if args.only and args.only not in names:
        ap.error(f"--only: unknown dataset {args.only!r}; one of {', '.join(names)}")
    rows, trajs, vp_rows = [], {}, []
    skipped: set[tuple[str, int]] = set()  # (dataset, robot) that failed to load: said once, not per estimator
    for name, robot, est, over in PLAN:
        if (args.only and name != args.only) or (name, robot) in skipped:
            continue
        try:
            log = load_dataset(name, None, robot, max_steps=3000 if args.quick else None)
        except (FileNotFoundError, ValueError) as e:
            print(f"skip {name}: {e}", file=sys.stderr)
            skipped.add((name, robot))
            continue
        t0 = time.process_time()
        res, rec = slam2d.run_named(est, log=log, seed=0, overrides=over)
        cpu = time.process_time() - t0
        row = {"dataset": name if name != "mrclam" else f"mrclam-7 robot {robot}",
               "estimator": est + (f" ({over['association.method']})" if "association.method" in over else "")
               + (f" M={over['particles']}" if "particles" in over else ""),
               "ate_m": rec.get("ate_rmse_m", float("nan")), "landmarks": rec["landmarks_estimated"],
               "cpu_s": cpu}
        if log.true_poses is None and log.gps_step is not None:
            row["ate_m"] = gps_ate(res.trajectory, log).rmse_m
        if name == "victoria-park" and est != "dead-reckoning" and not args.quick:
            ref = compare_with_processed_graph(log, res.trajectory, res.final.landmarks)
            vp_rows.append((row["estimator"], ref))
        if log.true_landmarks is not None and len(res.final.landmarks) and log.true_poses is not None:
            a = slam2d.ate(res.trajectory, log.true_poses)
            row["map_rmse_m"] = map_error(res.final.landmarks, log.true_landmarks, alignment=a.alignment,
                                          max_distance_m=5.0).rmse_m
        rows.append(row)
        trajs.setdefault(row["dataset"], (log, {}))[1][row["estimator"]] = res
        print(row, file=sys.stderr, flush=True)
    print("| dataset | estimator | ATE (m) | map RMSE (m) | landmarks | CPU (s) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        map_rmse = f"{r['map_rmse_m']:.3f}" if "map_rmse_m" in r else "–"  # no surveyed landmarks, or no map
        print(f"| {r['dataset']} | {r['estimator']} | {r['ate_m']:.3f} | {map_rmse} | {r['landmarks']} | "
              f"{r['cpu_s']:.1f} |")
    if vp_rows:
        print("\nVictoria Park: the processed graph (victoriaPark.txt) solved from each raw-data estimate (LM; from "
              "its odometry chain LM stops at chi2 503276, dog leg at 250028)\n")
        print("| estimator | chi2 start | chi2 optimum | trajectory vs optimum, median / RMSE (m) | "
              "landmarks matched (of 151, < 5 m), median (m) | optimum's GPS ATE (m) |")
        print("|---|---|---|---|---|---|")
        for label, ref in vp_rows:
            e, m = ref.trajectory_vs_optimum_m, ref.map_vs_optimum
            print(f"| {label} | {ref.chi2_initial:.0f} | {ref.chi2_final:.2f} | {np.median(e):.2f} / "
                  f"{np.sqrt(np.mean(e**2)):.2f} | {m.matched}, {np.median(m.errors_m):.2f} | "
                  f"{ref.optimum_gps_ate_m:.2f} |")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return 0
    DOCS.mkdir(exist_ok=True)
    for ds, (log, results) in trajs.items():
        if ds.startswith("mrclam") and not ds.endswith("robot 1"):
            continue
        fig, ax = plt.subplots(figsize=(7, 6))
        if log.true_poses is not None:
            ax.plot(*log.true_poses[:, :2].T, "k", lw=1, label="ground truth")
        elif log.gps_xy is not None:
            ax.plot(*log.gps_xy.T, "k.", ms=1, label="GPS")
        if log.true_landmarks is not None:
            ax.plot(*log.true_landmarks.T, "k+", ms=8, label="surveyed landmarks")
        for label, res in results.items():
            traj = res.trajectory
            if log.true_poses is not None:
                align = slam2d.ate(res.trajectory, log.true_poses).alignment
            else:
                align = gps_ate(res.trajectory, log).alignment
            traj = slam2d.geometry.compose(align, traj)
            (line,) = ax.plot(*traj[:, :2].T, lw=0.8, label=label)
            if log.true_landmarks is None and label == "ekf (mahalanobis)" and len(res.final.landmarks):
                lm = slam2d.geometry.transform_points(align, res.final.landmarks)
                ax.plot(*lm.T, "+", color=line.get_color(), ms=3, label=f"{label} map")
        ax.set_aspect("equal")
        ax.legend(fontsize=7)
        ax.set_title(ds)
        fig.tight_layout()
        out = DOCS / f"real_{ds.split()[0]}.png"
        fig.savefig(out, dpi=90)
        plt.close(fig)
        print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
