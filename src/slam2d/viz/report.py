"""An HTML report of a result directory: summary tables and PNG figures (ATE boxplots, NEES with band, scaling).

Reads what ``slam2d sweep`` (``results.jsonl``) and ``slam2d experiment scaling|consistency --out DIR``
(``scaling.json``, ``consistency.json``) wrote; draws only what is present.
"""

from __future__ import annotations

import html
import json
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from slam2d.eval.consistency import chi2_band, monte_carlo_consistency
from slam2d.io.atomic import atomic_write
from slam2d.lab.sweep import ResultStore


def _fmt(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        if not np.isfinite(v):
            return "nan"
        return f"{v:.4g}"
    return str(v)


def _table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(r.get(c)))}</td>" for c in columns) + "</tr>"
                   for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _label(cfg: Mapping[str, Any]) -> str:
    ov = ", ".join(f"{k}={v}" for k, v in sorted(cfg.get("overrides", {}).items()))
    return f"{cfg['estimator']} / {cfg['scenario']}" + (f" ({ov})" if ov else "")


def _metric(recs: Sequence[Mapping[str, Any]], name: str) -> np.ndarray:
    return np.array([r["metrics"][name] for r in recs
                     if r.get("status") == "ok" and r["metrics"].get(name) is not None], dtype=np.float64)


def _save(fig: Any, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path.name


def _ate_boxplot(groups: Mapping[str, Sequence[Mapping[str, Any]]], out: Path) -> str | None:
    data = [(label, _metric(recs, "ate_rmse_m")) for label, recs in groups.items()]
    data = [(label, v) for label, v in data if v.size]
    if not data:
        return None
    longest = max(len(label) for label, _ in data)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.1 * len(data) + 0.06 * longest + 2), 4.0 + 0.05 * longest))
    ax.boxplot([v for _, v in data], showmeans=True)
    ax.set_xticks(range(1, len(data) + 1), [label for label, _ in data], rotation=30, ha="right", fontsize=7)
    ax.set_ylabel("ATE RMSE (m)")
    ax.set_title("ATE per configuration (one point per seed)")
    return _save(fig, out / "ate_boxplot.png")


def _nees_series(groups: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for label, recs in groups.items():
        series = [r["metrics"].get("pose_nees") for r in recs if r.get("status") == "ok"]
        series = [s for s in series if s]
        if len(series) < 2 or len({len(s) for s in series}) != 1:
            continue
        out[label] = np.array([[np.nan if v is None else v for v in s] for s in series], dtype=np.float64)
    return out


def _nees_figure(series: Mapping[str, np.ndarray], out: Path, name: str, probability: float = 0.95) -> str | None:
    if not series:
        return None
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for i, (label, vals) in enumerate(series.items()):
        summ = monte_carlo_consistency(vals, dof=3, probability=probability)
        color = f"C{i % 10}"
        ax.plot(np.arange(1, summ.mean.size + 1), summ.mean, color=color, lw=1,
                label=f"{label} ({100 * summ.fraction_inside:.0f} % inside)")
        ax.axhspan(summ.band.low, summ.band.high, color=color, alpha=0.08)
        ax.axhline(summ.band.low, color=color, ls=":", lw=0.8)
        ax.axhline(summ.band.high, color=color, ls=":", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("mean pose NEES (3 dof)")
    ax.set_title(f"pose NEES over seeds with the {100 * probability:.0f} % chi-square band (dotted)")
    ax.legend(fontsize=7)
    return _save(fig, out / name)


def _scaling_figure(scaling: Mapping[str, Any], out: Path) -> str | None:
    rows = scaling.get("rows", [])
    if not rows:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.0))
    by: dict[str, list[Mapping[str, Any]]] = defaultdict(list)
    for r in rows:
        by[r["estimator"]].append(r)
    for i, (name, rs) in enumerate(sorted(by.items())):
        fit = scaling.get("fits", {}).get(name, {})
        claim = fit.get("claim_exponent")
        for ax, key, slope, end in ((axes[0], "mapped", fit.get("slope_vs_mapped"), fit.get("end_slope_vs_mapped")),
                                    (axes[1], "landmarks", fit.get("slope_vs_landmarks"), None)):
            x = np.array([r[key] for r in rs], dtype=np.float64)
            y = np.array([r["step_ms_median"] for r in rs], dtype=np.float64)
            if not np.any(x > 0):
                continue
            label = f"{name}: slope {_fmt(slope)}" + (f", end {_fmt(end)}" if end is not None else "")
            label += f" (claim {_fmt(claim)})" if claim is not None else ""
            ax.plot(x, y, "o-", color=f"C{i % 10}", label=label)
    for ax, xl in ((axes[0], "landmarks in the estimate (mapped)"), (axes[1], "landmarks in the world (N)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xl)
        ax.set_ylabel("CPU ms per step (median, last third)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="upper left")
    fig.suptitle("scaling on the grid scenario")
    return _save(fig, out / "scaling.png")


def _sweep_scaling(groups: Mapping[str, Sequence[Mapping[str, Any]]], out: Path) -> str | None:
    """Step time vs the ``landmarks`` override when a sweep varied it."""
    pts: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for recs in groups.values():
        ok = [r for r in recs if r.get("status") == "ok"]
        if not ok or "landmarks" not in ok[0]["config"].get("overrides", {}):
            continue
        n = float(ok[0]["config"]["overrides"]["landmarks"])
        pts[ok[0]["config"]["estimator"]].append((n, float(np.mean(_metric(ok, "step_ms_mean")))))
    pts = {k: sorted(v) for k, v in pts.items() if len({x for x, _ in v}) >= 2}
    if not pts:
        return None
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for i, (name, v) in enumerate(sorted(pts.items())):
        ax.plot(*np.array(v).T, "o-", color=f"C{i % 10}", label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("landmarks (override)")
    ax.set_ylabel("mean time per step (ms)")
    ax.legend(fontsize=7)
    return _save(fig, out / "sweep_scaling.png")


CSS = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}table{border-collapse:collapse;"
       "font-size:12px;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 6px;text-align:right}"
       "th{background:#f3f3f3}td:first-child{text-align:left}img{max-width:100%}")



def _read_json(path: Path) -> Any:
    """An experiment's JSON record; a file that is not JSON is named with the parser's line and column."""
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}:{e.lineno}: not JSON ({e.msg}, column {e.colno})") from None

def build_report(directory: str | Path, out: str | Path | None = None) -> Path:
    """Write ``index.html`` and its PNG figures into ``out`` (default ``DIRECTORY/report``); returns the page."""
    d = Path(directory)
    if not d.is_dir():
        raise FileNotFoundError(f"no such result directory: {d}")
    out_dir = Path(out) if out else d / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    parts: list[str] = [f"<h1>slam2d report: {html.escape(str(d))}</h1>"]
    found = False

    records, problems = ResultStore(d).scan()
    if records or problems:
        found = True
        groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for r in records.values():
            groups[_label(r["config"])].append(r)
        groups = dict(sorted(groups.items()))
        rows = []
        for label, recs in groups.items():
            ate = _metric(recs, "ate_rmse_m")
            nees = _metric(recs, "pose_nees_mean")
            rows.append({"configuration": label, "runs": len(recs),
                         "errors": sum(r.get("status") != "ok" for r in recs),
                         "ATE mean (m)": float(ate.mean()) if ate.size else None,
                         "ATE median (m)": float(np.median(ate)) if ate.size else None,
                         "ATE std (m)": float(ate.std()) if ate.size else None,
                         "RPE trans (m)": _mean(_metric(recs, "rpe_trans_rmse_m")),
                         "step ms": _mean(_metric(recs, "step_ms_mean")),
                         "pose NEES mean": _mean(nees),
                         "map RMSE (m)": _mean(_metric(recs, "map_rmse_m"))})
        parts.append(f"<h2>Sweep results ({len(records)} runs)</h2>")
        if problems:
            parts.append(f"<p><b>{len(problems)} unusable store lines</b> (they are re-run by the next "
                         f"<code>slam2d sweep</code>): " + "; ".join(html.escape(f"line {p.line}: {p.reason}")
                                                                   for p in problems[:10]) + "</p>")
        parts.append(_table(rows, list(rows[0]) if rows else ["configuration"]))
        errors = [r for r in records.values() if r.get("status") != "ok"]
        if errors:
            parts.append("<h3>Failed runs</h3>" + _table(
                [{"configuration": _label(r["config"]), "seed": r["seed"], "error": r.get("error")}
                 for r in errors[:50]], ["configuration", "seed", "error"]))
        for img in (_ate_boxplot(groups, out_dir), _nees_figure(_nees_series(groups), out_dir, "sweep_nees.png"),
                    _sweep_scaling(groups, out_dir)):
            if img:
                parts.append(f'<p><img src="{img}" alt="{img}"></p>')

    scaling_path = d / "scaling.json"
    if scaling_path.exists():
        found = True
        sc = _read_json(scaling_path)
        parts.append("<h2>Scaling (grid scenario)</h2>")
        parts.append(_table([{"estimator": k, **v} for k, v in sc.get("fits", {}).items()],
                            ["estimator", "slope_vs_mapped", "end_slope_vs_mapped", "slope_vs_landmarks", "claim",
                             "claim_exponent",
                             "points"]))
        parts.append(_table(sc.get("rows", []), ["estimator", "landmarks", "mapped", "obs_per_step",
                                                 "step_ms_median", "steps", "run_s"]))
        img = _scaling_figure(sc, out_dir)
        if img:
            parts.append(f'<p><img src="{img}" alt="scaling curves"></p>')

    cons_path = d / "consistency.json"
    if cons_path.exists():
        found = True
        cs = _read_json(cons_path)
        parts.append(f"<h2>Consistency ({html.escape(str(cs.get('scenario')))}, {cs.get('seeds')} seeds)</h2>")
        res = cs.get("results", {})
        parts.append(_table([{"estimator": k, "mean NEES": v["overall_mean"], "band low": v["band"][0],
                              "band high": v["band"][1], "fraction inside": v["fraction_inside"]}
                             for k, v in res.items()],
                            ["estimator", "mean NEES", "band low", "band high", "fraction inside"]))
        for k, why in cs.get("skipped", {}).items():
            parts.append(f"<p>skipped {html.escape(k)}: {html.escape(why)}</p>")
        series = {k: np.array([[np.nan if x is None else x for x in v["mean_nees"]]] * 1, dtype=np.float64)
                  for k, v in res.items()}
        img = _consistency_figure(series, cs, out_dir)
        if img:
            parts.append(f'<p><img src="{img}" alt="NEES with band"></p>')

    if not found:
        if (d / "results.jsonl").exists():
            raise ValueError(f"{d / 'results.jsonl'}: holds no runs yet (and {d} has no scaling.json or "
                             "consistency.json to report)")
        raise FileNotFoundError(f"{d} has no results.jsonl, scaling.json or consistency.json to report")
    page = out_dir / "index.html"
    with atomic_write(page) as fh:  # a report being rewritten is never seen half-written
        fh.write("<!doctype html><html><head><meta charset='utf-8'><title>slam2d report</title>"
                 f"<link rel='icon' href='data:,'><style>{CSS}</style></head><body>"
                 + "\n".join(parts) + "</body></html>\n")
    return page


def _mean(v: np.ndarray) -> float | None:
    return float(v.mean()) if v.size else None


def _consistency_figure(series: Mapping[str, np.ndarray], cs: Mapping[str, Any], out: Path) -> str | None:
    """Already-averaged NEES per estimator against the band of ``cs['seeds']`` runs."""
    if not series:
        return None
    prob = float(cs.get("probability", 0.95))
    band = chi2_band(3, int(cs["seeds"]), prob)
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for i, (label, vals) in enumerate(series.items()):
        ax.plot(np.arange(1, vals.shape[1] + 1), vals[0], color=f"C{i % 10}", lw=1,
                label=f"{label} ({100 * band.fraction_inside(vals[0]):.0f} % inside)")
    ax.axhspan(band.low, band.high, color="0.5", alpha=0.15, label=f"{100 * prob:.0f} % band, {cs['seeds']} runs")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("mean pose NEES (3 dof)")
    ax.legend(fontsize=7)
    return _save(fig, out / "consistency_nees.png")
