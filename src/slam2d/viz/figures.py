"""Static figures of runs: true vs estimated trajectories and landmark maps."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from slam2d.lab.runner import RunResult
from slam2d.log import Log


def save_runs_figure(log: Log, results: Mapping[str, RunResult], path: str | Path) -> Path:
    """One panel per estimator: walls, true path and landmarks, estimated path and landmarks."""
    n = max(1, len(results))
    fig, axes = plt.subplots(1, n, figsize=(5.0 * n, 4.2), squeeze=False)
    for ax, (name, res) in zip(axes[0], results.items(), strict=False):
        if log.walls is not None:
            for x0, y0, x1, y1 in log.walls:
                ax.plot([x0, x1], [y0, y1], color="0.6", lw=1)
        if log.true_landmarks is not None:
            ax.scatter(*log.true_landmarks.T, marker="+", color="k", s=25, label="true landmarks")
        if log.true_poses is not None:
            ax.plot(*log.true_poses[:, :2].T, color="k", lw=1, label="true path")
        ax.plot(*res.trajectory[:, :2].T, color="tab:red", lw=1, label="estimate")
        if len(res.final.landmarks):
            ax.scatter(*res.final.landmarks.T, marker="o", facecolors="none", edgecolors="tab:red", s=20,
                       label="estimated landmarks")
        ate = res.metrics.get("ate_rmse_m")
        ax.set_title(f"{name}" + (f"  ATE {ate:.2f} m" if ate is not None else ""))
        ax.set_aspect("equal")
    axes[0][0].legend(loc="best", fontsize=7)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def save_breakit_figure(rows: list[dict[str, object]], path: str | Path) -> Path:
    """Grouped bars: ATE per damage condition for each estimator (error bars = std over seeds)."""
    import numpy as np

    estimators = list(dict.fromkeys(str(r["estimator"]) for r in rows))
    conditions = list(dict.fromkeys(str(r["condition"]) for r in rows))
    fig, ax = plt.subplots(figsize=(8.0, 4.0))
    width = 0.8 / max(1, len(conditions))
    for k, cond in enumerate(conditions):
        vals = [next(float(r["ate_mean_m"]) for r in rows if r["estimator"] == e and r["condition"] == cond)  # type: ignore[arg-type]
                for e in estimators]
        errs = [next(float(r["ate_std_m"]) for r in rows if r["estimator"] == e and r["condition"] == cond)  # type: ignore[arg-type]
                for e in estimators]
        ax.bar(np.arange(len(estimators)) + k * width, vals, width, yerr=errs, label=cond, capsize=2)
    ax.set_xticks(np.arange(len(estimators)) + 0.4 - width / 2, estimators)
    ax.set_ylabel("ATE (m)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("break-it: what each damage does to each back end")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
