"""Place recognition and loop verification for landmark worlds.

A keyframe is the set of landmark points seen from one pose, in that pose's frame. Its descriptor is a histogram
of the pairwise distances between those points: invariant to where the robot stands and how it is turned, so the
same place seen again gives nearly the same histogram. Candidates are verified geometrically: RANSAC over pairs of
point correspondences (two pairs fix an SE(2) transform), then a weighted least-squares refinement whose inverse
Hessian is the constraint's covariance. A candidate that passes verification can still be a *false* loop (identical
warehouse aisles look the same and align perfectly); :func:`loop_gate` checks it against the trajectory estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.config import check_positive
from slam2d.geometry import se2
from slam2d.geometry.gaussian import chi2_gate
from slam2d.models.sensors import range_bearing_inverse, range_bearing_inverse_jacobians

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class PlaceRecognitionConfig:
    """Loop-closure detection and verification settings."""

    min_points: int = 5
    """a keyframe needs at least this many landmark points to be described or matched."""
    bins: int = 24
    """number of pairwise-distance histogram bins."""
    max_pair_distance_m: float = 16.0
    """pairwise distances beyond this fall in the last bin (about twice the sensor range)."""
    descriptor_max_distance: float = 0.6
    """L1 distance between normalised histograms below which two keyframes are candidates (0..2)."""
    top_k: int = 3
    """how many best candidates are verified."""
    min_separation: int = 20
    """keyframes closer than this in sequence are never loop candidates."""
    inlier_threshold_m: float = 0.6
    """a transformed point within this distance of its partner counts as an inlier (m)."""
    min_inliers: int = 5
    """a verified loop needs at least this many inlier correspondences."""
    ransac_iterations: int = 300
    """number of two-correspondence hypotheses."""
    min_spread_m: float = 1.0
    """inlier points must spread at least this far across their second principal axis (no collinear sets)."""

    def __post_init__(self) -> None:
        check_positive(self, "max_pair_distance_m", "descriptor_max_distance", "inlier_threshold_m")
        for n in ("min_points", "bins", "top_k", "ransac_iterations"):
            if getattr(self, n) < 1:
                raise ValueError(f"PlaceRecognitionConfig.{n} must be >= 1 (got {getattr(self, n)})")
        if self.min_inliers < 3:
            raise ValueError(f"PlaceRecognitionConfig.min_inliers must be >= 3 (got {self.min_inliers})")
        if self.min_separation < 0 or self.min_spread_m < 0:
            raise ValueError("PlaceRecognitionConfig.min_separation and min_spread_m must be >= 0")


def observation_points(z: Array, R: Array) -> tuple[Array, Array]:
    """Range-bearing observations (K,2) -> points in the robot frame (K,2) and their covariances (K,2,2)."""
    origin = np.zeros(3)
    z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    pts = range_bearing_inverse(origin, z)
    _, gz = range_bearing_inverse_jacobians(origin, z)
    return pts, gz @ R @ np.swapaxes(gz, -1, -2)


def constellation_descriptor(points: Array, config: PlaceRecognitionConfig) -> Array | None:
    """Normalised histogram of pairwise point distances, shape (bins,); None with fewer than ``min_points``."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(p) < config.min_points:
        return None
    i, j = np.triu_indices(len(p), k=1)
    d = np.minimum(np.hypot(*(p[i] - p[j]).T), config.max_pair_distance_m * (1 - 1e-9))
    hist = np.bincount((d / config.max_pair_distance_m * config.bins).astype(np.int64), minlength=config.bins)
    return hist / hist.sum()


class KeyframeDatabase:
    """Descriptors of past keyframes, queried all at once (one vectorised distance computation per query)."""

    def __init__(self, config: PlaceRecognitionConfig) -> None:
        self.config = config
        self.keys: list[int] = []
        self._desc = np.zeros((0, config.bins))

    def add(self, key: int, points: Array) -> bool:
        """Store keyframe ``key``'s descriptor; False when it has too few points to be described."""
        d = constellation_descriptor(points, self.config)
        if d is None:
            return False
        self.keys.append(int(key))
        self._desc = np.vstack([self._desc, d])
        return True

    def remove(self, key: int) -> None:
        """Forget a keyframe (e.g. after marginalisation); unknown keys are ignored."""
        if key in self.keys:
            i = self.keys.index(key)
            self.keys.pop(i)
            self._desc = np.delete(self._desc, i, axis=0)

    def query(self, points: Array, current_key: int) -> list[tuple[int, float]]:
        """Up to ``top_k`` (key, descriptor distance) of similar keyframes at least ``min_separation`` keys back."""
        d = constellation_descriptor(points, self.config)
        if d is None or not self.keys:
            return []
        keys = np.asarray(self.keys)
        dist = np.abs(self._desc - d).sum(axis=1)
        ok = (keys <= current_key - self.config.min_separation) & (dist <= self.config.descriptor_max_distance)
        idx = np.flatnonzero(ok)
        idx = idx[np.argsort(dist[idx], kind="stable")][: self.config.top_k]
        return [(int(keys[i]), float(dist[i])) for i in idx]


@dataclass(frozen=True)
class LoopHypothesis:
    """A verified relative pose between keyframes a and b: ``T_a_b`` (3,), covariance (3,3), inlier pairs (M,2)."""

    T_a_b: Array
    cov: Array
    inliers: NDArray[np.int64]
    rmse_m: float


def _two_point_transforms(pa: Array, pb: Array) -> Array:
    """SE(2) transforms mapping each pair of b points onto the matching pair of a points. (H,2,2),(H,2,2)->(H,3)."""
    va = pa[:, 1] - pa[:, 0]
    vb = pb[:, 1] - pb[:, 0]
    th = np.arctan2(va[:, 1], va[:, 0]) - np.arctan2(vb[:, 1], vb[:, 0])
    c, s = np.cos(th), np.sin(th)
    mb = pb.mean(axis=1)
    ma = pa.mean(axis=1)
    t = ma - np.stack([c * mb[:, 0] - s * mb[:, 1], s * mb[:, 0] + c * mb[:, 1]], axis=-1)
    return np.stack([t[:, 0], t[:, 1], se2.wrap_angle(th)], axis=-1)


def _refine(T: Array, pa: Array, ca: Array, pb: Array, cb: Array, iters: int = 6) -> tuple[Array, Array, float]:
    """Weighted Gauss-Newton on r_i = T(pb_i) - pa_i with Sigma_i = ca_i + R cb_i R^T; returns (T, cov, rmse)."""
    h = np.eye(3)
    for _ in range(iters):
        r = se2.transform_points(T, pb) - pa
        jt, _ = se2.transform_points_jacobians(T, pb)
        rot = se2.rotation_matrix(T[2])
        info = np.linalg.inv(ca + rot @ cb @ rot.T)
        h = np.einsum("kji,kjl,klm->im", jt, info, jt)
        g = np.einsum("kji,kjl,kl->i", jt, info, r)
        T = se2.retract(T, -np.linalg.solve(h, g))
    r = se2.transform_points(T, pb) - pa
    return T, np.asarray(np.linalg.inv(h), dtype=np.float64), float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def verify_loop(
    points_a: Array,
    cov_a: Array,
    points_b: Array,
    cov_b: Array,
    config: PlaceRecognitionConfig,
    rng: np.random.Generator,
) -> LoopHypothesis | None:
    """Find ``T_a_b`` with ``T_a_b (+) p_b ~= p_a`` for unknown correspondences, or None when not verifiable.

    Rejected (None): fewer points than the minimal set or ``min_inliers``, too few inliers, or inliers that lie
    on a line (spread below ``min_spread_m`` across the second principal axis: the rotation would be unobservable).
    """
    pa, pb = np.asarray(points_a, dtype=np.float64), np.asarray(points_b, dtype=np.float64)
    if len(pa) < max(2, config.min_inliers) or len(pb) < max(2, config.min_inliers):
        return None
    # candidate correspondences: every pair of a-points against every ordered pair of b-points with the same
    # separation (pose invariant); at most 40 points per side take part in hypothesis generation
    sa = rng.permutation(len(pa))[:40]
    sb = rng.permutation(len(pb))[:40]
    ia = np.stack(np.triu_indices(len(sa), k=1), axis=-1)
    ib = np.stack(np.triu_indices(len(sb), k=1), axis=-1)
    ib = np.vstack([ib, ib[:, ::-1]])
    da = np.hypot(*(pa[sa[ia[:, 0]]] - pa[sa[ia[:, 1]]]).T)
    db = np.hypot(*(pb[sb[ib[:, 0]]] - pb[sb[ib[:, 1]]]).T)
    match = (np.abs(da[:, None] - db[None, :]) < config.inlier_threshold_m) & (da[:, None] > 1.0)
    ka, kb = np.nonzero(match)
    if len(ka) == 0:
        return None
    pick = rng.choice(len(ka), size=min(len(ka), config.ransac_iterations), replace=False)
    ia, ib = sa[ia[ka[pick]]], sb[ib[kb[pick]]]
    hyps = _two_point_transforms(pa[ia], pb[ib])  # (H,3)
    moved = se2.transform_points(hyps[:, None, :], pb[None])  # (H,Kb,2)
    dist = np.hypot(*(moved[:, :, None, :] - pa[None, None]).transpose(3, 0, 1, 2))  # (H,Kb,Ka)
    nearest = dist.min(axis=2)
    score = (nearest < config.inlier_threshold_m).sum(axis=1)
    best = int(np.argmax(score))
    if score[best] < config.min_inliers:
        return None
    T = hyps[best]
    # mutual nearest neighbours under the best hypothesis form the inlier set
    d = dist[best]
    j_of_b = d.argmin(axis=1)
    mutual = d.argmin(axis=0)[j_of_b] == np.arange(len(pb))
    keep = mutual & (d[np.arange(len(pb)), j_of_b] < config.inlier_threshold_m)
    pairs = np.stack([j_of_b[keep], np.flatnonzero(keep)], axis=-1)
    if len(pairs) < config.min_inliers:
        return None
    sel = pa[pairs[:, 0]]
    sv = np.linalg.svd(sel - sel.mean(axis=0), compute_uv=False)
    if sv[-1] / np.sqrt(len(sel)) < config.min_spread_m / 2:
        return None
    ca, cb = np.asarray(cov_a), np.asarray(cov_b)
    T, cov, rmse = _refine(T, pa[pairs[:, 0]], ca[pairs[:, 0]], pb[pairs[:, 1]], cb[pairs[:, 1]])
    # re-associate under the refined transform with a statistical gate, then refine once more
    gate = chi2_gate(0.999, 2)
    for _ in range(2):
        moved_b = se2.transform_points(T, pb)
        j = np.argmin(np.hypot(*(moved_b[:, None] - pa[None]).transpose(2, 0, 1)), axis=1)
        rot = se2.rotation_matrix(T[2])
        r = moved_b - pa[j]
        d2 = np.einsum("ki,kij,kj->k", r, np.linalg.inv(ca[j] + rot @ cb @ rot.T), r)
        keep = d2 < gate
        # one a-point may take only one b-point: keep the closest
        order = np.argsort(d2)
        first = np.zeros(len(pb), dtype=bool)
        _, uniq = np.unique(j[order], return_index=True)
        first[order[uniq]] = True
        keep &= first
        if keep.sum() < config.min_inliers:
            return None
        pairs = np.stack([j[keep], np.flatnonzero(keep)], axis=-1)
        T, cov, rmse = _refine(T, pa[pairs[:, 0]], ca[pairs[:, 0]], pb[pairs[:, 1]], cb[pairs[:, 1]])
    return LoopHypothesis(T, cov, pairs.astype(np.int64), rmse)


def loop_gate(T_meas: Array, cov_meas: Array, T_pred: Array, cov_pred: Array,
              probability: float = 0.999) -> tuple[bool, float]:
    """Is a loop measurement consistent with the current estimate of the same relative pose?

    d2 = e^T (cov_meas + cov_pred)^-1 e with e = local(T_pred, T_meas); accepted when d2 is below the chi-square
    (3 dof) quantile. A place that merely looks the same (another aisle) sits far outside the estimate's
    uncertainty and fails; a true loop after long drift passes because the estimate's uncertainty has grown too.
    """
    e = se2.local(T_pred, T_meas)
    d2 = float(e @ np.linalg.solve(np.asarray(cov_meas) + np.asarray(cov_pred), e))
    return d2 <= chi2_gate(probability, 3), d2
