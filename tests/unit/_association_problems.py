"""Random association problems with a known truth, shared by the association tests (not a test module)."""

from __future__ import annotations

import numpy as np

from slam2d.association import Candidates
from slam2d.association.predict import candidates_from_belief
from slam2d.log import Observations
from slam2d.models.sensors import range_bearing

R = np.diag([0.1**2, 0.02**2])


def random_problem(rng: np.random.Generator, max_obs: int = 7, max_cand: int = 10,
                   spacing_m: float | None = None) -> tuple[Observations, Candidates]:
    """A robot with an uncertain pose, L mapped landmarks (some close together), K observations that mix mapped
    landmarks, unmapped ones and clutter. ``Observations.landmark_id`` holds the truth (-1 for clutter)."""
    n_cand = int(rng.integers(0, max_cand + 1))
    n_unmapped = int(rng.integers(0, 3))
    spacing = float(spacing_m if spacing_m is not None else rng.uniform(0.2, 2.0))
    n_all = n_cand + n_unmapped
    centres = rng.uniform(-6, 6, size=(max(1, n_all // 3 + 1), 2))
    lm = centres[rng.integers(0, len(centres), n_all)] + rng.normal(0, spacing, size=(n_all, 2))
    ids = rng.permutation(100)[:n_all]
    pose = np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    p_std = np.array([rng.uniform(0.02, 0.4), rng.uniform(0.02, 0.4), rng.uniform(0.005, 0.08)])
    corr = rng.uniform(-0.5, 0.5)
    p = np.diag(p_std**2)
    p[0, 1] = p[1, 0] = corr * p_std[0] * p_std[1]
    lm_std = rng.uniform(0.01, 0.1)
    dim = 3 + 2 * n_cand
    cov = np.zeros((dim, dim))
    cov[:3, :3] = p
    cov[3:, 3:] = lm_std**2 * np.eye(2 * n_cand)
    g = rng.normal(0, 0.03, size=(dim, 2))  # a little shared correlation, as in EKF-SLAM
    cov += g @ g.T
    err = rng.multivariate_normal(np.zeros(dim), cov)
    belief_pose = pose + err[:3]
    belief_lm = lm[:n_cand] + err[3:].reshape(n_cand, 2)
    cands = candidates_from_belief(belief_pose, belief_lm, ids[:n_cand], cov, R)
    seen = rng.random(n_all) < 0.8
    z_true = range_bearing(pose, lm[seen]).reshape(-1, 2)
    z = z_true + rng.normal(0, [0.1, 0.02], size=z_true.shape)
    n_clutter = int(rng.integers(0, 2))
    zc = np.column_stack([rng.uniform(0.5, 9, n_clutter), rng.uniform(-np.pi, np.pi, n_clutter)])
    z_all = np.vstack([z, zc])
    true_ids = np.concatenate([ids[seen], np.full(n_clutter, -1)]).astype(np.int64)
    perm = rng.permutation(len(z_all))[:max_obs]
    z_all, true_ids = z_all[perm], true_ids[perm]
    z_all[:, 0] = np.abs(z_all[:, 0])
    return Observations(z_all[:, 0], np.angle(np.exp(1j * z_all[:, 1])), true_ids), cands
