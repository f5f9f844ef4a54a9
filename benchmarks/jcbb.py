"""JCBB on 20 observations x 100 candidate landmarks: time, nodes visited, and the size of the search it replaces.

Two worlds: "spread" (100 landmarks over 40 x 40 m around the robot, ~4 m apart) and "dense" (100 landmarks over
14 x 14 m, ~1.4 m apart, so most observations have several individually compatible candidates). The belief has a
pose error drawn from P (0.3 m, 0.05 rad) and landmark errors of 0.05 m; 18 observations come from landmarks in view
and 2 are clutter. "exhaustive" is the number of nodes of the interpretation tree that an exhaustive search over
individually compatible, mutually exclusive pairings walks (every partial hypothesis over the observations in
order), counted exactly per connected component; "(L+1)^K" is the textbook tree without gating.

Run: ``.venv/bin/python benchmarks/jcbb.py``. Prints a table, the node-count ratio, and a log-log fit of time
against the number of observations.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from slam2d.association import AssociationConfig, associate, candidates_from_belief
from slam2d.association.gating import build_problem
from slam2d.log import Observations
from slam2d.models.sensors import range_bearing

R = np.diag([0.1**2, 0.02**2])


def make_problem(rng: np.random.Generator, n_obs: int, n_lm: int, half_width_m: float):
    lm = rng.uniform(-half_width_m, half_width_m, size=(n_lm, 2))
    pose = np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    p = np.diag([0.3**2, 0.3**2, 0.05**2])
    dim = 3 + 2 * n_lm
    cov = np.zeros((dim, dim))
    cov[:3, :3] = p
    cov[3:, 3:] = 0.05**2 * np.eye(2 * n_lm)
    err = rng.multivariate_normal(np.zeros(dim), cov)
    cands = candidates_from_belief(pose + err[:3], lm + err[3:].reshape(-1, 2), np.arange(n_lm), cov, R)
    n_clutter = min(2, n_obs // 5)
    seen = rng.choice(np.argsort(np.hypot(lm[:, 0], lm[:, 1]))[:40], size=n_obs - n_clutter, replace=False)
    z = range_bearing(pose, lm[seen]) + rng.normal(0, [0.1, 0.02], size=(len(seen), 2))
    zc = np.column_stack([rng.uniform(1, 8, n_clutter), rng.uniform(-np.pi, np.pi, n_clutter)])
    z = np.vstack([z, zc])
    ids = np.concatenate([seen, np.full(n_clutter, -1)])
    return Observations(np.abs(z[:, 0]), np.angle(np.exp(1j * z[:, 1])), ids.astype(np.int64)), cands


def exhaustive_nodes(ic: np.ndarray) -> float:
    """Nodes of the interpretation tree over the rows with a compatible candidate (fewest candidates first, as JCBB
    orders them at the root): at depth d, every matching of the first d rows. Exact per connected component."""
    counts = ic.sum(axis=1)
    rows = np.array(sorted(np.flatnonzero(counts > 0), key=lambda i: (counts[i], i)), dtype=int)
    if len(rows) == 0:
        return 1.0
    sub = ic[rows]
    k, a = sub.shape
    dense = np.block([[np.zeros((k, k)), sub], [sub.T, np.zeros((a, a))]])
    _, labels = connected_components(csr_matrix(dense), directed=False)
    per_comp: dict[int, dict[int, int]] = {}  # component -> {bitmask of used candidates: number of hypotheses}
    total = 1.0  # the root
    for d in range(k):
        c = labels[d]
        cols = np.flatnonzero(labels[k:] == c)
        states = per_comp.setdefault(int(c), {0: 1})
        new: dict[int, int] = {}
        opts = [int(np.searchsorted(cols, j)) for j in np.flatnonzero(sub[d])]
        for mask, cnt in states.items():
            new[mask] = new.get(mask, 0) + cnt  # this row unmatched
            for o in opts:
                if not mask >> o & 1:
                    m2 = mask | (1 << o)
                    new[m2] = new.get(m2, 0) + cnt
        if len(new) > 2_000_000:
            return float("inf")
        per_comp[int(c)] = new
        level = 1.0
        for st in per_comp.values():
            level *= float(sum(st.values()))
        total += level
    return total


def run(world: str, n_obs: int, n_lm: int, trials: int, rng: np.random.Generator) -> dict[str, float]:
    half = 20.0 if world == "spread" else 7.0
    cfg = AssociationConfig(method="jcbb")
    times, nodes, exh, ic_per_obs, correct = [], [], [], [], []
    for _ in range(trials):
        obs, cands = make_problem(rng, n_obs, n_lm, half)
        prob = build_problem(obs, cands, cfg)
        t0 = time.process_time()
        res = associate(obs, cands, cfg, rng=rng)
        times.append(time.process_time() - t0)
        nodes.append(res.nodes)
        exh.append(exhaustive_nodes(prob.ic))
        ic_per_obs.append(prob.ic.sum(axis=1).mean())
        m = res.assignment >= 0
        correct.append(np.mean(res.assignment[m] == obs.landmark_id[m]) if m.any() else np.nan)
    return {"world": world, "obs": n_obs, "cands": n_lm, "ms_median": 1e3 * float(np.median(times)),
            "ms_max": 1e3 * float(np.max(times)), "nodes_median": float(np.median(nodes)),
            "nodes_max": float(np.max(nodes)), "exhaustive_median": float(np.median(exh)),
            "ic_per_obs": float(np.mean(ic_per_obs)), "precision": float(np.nanmean(correct))}


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    rng = np.random.default_rng(2024)
    print("JCBB, 100 candidate landmarks; medians over 10 random problems per row; CPU time of one associate() call")
    header = f"{'world':7s} {'obs':>4s} {'IC/obs':>6s} {'cpu ms':>8s} {'cpu max':>8s} {'nodes med':>10s} " \
             f"{'nodes max':>10s} {'exhaustive':>12s} {'ratio':>10s} {'(L+1)^K':>9s} {'prec':>5s}"
    print(header)
    print("-" * len(header))
    rows = []
    for world in ("spread", "dense"):
        for n_obs in (5, 10, 15, 20):
            r = run(world, n_obs, 100, 10, rng)
            rows.append(r)
            ratio = r["exhaustive_median"] / r["nodes_median"]
            print(f"{world:7s} {n_obs:4d} {r['ic_per_obs']:6.2f} {r['ms_median']:8.2f} {r['ms_max']:8.2f} "
                  f"{r['nodes_median']:10.0f} {r['nodes_max']:10.0f} {r['exhaustive_median']:12.3g} "
                  f"{ratio:10.3g} {101.0**n_obs:9.2g} {r['precision']:5.3f}")
    for world in ("spread", "dense"):
        sel = [r for r in rows if r["world"] == world]
        k = np.log([r["obs"] for r in sel])
        slope_t = np.polyfit(k, np.log([r["ms_median"] for r in sel]), 1)[0]
        slope_n = np.polyfit(k, np.log([r["nodes_median"] for r in sel]), 1)[0]
        slope_e = np.polyfit(k, np.log([r["exhaustive_median"] for r in sel]), 1)[0]
        print(f"{world}: log-log slope vs observations: time {slope_t:.2f}, JCBB nodes {slope_n:.2f}, "
              f"exhaustive nodes {slope_e:.2f}")


if __name__ == "__main__":
    main()
